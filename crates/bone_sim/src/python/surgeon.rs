//! `SurgeonController`: the virtual surgeon's 1 kHz step, and a session drilled by it up to its
//! next record (`DrillingSession.drive`).

use numpy::ndarray::Array2;
use numpy::{IntoPyArray, PyArray1, PyArray2};
use pyo3::prelude::*;

use super::convert::{detached, from_python, to_python};
use super::errors::IntoPyResult;
use super::session::{record_row, PySession, POSE_COLUMNS};
use crate::error::{SimError, SimResult};
use crate::path::PlannedPath;
use crate::record::TICK_S;
use crate::skill::TaskRules;
use crate::surgeon::{self, CueMeaning, Perception, SurgeonController, SurgeonStyle};
use crate::volume::layer::Layer;

/// What the stylus reports, as `DrillingSession.feedback()` gives it: tip x, y, z (m), depth (m),
/// deviation (m), temperature (°C), layer id, cutting, breakthroughs, plunging, plunge depth (m),
/// read as numbers (a flag may come as a bool or an int, a count as an int or a float).
type Feedback = [f64; 11];

/// What the surgeon perceives of `feedback`, checked: every value finite, the layer a known id and
/// the breakthroughs a count (a NaN would otherwise steer the hand to a NaN pose).
fn perception(feedback: &Feedback, force_n: &[f64; 3], cue_n: &[f64; 3]) -> SimResult<Perception> {
    for (what, values) in [("feedback", &feedback[..]), ("force_n (N)", &force_n[..]), ("cue_n (N)", &cue_n[..])] {
        if let Some(bad) = values.iter().find(|v| !v.is_finite()) {
            return Err(SimError::NonFinite { what, value: *bad });
        }
    }
    let id = feedback[6];
    let layer = (id.fract() == 0.0 && (0.0..=f64::from(u8::MAX)).contains(&id))
        .then(|| Layer::from_id(id as u8))
        .flatten()
        .ok_or(SimError::InvalidParameter { name: "feedback layer id", value: id, reason: "must be a layer's id" })?;
    let breakthroughs = feedback[8];
    if breakthroughs < 0.0 || breakthroughs.fract() != 0.0 {
        return Err(SimError::InvalidParameter {
            name: "feedback breakthroughs",
            value: breakthroughs,
            reason: "must be a count",
        });
    }
    Ok(Perception {
        depth_m: feedback[3],
        temperature_c: feedback[5],
        layer,
        breakthroughs: breakthroughs as u32,
        plunge_depth_m: feedback[10],
    })
}

/// The pose rows and forces (N) of a kept attempt, one per tick.
type RawTicks = (Vec<[f64; POSE_COLUMNS]>, Vec<[f64; 3]>);

/// The 1 kHz poses (N, 9) and forces (N, 3) of a kept attempt.
type RawArrays<'py> = (Bound<'py, PyArray2<f64>>, Bound<'py, PyArray2<f64>>);

/// The virtual surgeon (`crate::surgeon`). Build it with `dhg.core.surgeon.SurgeonController`;
/// this is the native half.
#[pyclass(name = "SurgeonController", module = "dhg._bone_sim")]
pub struct PySurgeon {
    pub(crate) inner: SurgeonController,
    /// The attempt's pose rows and forces, when kept.
    pub(crate) raw: Option<RawTicks>,
}

#[pymethods]
impl PySurgeon {
    /// A surgeon of `style` (a dict of `dhg.core.surgeon.SurgeonStyle`'s fields) drilling the path
    /// `entry_m` → `target_m` (m) for at most `max_duration_s`; `seed` fixes its random draws.
    #[new]
    #[pyo3(signature = (entry_m, target_m, style, seed, max_duration_s, breakthrough_depth_m=None, cue_meaning="match", keep_raw=false))]
    #[allow(clippy::too_many_arguments)] // the constructor's keywords, one per fact
    fn new(
        entry_m: [f64; 3],
        target_m: [f64; 3],
        style: &Bound<'_, PyAny>,
        seed: u64,
        max_duration_s: f64,
        breakthrough_depth_m: Option<f64>,
        cue_meaning: &str,
        keep_raw: bool,
    ) -> PyResult<Self> {
        let path = PlannedPath::new(entry_m.into(), target_m.into()).py()?;
        let style: SurgeonStyle = from_python(style, "surgeon style")?;
        let cue = CueMeaning::from_name(cue_meaning).py()?;
        let inner = SurgeonController::new(&path, style, seed, max_duration_s, breakthrough_depth_m, cue).py()?;
        // Room for an attempt as long as the task's rules allow up front; a longer one (up to
        // `surgeon::MAX_ATTEMPT_S`) grows as it goes.
        let room = inner.max_ticks().min((TaskRules::default().max_duration_s / TICK_S) as usize);
        let raw = keep_raw.then(|| (Vec::with_capacity(room), Vec::with_capacity(room)));
        Ok(Self { inner, raw })
    }

