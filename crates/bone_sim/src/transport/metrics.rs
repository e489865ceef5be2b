//! Per-session metrics, accumulated on the comm side from the 10 Hz state and guidance streams;
//! the skill metrics among them are the core's one definition (`crate::skill`).

use nalgebra::{Point3, Vector3};

use crate::path::PlannedPath;
use crate::protocol::{GuidanceMsg, StateMsg};
use crate::skill::{AttemptEnd, SkillTally, TaskRules};

use super::replies::MetricsReply;

/// Running metrics of one session (SI units).
#[derive(Debug, Clone, Default)]
pub struct SessionMetrics {
    records: u64,
    time_s: f64,
    max_depth_m: f64,
    skill: SkillTally,
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
    /// Folds in one state message of a session drilling `path`.
    pub fn add_state(&mut self, s: &StateMsg, path: &PlannedPath) {
        self.records += 1;
        self.time_s = s.time_s;
        let depth = s.features[7];
        self.max_depth_m = self.max_depth_m.max(depth);
        let tip = Point3::new(s.features[3], s.features[4], s.features[5]);
        let force = Vector3::new(s.features[0], s.features[1], s.features[2]);
        self.skill.add_record(path, &tip, depth, &force);
        self.last_tip_m = tip.coords;
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
    pub fn worst_m(&self, path: &PlannedPath) -> (f64, f64) {
        (self.max_plunge_m, self.skill_metrics(path).max_deviation_m)
    }

    fn skill_metrics(&self, path: &PlannedPath) -> crate::skill::SkillMetrics {
        let end = AttemptEnd {
            final_tip_m: self.last_tip_m.into(),
            drilling_s: self.time_s,
            plunge_depth_m: self.max_plunge_m,
            peak_temperature_c: self.peak_temperature_c,
            time_above_47_s: self.time_above_47_s,
        };
        self.skill.metrics(path, &TaskRules::default(), &end)
    }

    /// Folds in one guidance message.
    pub fn add_guidance(&mut self, g: &GuidanceMsg) {
        self.guidance_count += 1;
        self.guidance_sum_n += g.guidance_n.norm();
        self.latency_sum_s += g.model_latency_s;
        self.latency_max_s = self.latency_max_s.max(g.model_latency_s);
    }

    /// The reply to a `metrics` query of session `session` drilling `path`; `mode`, `gain` and
    /// `burr_radius_m` (m) are its settings now.
    #[must_use]
    pub fn reply(
        &self,
        path: &PlannedPath,
        session: &str,
        mode: &'static str,
        gain: f64,
        burr_radius_m: f64,
    ) -> MetricsReply {
        #[allow(clippy::cast_precision_loss)] // a count of messages
        let mean = |sum: f64, n: u64| if n > 0 { sum / n as f64 } else { 0.0 };
        let skill = self.skill_metrics(path);
        MetricsReply {
            records: self.records,
            time_s: self.time_s,
            max_depth_m: self.max_depth_m,
            mean_deviation_m: skill.mean_deviation_m,
            max_deviation_m: skill.max_deviation_m,
            max_lateral_deviation_m: skill.max_lateral_deviation_m,
            target_distance_m: (self.records > 0).then_some(skill.target_distance_m),
            force_jerk_n_per_s: skill.force_jerk_n_per_s,
            peak_temperature_c: self.peak_temperature_c,
            time_above_47_s: self.time_above_47_s,
            plunge_depth_m: skill.plunge_depth_m,
            breakthroughs: self.breakthroughs,
            removed_mass_kg: self.removed_mass_kg,
            removed_volume_m3: self.removed_volume_m3,
            rejected_poses: self.rejected_poses,
            guidance_messages: self.guidance_count,
            mean_guidance_n: mean(self.guidance_sum_n, self.guidance_count),
            mean_model_latency_s: mean(self.latency_sum_s, self.guidance_count),
            max_model_latency_s: self.latency_max_s,
            session: session.to_owned(),
            guidance_mode: mode,
            guidance_gain: gain,
            burr_radius_m,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn path() -> PlannedPath {
        PlannedPath::new(Point3::origin(), Point3::new(0.0, 0.0, 0.04)).unwrap()
    }

    #[test]
    fn the_reported_plunge_is_the_attempts_largest_not_its_last() {
        let mut m = SessionMetrics::default();
        for plunge_m in [0.0, 3e-3, 2e-3, 0.0, 1e-3] {
            m.add_state(&StateMsg { plunge_depth_m: plunge_m, ..StateMsg::default() }, &path());
        }
        let r = m.reply(&path(), "s", "shaped", 1.0, 1.25e-3);
        assert!((r.plunge_depth_m - 3e-3).abs() < 1e-12);
        assert!((m.worst_m(&path()).0 - 3e-3).abs() < 1e-12);
    }

    #[test]
    fn the_skill_figures_are_the_cores_one_definition() {
        // The same records through the session metrics and through `crate::skill` directly.
        let p = path();
        let mut m = SessionMetrics::default();
        let mut tally = SkillTally::default();
        for (k, (x, z)) in [(0.0, -1e-3), (1e-3, 0.01), (0.5e-3, 0.043)].into_iter().enumerate() {
            let mut features = [0.0; crate::FEATURE_COUNT];
            features[0] = 0.1 * k as f64;
            (features[3], features[5], features[7]) = (x, z, z);
            m.add_state(&StateMsg { features, time_s: 0.1 * k as f64, ..StateMsg::default() }, &p);
            tally.add_record(&p, &Point3::new(x, 0.0, z), z, &Vector3::new(features[0], 0.0, 0.0));
        }
        let r = m.reply(&p, "s", "shaped", 1.0, 1.25e-3);
        let end = AttemptEnd {
            final_tip_m: Point3::new(0.5e-3, 0.0, 0.043),
            drilling_s: 0.2,
            plunge_depth_m: 0.0,
            peak_temperature_c: 0.0,
            time_above_47_s: 0.0,
        };
        let want = tally.metrics(&p, &TaskRules::default(), &end);
        assert_eq!(
            (
                r.mean_deviation_m,
                r.max_deviation_m,
                r.max_lateral_deviation_m,
                r.target_distance_m,
                r.force_jerk_n_per_s
            ),
            (
                want.mean_deviation_m,
                want.max_deviation_m,
                want.max_lateral_deviation_m,
                Some(want.target_distance_m),
                want.force_jerk_n_per_s
            )
        );
        assert!((want.max_lateral_deviation_m - 1e-3).abs() < 1e-12 && (want.force_jerk_n_per_s - 1.0).abs() < 1e-9);
    }
}
