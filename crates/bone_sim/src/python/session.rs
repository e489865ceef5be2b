//! `DrillingSession`: the 1 kHz drilling session, per tick or many ticks per call.

use numpy::ndarray::Array2;
use numpy::{IntoPyArray, PyArray1, PyArray2, PyReadonlyArray2};
use pyo3::prelude::*;
use pyo3::types::PyDict;

use super::convert::{detached, from_python, to_python};
use super::errors::IntoPyResult;
use super::volume::{xray_tuple, PyVolume, Views};
use crate::error::SimError;
use crate::guidance::GuidanceMode;
use crate::path::PlannedPath;
use crate::record::{Record, FEATURE_COUNT};
use crate::session::{DrillingSession, Pose, SessionConfig};

/// Columns of a pose row: x, y, z (m), qw, qx, qy, qz, `drill_on` (> 0.5 = on), `spindle_rpm`.
pub(crate) const POSE_COLUMNS: usize = 9;
/// Columns of a record row: time (s), the nine features, `drill_on` (0/1).
pub(crate) const RECORD_COLUMNS: usize = FEATURE_COUNT + 2;

/// A session's config from a (nested) dict of `dhg.SessionConfig`'s fields; missing fields take
/// the core's defaults, and unless it is given the coupling is as stiff as the device allows.
pub(crate) fn config_from_dict(dict: Option<&Bound<'_, PyDict>>) -> PyResult<SessionConfig> {
    let Some(dict) = dict else { return Ok(SessionConfig::default()) };
    let mut c: SessionConfig = from_python(dict.as_any(), "session config")?;
    if !dict.contains("coupling_stiffness_n_per_m")? {
        c.coupling_stiffness_n_per_m = c.device.max_stiffness_n_per_m;
    }
    Ok(c)
}

fn pose_from_row(row: &[f64]) -> Option<Pose> {
    if row.iter().all(|v| v.is_nan()) {
        return None; // no pose arrived this tick
    }
    Some(Pose::new([row[0], row[1], row[2]], [row[3], row[4], row[5], row[6]], row[7] > 0.5, row[8]))
}

pub(crate) fn record_row(r: &Record) -> [f64; RECORD_COLUMNS] {
    let mut row = [0.0; RECORD_COLUMNS];
    row[0] = r.time_s;
    row[1..=FEATURE_COUNT].copy_from_slice(&r.features);
    row[RECORD_COLUMNS - 1] = f64::from(u8::from(r.drill_on));
    row
}

/// Forces (N, 3) and records (M, 11) of a batch of ticks.
type StepArrays<'py> = (Bound<'py, PyArray2<f64>>, Bound<'py, PyArray2<f64>>);

/// A trainee's drilling session on a shared volume: 1 ms ticks, forces for the device, the
/// 10 Hz record. Build it with `dhg.DrillingSession`; this is the native half.
#[pyclass(name = "DrillingSession", module = "dhg._bone_sim")]
pub struct PySession {
    inner: DrillingSession,
}

impl PySession {
    pub(crate) fn native_mut(&mut self) -> &mut DrillingSession {
        &mut self.inner
    }
}

#[pymethods]
impl PySession {
    /// A session drilling `volume` along the path `entry_m` → `target_m` (m), with an optional
    /// (nested) config dict of `dhg.SessionConfig`'s fields.
    #[new]
    #[pyo3(signature = (volume, entry_m, target_m, config=None))]
    fn new(
        volume: Bound<'_, PyVolume>,
        entry_m: [f64; 3],
        target_m: [f64; 3],
        config: Option<&Bound<'_, PyDict>>,
    ) -> PyResult<Self> {
        let config = config_from_dict(config)?;
        let path = PlannedPath::new(entry_m.into(), target_m.into()).py()?;
        let inner = DrillingSession::new(std::sync::Arc::clone(&volume.get().inner), path, config).py()?;
        Ok(Self { inner })
    }

