//! Skill metrics of a drilling attempt: the one definition behind an offline attempt's metrics
//! (Python's `dhg.core.skill.skill_metrics`), a recorded live attempt's (`dhg record`) and
//! the server's per-session metrics (`transport::metrics`). `docs/dataset.md` lists them.

use nalgebra::{Point3, Vector3};
use serde::{Deserialize, Serialize};

use crate::error::{finite, non_negative, SimError, SimResult};
use crate::path::PlannedPath;
use crate::record::{RECORD_PERIOD_TICKS, TICK_S};

/// What counts as completing the drilling task A → B.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct TaskRules {
    /// The final tip must be this close to B (m).
    pub max_target_distance_m: f64,
    /// The tip may stray at most this far from the planned segment while in bone (m).
    pub max_deviation_m: f64,
    /// The attempt must finish within this time (s).
    pub max_duration_s: f64,
}

impl Default for TaskRules {
    fn default() -> Self {
        // DHG's own tolerances: Fekri et al. 2021 state none for their task A→B.
        Self { max_target_distance_m: 3e-3, max_deviation_m: 3e-3, max_duration_s: 240.0 }
    }
}

impl TaskRules {
    /// Checks that every limit is finite and positive.
    ///
    /// # Errors
    /// [`SimError::InvalidParameter`] naming the first bad limit.
    pub fn validate(&self) -> SimResult<()> {
        for (name, v) in [
            ("task max_target_distance_m", self.max_target_distance_m),
            ("task max_deviation_m", self.max_deviation_m),
            ("task max_duration_s", self.max_duration_s),
        ] {
            if !(v.is_finite() && v > 0.0) {
                return Err(SimError::InvalidParameter { name, value: v, reason: "must be finite and > 0" });
            }
        }
        Ok(())
    }
}

/// How an attempt ended, as its driver knows it.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct AttemptEnd {
    /// Where the tip was at the end (m).
    pub final_tip_m: Point3<f64>,
    /// Time from drill start to drill stop (s).
    pub drilling_s: f64,
    /// The attempt's largest plunge (m).
    pub plunge_depth_m: f64,
    /// Peak drill-tip temperature (°C).
    pub peak_temperature_c: f64,
    /// Time the tip spent above 47 °C (s).
    pub time_above_47_s: f64,
}

impl AttemptEnd {
    /// Checks every field: finite, and the durations and the plunge not negative.
    ///
    /// # Errors
    /// A non-finite value, or a negative duration or plunge, named.
    pub fn validate(&self) -> SimResult<()> {
        let [x, y, z] = self.final_tip_m.coords.into();
        for (what, v) in [
            ("final_tip_m x (m)", x),
            ("final_tip_m y (m)", y),
            ("final_tip_m z (m)", z),
            ("peak_temperature_c (°C)", self.peak_temperature_c),
        ] {
            finite(what, v)?;
        }
        non_negative("drilling_s (s)", self.drilling_s)?;
        non_negative("plunge_depth_m (m)", self.plunge_depth_m)?;
        non_negative("time_above_47_s (s)", self.time_above_47_s)?;
        Ok(())
    }
}

/// The skill metrics of one attempt (SI units; `docs/dataset.md`).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct SkillMetrics {
    /// Time from drill start to drill stop (s).
    pub completion_time_s: f64,
    /// Mean distance of the tip from the segment A→B while in bone (m).
    pub mean_deviation_m: f64,
    /// Largest distance of the tip from the segment A→B while in bone (m; past B, the distance to B).
    pub max_deviation_m: f64,
    /// Largest offset of the tip across the path, from the line through A and B, while in bone (m;
    /// decision 0015).
    pub max_lateral_deviation_m: f64,
    /// Distance of the final tip from B (m).
    pub target_distance_m: f64,
    /// The attempt's largest plunge (m).
    pub plunge_depth_m: f64,
    /// Peak drill-tip temperature (°C).
    pub peak_temperature_c: f64,
    /// Time above 47 °C (s).
    pub time_above_47_s: f64,
    /// RMS rate of change of the device force (N/s), over the 1 kHz stream when given, else over
    /// the 10 Hz records.
    pub force_jerk_n_per_s: f64,
    /// Within the target distance, the deviation limit and the time limit of [`TaskRules`].
    pub completed: bool,
}

