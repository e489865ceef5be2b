//! The guidance share of the rendered force.
//!
//! Each model reply sets a target: the predicted expert force minus the trainee's force feedback
//! at that moment (Fekri et al. 2021, section 2.4). The share mixed into the force follows
//! `gain · target`, clamped to `max_n` and moved at most `max_rate_n_per_s`, so a new target is a
//! ramp and a lost model is a fade-out, never a jump. A target older than `timeout_s` counts as
//! lost.

use nalgebra::Vector3;

use crate::error::{positive, SimError, SimResult};

/// Largest accepted guidance gain.
pub const MAX_GAIN: f64 = 4.0;

/// Guidance limits.
#[derive(Debug, Clone, PartialEq)]
pub struct GuidanceParams {
    /// Largest guidance share (N); at most the device's continuous force by default, so guidance
    /// alone can be held indefinitely.
    pub max_n: f64,
    /// Fastest change of the guidance share (N/s).
    pub max_rate_n_per_s: f64,
    /// Age after which a model target is dropped and guidance fades out (s).
    pub timeout_s: f64,
}

impl Default for GuidanceParams {
    fn default() -> Self {
        Self { max_n: 0.88, max_rate_n_per_s: 8.0, timeout_s: 0.35 }
    }
}

impl GuidanceParams {
    /// Checks every field.
    ///
    /// # Errors
    /// A non-positive or non-finite value.
    pub fn validate(&self) -> SimResult<()> {
        positive("guidance max_n", self.max_n)?;
        positive("guidance max_rate_n_per_s", self.max_rate_n_per_s)?;
        positive("guidance timeout_s", self.timeout_s).map(|_| ())
    }
}

/// Checks a guidance gain.
///
/// # Errors
/// A gain outside `0..=MAX_GAIN`.
pub fn check_gain(gain: f64) -> SimResult<f64> {
    if gain.is_finite() && (0.0..=MAX_GAIN).contains(&gain) {
        Ok(gain)
    } else {
        Err(SimError::InvalidParameter { name: "guidance gain", value: gain, reason: "must be within 0..=4" })
    }
}

/// One session's guidance mixer (no allocation; runs on the tick thread).
#[derive(Debug, Clone)]
pub struct GuidanceMixer {
    params: GuidanceParams,
    gain: f64,
    target_n: Vector3<f64>,
    target_age_s: f64,
    applied_n: Vector3<f64>,
}

impl GuidanceMixer {
    /// A mixer with no target.
    #[must_use]
    pub fn new(params: GuidanceParams, gain: f64) -> Self {
        Self { params, gain, target_n: Vector3::zeros(), target_age_s: f64::INFINITY, applied_n: Vector3::zeros() }
    }

    /// Back to no target and no share, with `gain`.
    pub fn reset(&mut self, gain: f64) {
        *self = Self::new(self.params.clone(), gain);
    }

    /// Sets the gain (already checked).
    pub fn set_gain(&mut self, gain: f64) {
        self.gain = gain;
    }

    /// The gain.
    #[must_use]
    pub fn gain(&self) -> f64 {
        self.gain
    }

    /// A new target (N); non-finite targets are ignored.
    pub fn set_target(&mut self, guidance_n: Vector3<f64>) {
        if guidance_n.iter().all(|x| x.is_finite()) {
            self.target_n = guidance_n;
            self.target_age_s = 0.0;
        }
    }

    /// Whether the newest target is still fresh.
    #[must_use]
    pub fn is_live(&self) -> bool {
        self.target_age_s <= self.params.timeout_s
    }

    /// Advances by `dt_s` and returns the share to mix into the force (N).
    pub fn step(&mut self, dt_s: f64) -> Vector3<f64> {
        self.target_age_s += dt_s;
        let mut want = if self.is_live() { self.target_n * self.gain } else { Vector3::zeros() };
        let n = want.norm();
        if n > self.params.max_n {
            want *= self.params.max_n / n;
        }
        let delta = want - self.applied_n;
        let max_step = self.params.max_rate_n_per_s * dt_s;
        let d = delta.norm();
        self.applied_n += if d > max_step { delta * (max_step / d) } else { delta };
        self.applied_n
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn ramps_clamps_and_fades_out_when_the_model_goes_quiet() {
        let p = GuidanceParams::default();
        let mut m = GuidanceMixer::new(p.clone(), 1.0);
        m.set_target(Vector3::new(5.0, 0.0, 0.0));
        let first = m.step(1e-3);
        assert!((first.x - p.max_rate_n_per_s * 1e-3).abs() < 1e-12, "a step is a ramp: {first}");
        let mut last = first;
        for _ in 0..300 {
            last = m.step(1e-3);
        }
        assert!((last.norm() - p.max_n).abs() < 1e-9, "clamped to max_n: {last}");
        // No new target: after the timeout the share fades to zero at the rate limit.
        let mut prev = last.norm();
        for _ in 0..1000 {
            let now = m.step(1e-3).norm();
            assert!(prev - now <= p.max_rate_n_per_s * 1e-3 + 1e-12);
            prev = now;
        }
        assert!(!m.is_live());
        assert!(prev < 1e-12, "faded out: {prev}");
    }

    #[test]
    fn zero_gain_mixes_nothing_and_bad_gains_are_refused() {
        let mut m = GuidanceMixer::new(GuidanceParams::default(), 0.0);
        m.set_target(Vector3::new(0.5, 0.5, 0.0));
        assert_eq!(m.step(1e-3), Vector3::zeros());
        m.set_target(Vector3::new(f64::NAN, 0.0, 0.0));
        assert!(m.step(1e-3).iter().all(|x| x.is_finite()));
        assert!(check_gain(-0.1).is_err() && check_gain(f64::NAN).is_err() && check_gain(4.5).is_err());
        assert_eq!(check_gain(0.5), Ok(0.5));
    }
}