    /// One tick: the pose row for what the stylus reports (`feedback`, as
    /// `DrillingSession.feedback()` gives it), the force felt and its guidance share (N), or None
    /// once the surgeon has finished.
    #[pyo3(signature = (feedback, force_n, cue_n=[0.0, 0.0, 0.0]))]
    fn step(
        &mut self,
        feedback: Feedback,
        force_n: [f64; 3],
        cue_n: [f64; 3],
    ) -> PyResult<Option<[f64; POSE_COLUMNS]>> {
        let now = perception(&feedback, &force_n, &cue_n).py()?;
        Ok(self.inner.step(&now, &force_n.into(), &cue_n.into()))
    }

    /// Whether the surgeon has finished (stopped at B, or ran out of time).
    #[getter]
    fn done(&self) -> bool {
        self.inner.done()
    }

    /// `approach`, `align`, `feed`, `stop` or `done`.
    #[getter]
    fn phase(&self) -> &'static str {
        self.inner.phase().name()
    }

    /// Ticks stepped so far.
    #[getter]
    fn ticks(&self) -> usize {
        self.inner.ticks()
    }

    /// The most ticks the attempt may last.
    #[getter]
    fn max_ticks(&self) -> usize {
        self.inner.max_ticks()
    }

    /// Time from drill start to drill stop (s), as far as the attempt has come.
    #[getter]
    fn drilling_s(&self) -> f64 {
        self.inner.drilling_s()
    }

    /// The push the surgeon means to make along A→B (N), before the lean into a cue.
    #[getter]
    fn push_n(&self) -> f64 {
        self.inner.push_n()
    }

    /// The push added in response to the guidance cue (N).
    #[getter]
    fn lean_n(&self) -> f64 {
        self.inner.lean_n()
    }

    /// The deepest plunge seen so far (m).
    #[getter]
    fn max_plunge_m(&self) -> f64 {
        self.inner.max_plunge_m()
    }

    /// How long a vibration was felt in the cue so far (s): the heat cue, or anything read as one.
    #[getter]
    fn buzz_felt_s(&self) -> f64 {
        self.inner.buzz_felt_s()
    }

    /// The attempt's 1 kHz pose rows (N, 9) and forces (N, 3) in N, if kept.
    fn raw<'py>(&self, py: Python<'py>) -> Option<RawArrays<'py>> {
        let (poses, forces) = self.raw.as_ref()?;
        let p = Array2::from_shape_fn((poses.len(), POSE_COLUMNS), |(i, j)| poses[i][j]);
        let f = Array2::from_shape_fn((forces.len(), 3), |(i, j)| forces[i][j]);
        Some((p.into_pyarray(py), f.into_pyarray(py)))
    }
}

/// Drills `session` with `surgeon` until the session's next 10 Hz record (returned as its
/// 11-column row) or until the surgeon finishes (None), with the GIL released.
pub(crate) fn drive<'py>(
    py: Python<'py>,
    session: &mut PySession,
    surgeon: &mut PySurgeon,
    guided: bool,
) -> Option<Bound<'py, PyArray1<f64>>> {
    let PySurgeon { inner, raw } = surgeon;
    let session = session.native_mut();
    let record = detached(py, || {
        inner.drill_until_record(session, guided, |row, force| {
            if let Some((poses, forces)) = raw.as_mut() {
                poses.push(*row);
                forces.push([force.x, force.y, force.z]);
            }
        })
    });
    record.map(|r| record_row(&r).to_vec().into_pyarray(py))
}

/// The virtual surgeon's constants (`crate::surgeon`), SI units, by name.
#[pyfunction]
pub(crate) fn surgeon_constants(py: Python<'_>) -> PyResult<Bound<'_, PyAny>> {
    let c: [(&str, f64); 11] = [
        ("HAND_MASS_KG", surgeon::HAND_MASS_KG),
        ("TRACK_STIFFNESS_N_PER_M", surgeon::TRACK_STIFFNESS_N_PER_M),
        ("LATERAL_STIFFNESS_N_PER_M", surgeon::LATERAL_STIFFNESS_N_PER_M),
        ("GENERIC_BREAKTHROUGH_DEPTH_M", surgeon::GENERIC_BREAKTHROUGH_DEPTH_M),
        ("AIM_FOLLOW_S", surgeon::AIM_FOLLOW_S),
        ("PUSH_MARGIN_N", surgeon::PUSH_MARGIN_N),
        ("MAX_PUSH_N", surgeon::MAX_PUSH_N),
        ("YIELD_SETTLE_S", surgeon::YIELD_SETTLE_S),
        ("CUE_LEAK_PER_S", surgeon::CUE_LEAK_PER_S),
        ("MAX_ATTEMPT_S", surgeon::MAX_ATTEMPT_S),
        ("START_S_M", surgeon::START_S_M),
    ];
    to_python(py, &std::collections::BTreeMap::from(c))
}

/// The stylus orientation (w, x, y, z) that points the drill along the unit direction `d`.
#[pyfunction]
pub(crate) fn axis_quaternion(d: [f64; 3]) -> [f64; 4] {
    surgeon::axis_quaternion(&d.into())
}