/// The running sums behind [`SkillMetrics`], folded in one record (and one force) at a time, so
/// a whole attempt and a live session's stream give the same figures.
#[derive(Debug, Clone, Copy, Default)]
pub struct SkillTally {
    inside: u64,
    deviation_sum_m: f64,
    max_deviation_m: f64,
    max_offset_m: f64,
    record_force: Jerk,
    tick_force: Jerk,
}

/// The RMS rate of change of a force sampled at a fixed period.
#[derive(Debug, Clone, Copy, Default)]
struct Jerk {
    last_n: Option<Vector3<f64>>,
    sum_sq: f64,
    count: u64,
}

impl Jerk {
    fn add(&mut self, force_n: &Vector3<f64>, period_s: f64) {
        if let Some(last) = self.last_n {
            self.sum_sq += ((force_n - last) / period_s).norm_squared();
            self.count += 1;
        }
        self.last_n = Some(*force_n);
    }

    fn rms(&self) -> Option<f64> {
        #[allow(clippy::cast_precision_loss)] // a count of samples
        (self.count > 0).then(|| (self.sum_sq / self.count as f64).sqrt())
    }
}

/// The 10 Hz record period (s) the record forces are differenced over.
#[allow(clippy::cast_precision_loss)] // 100 ticks
const RECORD_PERIOD_S: f64 = RECORD_PERIOD_TICKS as f64 * TICK_S;

impl SkillTally {
    /// Folds in one 10 Hz record: the tip (m), its depth along A→B (m; in bone when > 0) and the
    /// device force (N).
    pub fn add_record(&mut self, path: &PlannedPath, tip_m: &Point3<f64>, depth_m: f64, force_n: &Vector3<f64>) {
        if depth_m > 0.0 {
            let deviation = path.deviation_m(tip_m);
            self.inside += 1;
            self.deviation_sum_m += deviation;
            self.max_deviation_m = self.max_deviation_m.max(deviation);
            self.max_offset_m = self.max_offset_m.max(path.offset_from_line_m(tip_m));
        }
        self.record_force.add(force_n, RECORD_PERIOD_S);
    }

    /// Folds in one 1 kHz device force (N); once any is given, the force jerk is taken from them.
    pub fn add_tick_force(&mut self, force_n: &Vector3<f64>) {
        self.tick_force.add(force_n, TICK_S);
    }

    /// 10 Hz records folded in with the tip in bone.
    #[must_use]
    pub fn records_inside(&self) -> u64 {
        self.inside
    }

