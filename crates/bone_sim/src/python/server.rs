//! `dhg._bone_sim.Server`: the real-time server (engine + Zenoh transport) and the protocol
//! layouts, for `dhg.serve` and `dhg.protocol`.

use std::time::Duration;

use pyo3::prelude::*;
use pyo3::types::{PyDict, PyList};

use super::convert::detached;
use super::errors::IntoPyResult;
use super::session::{config_from_dict, set_flat_fields};
use super::volume::{xray_tuple, PyVolume, Views};
use crate::engine::{EngineConfig, WaitMode};
use crate::error::SimError;
use crate::guidance::{GuidanceMode, GuidanceParams};
use crate::path::PlannedPath;
use crate::protocol::LAYOUTS;
use crate::transport::{Server, ServerConfig};

/// Every configurable number of the server, by its flat key.
fn server_fields<'a>(
    e: &'a mut EngineConfig,
    s: &'a mut ServerConfig,
    g: &'a mut f64,
) -> [(&'static str, &'a mut f64); 6] {
    let GuidanceParams { max_n, max_rate_n_per_s, timeout_s, .. } = &mut e.guidance;
    [
        ("idle_timeout_s", &mut s.idle_timeout_s),
        ("model_timeout_s", &mut s.model_timeout_s),
        ("guidance_gain", g),
        ("guidance.max_n", max_n),
        ("guidance.max_rate_n_per_s", max_rate_n_per_s),
        ("guidance.timeout_s", timeout_s),
    ]
}

/// The real-time server. Build it with `dhg.serve`; this is the native half.
#[pyclass(name = "Server", module = "dhg._bone_sim")]
pub struct PyServer {
    inner: Option<Server>,
}

impl PyServer {
    fn server(&self) -> PyResult<&Server> {
        self.inner.as_ref().ok_or_else(|| SimError::Engine("the server is stopped".into())).py()
    }
}

fn json_to_py(py: Python<'_>, v: &serde_json::Value) -> PyResult<Py<PyAny>> {
    Ok(py.import("json")?.call_method1("loads", (v.to_string(),))?.unbind())
}

#[pymethods]
impl PyServer {
    /// Starts the engine on `volume` with the default path `entry_m` → `target_m` (m) and opens
    /// its Zenoh session from `zenoh_json5`. `server` is a flat dict of the keys of
    /// `dhg.serve.ServerSettings`; `session` a flat `dhg.SessionConfig` dict. `wait` is how the
    /// tick and publisher threads wait: `"sleep"`, or `"spin"` (two cores busy, no wake-up latency).
    /// `guidance_mode` is a new session's guidance mode (`paper`, `corridor`, `brake`, `shaped`);
    /// `corridor_profile` (bin width (m), stiffness per bin (N/m)) its corridor's stiffness along A→B.
    #[new]
    /// `session_owners` names the stations whose sessions (`S` or `S-<anything>`) are capped at
    /// `max_sessions_per_owner` each (0: no cap).
    #[pyo3(signature = (volume, entry_m, target_m, zenoh_json5, prefix="dhg", max_sessions=16, server=None, session=None, wait="sleep", guidance_mode="shaped", corridor_profile=None, session_owners=Vec::new(), max_sessions_per_owner=0))]
    #[allow(clippy::too_many_arguments)]
    fn new(
        py: Python<'_>,
        volume: Bound<'_, PyVolume>,
        entry_m: [f64; 3],
        target_m: [f64; 3],
        zenoh_json5: String,
        prefix: &str,
        max_sessions: usize,
        server: Option<&Bound<'_, PyDict>>,
        session: Option<&Bound<'_, PyDict>>,
        wait: &str,
        guidance_mode: &str,
        corridor_profile: Option<(f64, Vec<f64>)>,
        session_owners: Vec<String>,
        max_sessions_per_owner: usize,
    ) -> PyResult<Self> {
        let path = PlannedPath::new(entry_m.into(), target_m.into()).py()?;
        let mut engine = EngineConfig::new(path);
        engine.max_sessions = max_sessions;
        engine.wait = WaitMode::from_name(wait).py()?;
        engine.default_mode = GuidanceMode::from_name(guidance_mode).py()?;
        if let Some((bin_m, stiffness)) = corridor_profile {
            engine.guidance.corridor_profile_bin_m = bin_m;
            engine.guidance.corridor_profile_n_per_m = stiffness;
            engine.guidance.validate().py()?;
        }
        engine.session = config_from_dict(session)?;
        let owners = crate::transport::registry::Owners { names: session_owners, max_sessions: max_sessions_per_owner };
        let mut cfg =
            ServerConfig { prefix: prefix.to_owned(), idle_timeout_s: 5.0, model_timeout_s: 0.25, zenoh_json5, owners };
        let mut gain = engine.default_gain;
        if let Some(dict) = server {
            set_flat_fields(
                dict,
                "server setting",
                "idle_timeout_s, model_timeout_s, guidance_gain, guidance.max_n, guidance.max_rate_n_per_s, guidance.timeout_s",
                |key, value| {
                    let mut fields = server_fields(&mut engine, &mut cfg, &mut gain);
                    fields.iter_mut().find(|(n, _)| *n == key).map(|(_, slot)| **slot = value).is_some()
                },
            )?;
        }
        engine.default_gain = gain;
        let volume = std::sync::Arc::clone(&volume.get().inner);
        let inner = detached(py, || Server::start(&volume, &engine, cfg)).py()?;
        Ok(Self { inner: Some(inner) })
    }