    /// One tick. `pose` is a 9-value row (see `POSE_COLUMNS`) or None when no pose arrived.
    /// Returns (force (3,) in N, record (11,) or None).
    #[pyo3(signature = (pose=None))]
    fn tick<'py>(
        &mut self,
        py: Python<'py>,
        pose: Option<[f64; POSE_COLUMNS]>,
    ) -> (Bound<'py, PyArray1<f64>>, Option<Bound<'py, PyArray1<f64>>>) {
        let pose = pose.and_then(|row| pose_from_row(&row));
        let out = self.inner.tick(pose.as_ref());
        let force = vec![out.force_n.x, out.force_n.y, out.force_n.z].into_pyarray(py);
        (force, out.record.map(|r| record_row(&r).to_vec().into_pyarray(py)))
    }

    /// Runs one tick per row of `poses` (N, 9) with the GIL released. Returns forces (N, 3) in N
    /// and the records produced (M, 11).
    fn step<'py>(&mut self, py: Python<'py>, poses: PyReadonlyArray2<'_, f64>) -> PyResult<StepArrays<'py>> {
        let view = poses.as_array();
        if view.ncols() != POSE_COLUMNS {
            return Err(SimError::ShapeMismatch {
                what: "poses",
                expected: format!("shape (N, {POSE_COLUMNS})"),
                got: format!("{:?}", view.shape()),
            })
            .py();
        }
        let rows: Vec<[f64; POSE_COLUMNS]> = view.rows().into_iter().map(|r| std::array::from_fn(|c| r[c])).collect();
        let inner = &mut self.inner;
        let (forces, records) = detached(py, move || {
            let mut forces = Vec::with_capacity(rows.len() * 3);
            let mut records = Vec::with_capacity((rows.len() / 100 + 1) * RECORD_COLUMNS);
            for row in &rows {
                let out = inner.tick(pose_from_row(row).as_ref());
                forces.extend_from_slice(out.force_n.as_slice());
                if let Some(r) = out.record {
                    records.extend_from_slice(&record_row(&r));
                }
            }
            (forces, records)
        });
        let n = forces.len() / 3;
        let m = records.len() / RECORD_COLUMNS;
        let internal =
            |e: numpy::ndarray::ShapeError| pyo3::exceptions::PyRuntimeError::new_err(format!("internal: {e}"));
        Ok((
            Array2::from_shape_vec((n, 3), forces).map_err(internal)?.into_pyarray(py),
            Array2::from_shape_vec((m, RECORD_COLUMNS), records).map_err(internal)?.into_pyarray(py),
        ))
    }

    /// What an operator perceives, cheaply, as a tuple: (tip x, y, z (m), depth (m), deviation (m),
    /// temperature (°C), layer id, cutting, breakthroughs, plunging, plunge depth (m)).
    #[allow(clippy::type_complexity)] // a flat tuple is the cheap thing to hand Python per tick
    fn feedback(&self) -> (f64, f64, f64, f64, f64, f64, u8, bool, u32, bool, f64) {
        let s = self.inner.state();
        (
            s.tip_m.x,
            s.tip_m.y,
            s.tip_m.z,
            s.depth_m,
            s.deviation_m,
            s.temperature_c,
            s.layer.id(),
            s.cutting,
            s.breakthroughs,
            s.plunging,
            s.plunge_depth_m,
        )
    }

    /// The guidance share of the last tick's force (N), as a tuple: cheap, for per-tick loops.
    fn guidance_share(&self) -> (f64, f64, f64) {
        let g = self.inner.state().guidance_n;
        (g.x, g.y, g.z)
    }

    /// The current state as a dict (SI units).
    fn state<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyAny>> {
        to_python(py, self.inner.state())
    }

    /// Replaces the planned path (m).
    fn set_path(&mut self, entry_m: [f64; 3], target_m: [f64; 3]) -> PyResult<()> {
        self.inner.set_path(PlannedPath::new(entry_m.into(), target_m.into()).py()?);
        Ok(())
    }

    /// The planned path as (entry (3,), target (3,)) in m.
    fn path(&self) -> ([f64; 3], [f64; 3]) {
        let (a, b) = (self.inner.path().entry_m(), self.inner.path().target_m());
        ([a.x, a.y, a.z], [b.x, b.y, b.z])
    }

    /// Sets the guidance mode (`paper`, `corridor`, `brake`, `shaped`) and gain (0..=4; 0 off).
    fn set_guidance(&mut self, mode: &str, gain: f64) -> PyResult<()> {
        let mode = GuidanceMode::from_name(mode).py()?;
        self.inner.set_guidance(mode, gain).py()
    }

    /// Sets the corridor's stiffness per depth bin of `bin_m` (m) along A→B (N/m, from the
    /// experts' lateral spread); an empty list restores the fixed stiffness.
    fn set_corridor_profile(&mut self, bin_m: f64, stiffness_n_per_m: Vec<f64>) -> PyResult<()> {
        let mut params = self.inner.guide().params().clone();
        params.corridor_profile_bin_m = bin_m;
        params.corridor_profile_n_per_m = stiffness_n_per_m;
        self.inner.set_guidance_params(params).py()
    }

    /// Fades the gain over attempts: the schedule's params as a dict (missing fields take the
    /// core's defaults), or None to stop fading.
    #[pyo3(signature = (params=None))]
    fn set_fading(&mut self, params: Option<&Bound<'_, PyAny>>) -> PyResult<()> {
        let params = params.map(|p| from_python(p, "fading params")).transpose()?;
        self.inner.set_fading(params).py()
    }

    /// The fading schedule (`params`, `attempts`, `assistance`, `gain`, `probe`, `last_error`),
    /// or None.
    fn fading<'py>(&self, py: Python<'py>) -> PyResult<Option<Bound<'py, PyAny>>> {
        self.inner.fading().map(|f| to_python(py, &f.schedule())).transpose()
    }

    /// Every guidance limit and force law (`crate::guidance::GuidanceParams`, SI units).
    fn guidance_params<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyAny>> {
        to_python(py, self.inner.guide().params())
    }

    /// Replaces the guidance limits and force laws: a dict of `guidance_params()`'s fields
    /// (missing ones take the core's defaults).
    fn set_guidance_params(&mut self, params: &Bound<'_, PyAny>) -> PyResult<()> {
        let params: crate::guidance::GuidanceParams = from_python(params, "guidance params")?;
        self.inner.set_guidance_params(params).py()
    }

    /// The guidance (mode, gain).
    fn guidance(&self) -> (&'static str, f64) {
        (self.inner.guide().mode().name(), self.inner.guide().gain())
    }

    /// A model reply: the predicted expert force (N, (3,)). Returns the paper's guidance as
    /// mixed: gain · (predicted − the current force feedback), clamped.
    fn set_prediction<'py>(&mut self, py: Python<'py>, predicted_n: [f64; 3]) -> PyResult<Bound<'py, PyArray1<f64>>> {
        if !predicted_n.iter().all(|v| v.is_finite()) {
            let value = predicted_n.into_iter().find(|v| !v.is_finite()).unwrap_or(f64::NAN);
            return Err(SimError::NonFinite { what: "predicted force (N)", value }).py();
        }
        let g = self.inner.set_prediction(nalgebra::Vector3::from(predicted_n));
        Ok(vec![g.x, g.y, g.z].into_pyarray(py))
    }

    /// The tip depth (m) at which the planning CT shows the burr leaving the first cortex, or None.
    #[getter]
    fn planned_breakthrough_depth_m(&self) -> Option<f64> {
        self.inner.planned_breakthrough_depth_m()
    }

    /// Restores the undrilled bone and a fresh state; with `rest_device`, the device too (zero
    /// force, cold motors), as for a new device.
    #[pyo3(signature = (rest_device=false))]
    fn reset(&mut self, rest_device: bool) {
        if rest_device {
            self.inner.reset_device();
        } else {
            self.inner.reset();
        }
    }

    /// X-ray line integrals of the bone as drilled: (top, front, side).
    fn xray<'py>(&self, py: Python<'py>) -> Views<'py> {
        let bone = self.inner.bone();
        let p = detached(py, || bone.xray());
        xray_tuple(py, &p)
    }

    /// Bytes this session's bone holds beyond the shared volume.
    #[getter]
    fn memory_bytes(&self) -> usize {
        self.inner.bone().memory_bytes()
    }

    /// Drills with `surgeon` (a `SurgeonController`) until the next 10 Hz record (its 11-column
    /// row) or until the surgeon finishes (None). With `guided`, the surgeon reads the guidance
    /// share as its cue.
    #[pyo3(signature = (surgeon, guided=false))]
    fn drive<'py>(
        &mut self,
        py: Python<'py>,
        mut surgeon: PyRefMut<'_, super::surgeon::PySurgeon>,
        guided: bool,
    ) -> Option<Bound<'py, PyArray1<f64>>> {
        super::surgeon::drive(py, self, &mut surgeon, guided)
    }

    /// The configuration in use, as a nested dict of `dhg.SessionConfig`'s fields.
    fn config<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyAny>> {
        to_python(py, self.inner.config())
    }
}