    /// The metrics of the attempt so far.
    #[must_use]
    pub fn metrics(&self, path: &PlannedPath, rules: &TaskRules, end: &AttemptEnd) -> SkillMetrics {
        #[allow(clippy::cast_precision_loss)] // a count of records
        let mean = if self.inside > 0 { self.deviation_sum_m / self.inside as f64 } else { 0.0 };
        let target_distance_m = (end.final_tip_m - path.target_m()).norm();
        SkillMetrics {
            completion_time_s: end.drilling_s,
            mean_deviation_m: mean,
            max_deviation_m: self.max_deviation_m,
            max_lateral_deviation_m: self.max_offset_m,
            target_distance_m,
            plunge_depth_m: end.plunge_depth_m,
            peak_temperature_c: end.peak_temperature_c,
            time_above_47_s: end.time_above_47_s,
            force_jerk_n_per_s: self.tick_force.rms().or_else(|| self.record_force.rms()).unwrap_or(0.0),
            completed: target_distance_m <= rules.max_target_distance_m
                && self.max_deviation_m <= rules.max_deviation_m
                && end.drilling_s <= rules.max_duration_s,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn path() -> PlannedPath {
        PlannedPath::new(Point3::origin(), Point3::new(0.0, 0.0, 0.04)).unwrap()
    }

    fn end(final_tip_m: Point3<f64>) -> AttemptEnd {
        AttemptEnd {
            final_tip_m,
            drilling_s: 100.0,
            plunge_depth_m: 2e-3,
            peak_temperature_c: 45.0,
            time_above_47_s: 0.0,
        }
    }

    #[test]
    fn deviation_counts_only_in_bone_and_the_offset_across_ignores_the_overshoot() {
        let p = path();
        let mut t = SkillTally::default();
        let zero = Vector3::zeros();
        // Before A, off the line: not in bone, not counted.
        t.add_record(&p, &Point3::new(5e-3, 0.0, -2e-3), -2e-3, &zero);
        // In bone: 1 mm and 2 mm off the line.
        t.add_record(&p, &Point3::new(1e-3, 0.0, 0.01), 0.01, &zero);
        t.add_record(&p, &Point3::new(0.0, 2e-3, 0.02), 0.02, &zero);
        // 3 mm past B, 0.5 mm off the line: 3.04 mm from the segment, 0.5 mm across.
        let past = Point3::new(0.5e-3, 0.0, 0.043);
        t.add_record(&p, &past, 0.043, &zero);
        let m = t.metrics(&p, &TaskRules::default(), &end(past));
        let overshoot = (0.5e-3_f64.powi(2) + 3e-3_f64.powi(2)).sqrt();
        assert_eq!(t.records_inside(), 3);
        assert!((m.max_deviation_m - overshoot).abs() < 1e-7, "{m:?}");
        assert!((m.max_lateral_deviation_m - 2e-3).abs() < 1e-12, "{m:?}");
        assert!((m.mean_deviation_m - (1e-3 + 2e-3 + overshoot) / 3.0).abs() < 1e-7, "{m:?}");
        assert!((m.target_distance_m - (0.5e-3_f64.powi(2) + 3e-3_f64.powi(2)).sqrt()).abs() < 1e-12);
        assert!(!m.completed, "3.04 mm from B is past the 3 mm rule");
    }

    #[test]
    fn completion_needs_every_rule_and_jerk_prefers_the_1khz_stream() {
        let p = path();
        let mut t = SkillTally::default();
        t.add_record(&p, &Point3::new(0.0, 0.0, 0.01), 0.01, &Vector3::zeros());
        t.add_record(&p, &Point3::new(0.0, 0.0, 0.039), 0.039, &Vector3::new(0.3, 0.0, 0.0));
        let rules = TaskRules::default();
        let at_b = end(Point3::new(0.0, 0.0, 0.039));
        let m = t.metrics(&p, &rules, &at_b);
        assert!(m.completed, "{m:?}");
        assert!((m.force_jerk_n_per_s - 3.0).abs() < 1e-12, "0.3 N in 0.1 s: {m:?}");
        assert!(!t.metrics(&p, &rules, &AttemptEnd { drilling_s: 241.0, ..at_b }).completed);
        for f in [0.0, 0.002, 0.0] {
            t.add_tick_force(&Vector3::new(0.0, f, 0.0));
        }
        assert!((t.metrics(&p, &rules, &at_b).force_jerk_n_per_s - 2.0).abs() < 1e-9, "2 mN per ms");
        let empty = SkillTally::default().metrics(&p, &rules, &at_b);
        assert_eq!((empty.mean_deviation_m, empty.max_deviation_m, empty.force_jerk_n_per_s), (0.0, 0.0, 0.0));
        assert!(TaskRules { max_duration_s: f64::NAN, ..rules }.validate().is_err());
        assert!(rules.validate().is_ok());
    }
}
