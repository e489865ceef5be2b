//! `dhg._bone_sim.Server`: the real-time server (engine + Zenoh transport) and the protocol
//! layouts, for `dhg.core.server` and `dhg.core.protocol`.

use std::time::Duration;

use pyo3::prelude::*;
use pyo3::types::{PyDict, PyList};

use super::convert::{detached, from_python, json_from_python, to_python};
use super::errors::IntoPyResult;
use super::session::config_from_dict;
use super::volume::{bricks_arrays, xray_tuple, Bricks, PyVolume, Views};
use crate::engine::NewSessionGuidance;
use crate::error::SimError;
use crate::path::PlannedPath;
use crate::protocol::LAYOUTS;
use crate::transport::{Server, ServerSettings};

/// The real-time server. Build it with `dhg.core.server.start_engine`; this is the native half.
#[pyclass(name = "Server", module = "dhg._bone_sim")]
pub struct PyServer {
    inner: Option<Server>,
    guidance: NewSessionGuidance,
}

impl PyServer {
    fn server(&self) -> PyResult<&Server> {
        self.inner.as_ref().ok_or_else(|| SimError::Engine("the server is stopped".into())).py()
    }
}

#[pymethods]
impl PyServer {
    /// Starts the engine on `volume` with the default path `entry_m` → `target_m` (m) and opens
    /// its Zenoh session from `zenoh_json5`. `settings` is a dict of the fields of
    /// `dhg.core.server.ServerSettings` (the core's `ServerSettings`; missing ones take its defaults),
    /// `session` a (nested) `dhg.SessionConfig` dict.
    #[new]
    #[pyo3(signature = (volume, entry_m, target_m, zenoh_json5, prefix="dhg", settings=None, session=None))]
    #[allow(clippy::too_many_arguments)] // pyo3's `py` token is one of them
    fn new(
        py: Python<'_>,
        volume: Bound<'_, PyVolume>,
        entry_m: [f64; 3],
        target_m: [f64; 3],
        zenoh_json5: String,
        prefix: &str,
        settings: Option<&Bound<'_, PyDict>>,
        session: Option<&Bound<'_, PyDict>>,
    ) -> PyResult<Self> {
        let path = PlannedPath::new(entry_m.into(), target_m.into()).py()?;
        let settings: ServerSettings =
            settings.map_or_else(|| Ok(ServerSettings::default()), |d| from_python(d.as_any(), "server settings"))?;
        let (engine, cfg) = settings.configs(path, config_from_dict(session)?, prefix, zenoh_json5).py()?;
        let volume = std::sync::Arc::clone(&volume.get().inner);
        let inner = detached(py, || Server::start(&volume, &engine, cfg)).py()?;
        Ok(Self { inner: Some(inner), guidance: engine.new_session_guidance() })
    }

    /// Health report (dict): sessions, tick lateness quantiles over the last `window_s` s, missed
    /// ticks, refused payloads, model availability and latency.
    #[pyo3(signature = (window_s=10.0))]
    fn health<'py>(&self, py: Python<'py>, window_s: f64) -> PyResult<Bound<'py, PyAny>> {
        to_python(py, &self.server()?.health(window_s))
    }

    /// Ids of the open sessions.
    fn sessions(&self) -> PyResult<Vec<String>> {
        Ok(self.server()?.sessions())
    }

    /// A session's metrics (dict, SI units).
    fn metrics<'py>(&self, py: Python<'py>, session_id: &str) -> PyResult<Bound<'py, PyAny>> {
        let v = self.server()?.metrics(session_id).py()?;
        to_python(py, &v)
    }

    /// Applies a control request (dict with "op") to a session; returns the session info.
    fn control<'py>(
        &self,
        py: Python<'py>,
        session_id: &str,
        request: &Bound<'_, PyDict>,
    ) -> PyResult<Bound<'py, PyAny>> {
        let req = json_from_python(request.as_any(), "control request")?;
        let v = self.server()?.control(session_id, &req).py()?;
        to_python(py, &v)
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

    /// The bricks a session has drilled, as drilled now: origins (n, 3) voxel (i, j, k) and
    /// material (n, 8, 8, 8) u16 [k][j][i] (65535 = full); every other voxel is pristine.
    #[pyo3(signature = (session_id, timeout_s=1.0))]
    fn bricks<'py>(&self, py: Python<'py>, session_id: &str, timeout_s: f64) -> PyResult<Bricks<'py>> {
        let server = self.server()?;
        crate::error::positive("timeout_s", timeout_s).py()?;
        let timeout = Duration::from_secs_f64(timeout_s.min(60.0));
        let bone = detached(py, || server.snapshot(session_id, timeout)).py()?;
        Ok(bricks_arrays(py, &bone))
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

    /// How a new session is guided (dict): `mode`, `gain`, and `params`, the guidance laws every
    /// session runs (the core's `GuidanceParams`, the server's settings applied).
    #[getter]
    fn new_session_guidance<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyAny>> {
        to_python(py, &self.guidance)
    }
}

/// Returns `session_id` if it is a valid session id (the engine's rule), else raises
/// `InvalidInputError` saying the rule.
#[pyfunction]
pub(crate) fn check_session_id(session_id: &str) -> PyResult<String> {
    crate::transport::registry::check_id(session_id).map(str::to_owned).py()
}

/// Raises `InvalidInputError` when Zenoh cannot read the `ZENOH_RUNTIME` environment variable
/// (it would panic at the process's first session); nothing when it is unset or readable.
#[pyfunction]
pub(crate) fn check_zenoh_runtime() -> PyResult<()> {
    crate::transport::check_zenoh_runtime().py()
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

/// The key space (`protocol::keys`): `templates` (name → key with `{prefix}`, `{id}` and, for
/// `server`, `{leaf}` to fill in), `session_leaves`, `server_leaves` and `client_put_leaf`.
#[pyfunction]
pub(crate) fn key_layout(py: Python<'_>) -> PyResult<Bound<'_, PyAny>> {
    use crate::protocol::keys;
    let all = serde_json::json!({
        "templates": keys::layout(),
        "session_leaves": keys::SESSION_LEAVES,
        "server_leaves": keys::SERVER_LEAVES,
        "client_put_leaf": keys::CLIENT_PUT_LEAF,
    });
    to_python(py, &all)
}

/// The JSON schemas of the `metrics` and `health` replies (`transport::replies`).
#[pyfunction]
pub(crate) fn reply_schemas(py: Python<'_>) -> PyResult<Bound<'_, PyAny>> {
    to_python(py, &crate::transport::replies::schemas())
}

/// The core's defaults, the one definition Python's dataclasses read theirs from: `session`
/// (`SessionConfig`, nested), `hu_mapping`, `server` (`ServerSettings`), `guidance`
/// (`GuidanceParams`), `fading` (`FadingParams`), `task_rules` (`TaskRules`).
#[pyfunction]
pub(crate) fn defaults(py: Python<'_>) -> PyResult<Bound<'_, PyAny>> {
    let all = serde_json::json!({
        "session": crate::session::SessionConfig::default(),
        "hu_mapping": crate::volume::material::HuMapping::default(),
        "server": ServerSettings::default(),
        "guidance": crate::guidance::GuidanceParams::default(),
        "fading": crate::guidance::FadingParams::default(),
        "task_rules": crate::skill::TaskRules::default(),
    });
    to_python(py, &all)
}

/// Each control operation with the fields it takes (`ControlRequest`), for the docs' test.
#[pyfunction]
pub(crate) fn control_ops() -> Vec<(String, Vec<String>)> {
    crate::transport::control_fields()
}