    /// Health report (dict): sessions, tick lateness quantiles over the last `window_s` s, missed
    /// ticks, refused payloads, model availability and latency.
    #[pyo3(signature = (window_s=10.0))]
    fn health(&self, py: Python<'_>, window_s: f64) -> PyResult<Py<PyAny>> {
        json_to_py(py, &self.server()?.health(window_s))
    }

    /// Ids of the open sessions.
    fn sessions(&self) -> PyResult<Vec<String>> {
        Ok(self.server()?.sessions())
    }

    /// A session's metrics (dict, SI units).
    fn metrics(&self, py: Python<'_>, session_id: &str) -> PyResult<Py<PyAny>> {
        let v = self.server()?.metrics(session_id).py()?;
        json_to_py(py, &v)
    }

    /// Applies a control request (dict with "op") to a session; returns the session info.
    fn control(&self, py: Python<'_>, session_id: &str, request: &Bound<'_, PyDict>) -> PyResult<Py<PyAny>> {
        let text: String = py.import("json")?.call_method1("dumps", (request,))?.extract()?;
        let req: serde_json::Value = serde_json::from_str(&text)
            .map_err(|e| SimError::Payload { message: "control", reason: e.to_string() })
            .py()?;
        let v = self.server()?.control(session_id, &req).py()?;
        json_to_py(py, &v)
    }

    /// The three X-ray views (top, front, side line integrals) of a session's bone as drilled now.
    #[pyo3(signature = (session_id, timeout_s=1.0))]
    fn xray<'py>(&self, py: Python<'py>, session_id: &str, timeout_s: f64) -> PyResult<Views<'py>> {
        let server = self.server()?;
        crate::error::positive("timeout_s", timeout_s).py()?;
        let timeout = Duration::from_secs_f64(timeout_s.min(60.0));
        let p = detached(py, || server.snapshot(session_id, timeout).map(|bone| bone.xray())).py()?;
        Ok(xray_tuple(py, &p))
    }

    /// Stops the engine and closes its Zenoh session (idempotent; waits at most a few ms).
    fn stop(&mut self, py: Python<'_>) {
        if let Some(mut s) = self.inner.take() {
            detached(py, move || s.stop());
        }
    }

    /// Whether the server runs.
    #[getter]
    fn running(&self) -> bool {
        self.inner.is_some()
    }
}

/// Returns `session_id` if it is a valid session id (the engine's rule), else raises
/// `InvalidInputError` saying the rule.
#[pyfunction]
pub(crate) fn check_session_id(session_id: &str) -> PyResult<String> {
    crate::transport::registry::check_id(session_id).map(str::to_owned).py()
}

/// The payload layouts: {name: {"kind", "size", "fields": [(name, type, offset, count, unit)]}}.
#[pyfunction]
pub(crate) fn protocol_layouts(py: Python<'_>) -> PyResult<Bound<'_, PyDict>> {
    let out = PyDict::new(py);
    for l in LAYOUTS {
        let d = PyDict::new(py);
        d.set_item("kind", l.kind)?;
        d.set_item("size", l.size)?;
        let fields: Vec<_> = l.fields.iter().map(|f| (f.name, f.ty, f.offset, f.count, f.unit)).collect();
        d.set_item("fields", PyList::new(py, fields)?)?;
        out.set_item(l.name, d)?;
    }
    Ok(out)
}
