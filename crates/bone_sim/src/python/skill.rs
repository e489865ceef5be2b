//! `skill_metrics`: the core's skill metrics (`crate::skill`) of an attempt's 10 Hz records.

use nalgebra::{Point3, Vector3};
use numpy::PyReadonlyArray2;
use pyo3::prelude::*;

use super::convert::{from_python, to_python};
use super::errors::IntoPyResult;
use super::session::RECORD_COLUMNS;
use crate::error::SimError;
use crate::path::PlannedPath;
use crate::skill::{AttemptEnd, SkillTally, TaskRules};

/// The skill metrics (a dict, SI units) of an attempt on the path `entry_m` → `target_m` (m):
/// its 10 Hz `records` (M, 11: time, the nine features, drill on), how it ended, the task
/// `rules` (a dict of `TaskRules`' fields; missing ones take the core's defaults) and, when kept,
/// its 1 kHz device forces `forces_n` (N, 3) in N.
#[pyfunction]
#[pyo3(signature = (records, entry_m, target_m, final_tip_m, drilling_s, plunge_depth_m, peak_temperature_c, time_above_47_s, rules=None, forces_n=None))]
#[allow(clippy::too_many_arguments)] // the attempt's facts, one keyword each
pub(crate) fn skill_metrics<'py>(
    py: Python<'py>,
    records: PyReadonlyArray2<'py, f64>,
    entry_m: [f64; 3],
    target_m: [f64; 3],
    final_tip_m: [f64; 3],
    drilling_s: f64,
    plunge_depth_m: f64,
    peak_temperature_c: f64,
    time_above_47_s: f64,
    rules: Option<&Bound<'py, PyAny>>,
    forces_n: Option<PyReadonlyArray2<'py, f64>>,
) -> PyResult<Bound<'py, PyAny>> {
    let path = PlannedPath::new(entry_m.into(), target_m.into()).py()?;
    let rules: TaskRules = match rules {
        Some(r) => from_python(r, "task rules")?,
        None => TaskRules::default(),
    };
    rules.validate().py()?;
    let rec = records.as_array();
    if rec.nrows() > 0 && rec.ncols() != RECORD_COLUMNS {
        return Err(SimError::ShapeMismatch {
            what: "records",
            expected: format!("shape (M, {RECORD_COLUMNS})"),
            got: format!("{:?}", rec.shape()),
        })
        .py();
    }
    if let Some(bad) = rec.iter().find(|v| !v.is_finite()) {
        return Err(SimError::NonFinite { what: "records", value: *bad }).py();
    }
    let mut tally = SkillTally::default();
    for r in rec.rows() {
        let tip = Point3::new(r[4], r[5], r[6]);
        tally.add_record(&path, &tip, r[8], &Vector3::new(r[1], r[2], r[3]));
    }
    if let Some(forces) = forces_n {
        let f = forces.as_array();
        if f.nrows() > 0 && f.ncols() != 3 {
            return Err(SimError::ShapeMismatch {
                what: "forces_n",
                expected: "shape (N, 3)".into(),
                got: format!("{:?}", f.shape()),
            })
            .py();
        }
        if let Some(bad) = f.iter().find(|v| !v.is_finite()) {
            return Err(SimError::NonFinite { what: "forces_n (N)", value: *bad }).py();
        }
        for r in f.rows() {
            tally.add_tick_force(&Vector3::new(r[0], r[1], r[2]));
        }
    }
    let end =
        AttemptEnd { final_tip_m: final_tip_m.into(), drilling_s, plunge_depth_m, peak_temperature_c, time_above_47_s };
    end.validate().py()?;
    to_python(py, &tally.metrics(&path, &rules, &end))
}
