//! Per-session metrics, accumulated on the comm side from the 10 Hz state and guidance streams.

use nalgebra::{Point3, Vector3};
use serde_json::{json, Value};

use crate::protocol::{GuidanceMsg, StateMsg};

/// Running metrics of one session (SI units).
#[derive(Debug, Clone, Default)]
pub struct SessionMetrics {
    records: u64,
    time_s: f64,
    max_depth_m: f64,
    deviation_sum_m: f64,
    deviation_inside: u64,
    max_deviation_m: f64,
    last_tip_m: Vector3<f64>,
    peak_temperature_c: f64,
    time_above_47_s: f64,
    max_plunge_m: f64,
    breakthroughs: u16,
    removed_mass_kg: f64,
    removed_volume_m3: f64,
    rejected_poses: u32,
    guidance_count: u64,
    guidance_sum_n: f64,
    latency_sum_s: f64,
    latency_max_s: f64,
}

impl SessionMetrics {
    /// Folds in one state message.
    pub fn add_state(&mut self, s: &StateMsg) {
        self.records += 1;
        self.time_s = s.time_s;
        let depth = s.features[7];
        self.max_depth_m = self.max_depth_m.max(depth);
        if depth > 0.0 {
            self.deviation_sum_m += s.deviation_m;
            self.deviation_inside += 1;
            self.max_deviation_m = self.max_deviation_m.max(s.deviation_m);
        }
        self.last_tip_m = Vector3::new(s.features[3], s.features[4], s.features[5]);
        self.peak_temperature_c = s.peak_temperature_c;
        self.time_above_47_s = s.time_above_47_s;
        self.max_plunge_m = self.max_plunge_m.max(s.plunge_depth_m);
        self.breakthroughs = s.breakthroughs;
        self.removed_mass_kg = s.removed_mass_kg;
        self.removed_volume_m3 = s.removed_volume_m3;
        self.rejected_poses = s.rejected_poses;
    }

    /// 10 Hz records folded in.
    #[must_use]
    pub fn records(&self) -> u64 {
        self.records
    }

    /// The attempt's largest plunge and largest lateral deviation inside the bone (m).
    #[must_use]
    pub fn worst_m(&self) -> (f64, f64) {
        (self.max_plunge_m, self.max_deviation_m)
    }

    /// Folds in one guidance message.
    pub fn add_guidance(&mut self, g: &GuidanceMsg) {
        self.guidance_count += 1;
        self.guidance_sum_n += g.guidance_n.norm();
        self.latency_sum_s += g.model_latency_s;
        self.latency_max_s = self.latency_max_s.max(g.model_latency_s);
    }

    /// The metrics as JSON, with the distance from the last tip to the target `target_m`.
    #[must_use]
    pub fn to_json(&self, target_m: &Point3<f64>) -> Value {
        let mean = |sum: f64, n: u64| if n > 0 { sum / n as f64 } else { 0.0 };
        json!({
            "records": self.records,
            "time_s": self.time_s,
            "max_depth_m": self.max_depth_m,
            "mean_deviation_m": mean(self.deviation_sum_m, self.deviation_inside),
            "max_deviation_m": self.max_deviation_m,
            "target_distance_m": if self.records > 0 { (self.last_tip_m - target_m.coords).norm() } else { f64::NAN },
            "peak_temperature_c": self.peak_temperature_c,
            "time_above_47_s": self.time_above_47_s,
            // The attempt's largest plunge, as `dhg.operators.metrics.skill_metrics` reports it (a later,
            // smaller plunge after a second breakthrough must not hide the first).
            "plunge_depth_m": self.max_plunge_m,
            "breakthroughs": self.breakthroughs,
            "removed_mass_kg": self.removed_mass_kg,
            "removed_volume_m3": self.removed_volume_m3,
            "rejected_poses": self.rejected_poses,
            "guidance_messages": self.guidance_count,
            "mean_guidance_n": mean(self.guidance_sum_n, self.guidance_count),
            "mean_model_latency_s": mean(self.latency_sum_s, self.guidance_count),
            "max_model_latency_s": self.latency_max_s,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_reported_plunge_is_the_attempts_largest_not_its_last() {
        let mut m = SessionMetrics::default();
        for plunge_m in [0.0, 3e-3, 2e-3, 0.0, 1e-3] {
            m.add_state(&StateMsg { plunge_depth_m: plunge_m, ..StateMsg::default() });
        }
        let v = m.to_json(&Point3::origin());
        assert!((v["plunge_depth_m"].as_f64().unwrap() - 3e-3).abs() < 1e-12);
        assert!((m.worst_m().0 - 3e-3).abs() < 1e-12);
    }
}
