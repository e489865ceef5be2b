//! Device safety: what may reach a haptic device, whatever the simulation asks for.
//!
//! Every force passes through [`ForceLimiter::step`] once per tick. It guarantees, always, the
//! three device limits, each defined once here (and tabled in `docs/frames.md`):
//! - **finite**: a NaN or infinite request is treated as a request for zero force;
//! - **peak**: |F| never exceeds the profile's peak force;
//! - **continuous**: the motors' heating never exceeds what the continuous rating allows. The
//!   motors are modelled as one first-order thermal node: their temperature rise follows |F|²
//!   low-passed with the winding's time constant τ, `dθ/dt = (|F|² − θ)/τ` (θ in N², so the
//!   continuous force `F_c` held for ever settles at `θ = F_c²`). The limit is `θ ≤ F_c²` at
//!   every tick. While θ is below 75 % of `F_c²` the peak is allowed; between 75 % and 100 % the
//!   allowed force falls linearly to `F_c` (a soft knee, so derating never jerks the hand). Held
//!   from cold, the peak lasts `τ·ln(1 / (1 − 0.75·F_c²/F_p²))` (1.1 s for the Touch) before
//!   the knee starts; any force at or below `F_c` can be held indefinitely. This is the
//!   average-energy thermal protection of haptic actuators (Goldenberg et al., US patent
//!   7,233,476, Immersion Corp. 2007: the allowed current ramps down to a sustainable level as
//!   the averaged energy reaches a warning level);
//! - **rate**: the force changes by at most `max_force_rate_n_per_s · dt` per tick, so contact
//!   onset and breakthrough produce ramps, not jumps;
//!
//! and, when no pose has arrived for `stale_after_s`, it replaces the request by zero and ramps
//! the force down.
//!
//! The limiter allocates nothing and takes no locks, so it can run on the 1 kHz thread.

use nalgebra::Vector3;

use crate::error::{positive, SimError, SimResult};

/// Fraction of the continuous budget (`θ / F_c²`) up to which the peak force is allowed: the
/// project's choice (the makers publish no thermal model, see [`DeviceProfile::geomagic_touch`]),
/// so that derating starts with a quarter of the budget in hand and ramps the force down rather
/// than cutting it at the budget's edge.
const THERMAL_KNEE: f64 = 0.75;

/// The Touch's continuous ("24 hours") force (N; 3D Systems, Touch device specifications): the
/// default profile's, and the guidance share's default cap.
pub const TOUCH_CONTINUOUS_FORCE_N: f64 = 0.88;
/// The Touch's stiffness (N/m), the lower end of its quoted 0.4–0.7 N/mm: the default profile's
/// rendering limit, and the guidance corridor's and brake's default stiffness.
pub const TOUCH_STIFFNESS_N_PER_M: f64 = 400.0;

/// Force and rate limits of a haptic device.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
// Python and the wire name the fields as here; a missing field takes its default, an unknown one
// is refused.
#[serde(default, deny_unknown_fields)]
pub struct DeviceProfile {
    /// Largest force the device may render, at any instant (N).
    pub peak_force_n: f64,
    /// Force the device may render indefinitely (N).
    pub continuous_force_n: f64,
    /// Time constant τ of the motors' first-order thermal model (s): how fast heating from |F|²
    /// builds up and cools off.
    pub thermal_time_constant_s: f64,
    /// Largest rendering stiffness for the force model (N/m).
    pub max_stiffness_n_per_m: f64,
    /// Largest change of force per second (N/s).
    pub max_force_rate_n_per_s: f64,
    /// Time without a fresh pose after which the force is ramped to zero (s).
    pub stale_after_s: f64,
}

impl DeviceProfile {
    /// The 3D Systems (Geomagic) Touch: 3.3 N peak and 0.88 N continuous ("24 hours") force, and
    /// stiffness 0.4 N/mm, the lower end of its quoted 0.4–0.7 N/mm range so every axis can
    /// render it (3D Systems, Touch device specifications). The makers do not publish their
    /// motors' thermal model: τ = 20 s is this project's choice, of the order of the winding
    /// thermal time constants that DC-motor catalogues list for small coreless motors (maxon,
    /// "thermal time constant winding"). The 200 N/s rate limit is this project's choice too (a
    /// 0.2 N step per 1 ms tick is below what a hand feels as a jolt).
    #[must_use]
    pub fn geomagic_touch() -> Self {
        Self {
            peak_force_n: 3.3,
            continuous_force_n: TOUCH_CONTINUOUS_FORCE_N,
            thermal_time_constant_s: 20.0,
            max_stiffness_n_per_m: TOUCH_STIFFNESS_N_PER_M,
            max_force_rate_n_per_s: 200.0,
            stale_after_s: 0.05,
        }
    }

    /// Checks every field.
    ///
    /// # Errors
    /// A non-finite or non-positive field, or a continuous force above the peak.
    pub fn validate(&self) -> SimResult<()> {
        positive("peak_force_n", self.peak_force_n)?;
        positive("continuous_force_n", self.continuous_force_n)?;
        positive("thermal_time_constant_s", self.thermal_time_constant_s)?;
        positive("max_stiffness_n_per_m", self.max_stiffness_n_per_m)?;
        positive("max_force_rate_n_per_s", self.max_force_rate_n_per_s)?;
        positive("stale_after_s", self.stale_after_s)?;
        if self.continuous_force_n > self.peak_force_n {
            return Err(SimError::InvalidParameter {
                name: "continuous_force_n",
                value: self.continuous_force_n,
                reason: "must not exceed peak_force_n",
            });
        }
        Ok(())
    }

    /// How long the peak force can be held from cold before derating begins (s).
    #[must_use]
    pub fn peak_hold_s(&self) -> f64 {
        let ratio = THERMAL_KNEE * (self.continuous_force_n / self.peak_force_n).powi(2);
        -self.thermal_time_constant_s * (1.0 - ratio).ln()
    }
}

impl Default for DeviceProfile {
    fn default() -> Self {
        Self::geomagic_touch()
    }
}

/// The always-on safety stage between the simulation and the device.
#[derive(Debug, Clone)]
pub struct ForceLimiter {
    profile: DeviceProfile,
    output_n: Vector3<f64>,
    /// The motors' thermal state θ (N²): |F|² low-passed with the thermal time constant, in
    /// `0..=continuous_force_n²`.
    heat_n2: f64,
    since_pose_s: f64,
    rejected_requests: u64,
}

impl ForceLimiter {
    /// A limiter at rest (zero force, cold, with no pose yet: it renders nothing until
    /// [`pose_received`](Self::pose_received) is called).
    ///
    /// # Errors
    /// An invalid profile.
    pub fn new(profile: DeviceProfile) -> SimResult<Self> {
        profile.validate()?;
        let since_pose_s = f64::INFINITY;
        Ok(Self { profile, output_n: Vector3::zeros(), heat_n2: 0.0, since_pose_s, rejected_requests: 0 })
    }

    /// The device profile.
    #[must_use]
    pub fn profile(&self) -> &DeviceProfile {
        &self.profile
    }

    /// Back to rest: zero force, cold, no pose yet.
    pub fn reset(&mut self) {
        self.output_n = Vector3::zeros();
        self.heat_n2 = 0.0;
        self.since_pose_s = f64::INFINITY;
        self.rejected_requests = 0;
    }

    /// A new attempt on the same device: until the next pose the force ramps down from where it
    /// is at the rate limit (a step to zero would be a jolt the limit exists to prevent), and the
    /// motors keep the heat they have (a reset does not cool them).
    pub fn release(&mut self) {
        self.since_pose_s = f64::INFINITY;
    }

    /// Marks that a fresh, valid pose arrived this tick.
    pub fn pose_received(&mut self) {
        self.since_pose_s = 0.0;
    }

    /// Whether the input is stale (no pose for longer than the profile allows).
    #[must_use]
    pub fn is_stale(&self) -> bool {
        self.since_pose_s > self.profile.stale_after_s
    }

    /// The force most recently output (N).
    #[must_use]
    pub fn output_n(&self) -> Vector3<f64> {
        self.output_n
    }

    /// The motors' thermal load: θ / `F_c²`, in `0..=1` (1 = the continuous budget is used up
    /// and only the continuous force is allowed).
    #[must_use]
    pub fn thermal_load(&self) -> f64 {
        self.heat_n2 / self.profile.continuous_force_n.powi(2)
    }

    /// Largest force magnitude the thermal knee allows right now (N): the peak up to 75 % of the
    /// continuous budget, then falling linearly to the continuous force at 100 %.
    #[must_use]
    pub fn allowed_force_n(&self) -> f64 {
        let p = &self.profile;
        let derate = ((self.thermal_load() - THERMAL_KNEE) / (1.0 - THERMAL_KNEE)).clamp(0.0, 1.0);
        p.peak_force_n - (p.peak_force_n - p.continuous_force_n) * derate
    }

    /// Requests that had a NaN or infinite component (each one was rendered as zero force).
    #[must_use]
    pub fn rejected_requests(&self) -> u64 {
        self.rejected_requests
    }

    /// Advances one tick of `dt_s` seconds and returns the force to send to the device (N).
    /// A non-finite or non-positive `dt_s` holds the previous output.
    pub fn step(&mut self, requested_n: Vector3<f64>, dt_s: f64) -> Vector3<f64> {
        if !(dt_s.is_finite() && dt_s > 0.0) {
            return self.output_n;
        }
        self.since_pose_s += dt_s;
        let mut target = requested_n;
        if !target.iter().all(|v| v.is_finite()) {
            self.rejected_requests += 1;
            target = Vector3::zeros();
        }
        if self.is_stale() {
            target = Vector3::zeros();
        }
        // The thermal filter's weight for this tick (exact for a force held over the tick).
        let alpha = -(-dt_s / self.profile.thermal_time_constant_s).exp_m1();
        let budget = self.profile.continuous_force_n.powi(2);
        // The knee, and the hard bound that keeps θ within the budget after this tick.
        let hard = (self.heat_n2 + (budget - self.heat_n2) / alpha).max(0.0).sqrt();
        let allowed = self.allowed_force_n().min(hard).min(self.profile.peak_force_n);
        let norm = target.norm();
        if norm > allowed {
            target *= allowed / norm;
        }
        // Rate limit.
        let max_step = self.profile.max_force_rate_n_per_s * dt_s;
        let delta = target - self.output_n;
        let step = delta.norm();
        let mut next = if step > max_step { self.output_n + delta * (max_step / step) } else { target };
        // A ramp down from above the allowed force may still sit above it: the hard thermal
        // bound and the peak win over the rate limit (they only ever lower the force).
        let bound = hard.min(self.profile.peak_force_n);
        let n = next.norm();
        if n > bound {
            next *= bound / n;
        }
        self.output_n = next;
        self.heat_n2 += (self.output_n.norm_squared() - self.heat_n2) * alpha;
        self.output_n
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const DT: f64 = 1e-3;

    fn live() -> ForceLimiter {
        let mut l = ForceLimiter::new(DeviceProfile::geomagic_touch()).unwrap();
        l.pose_received();
        l
    }

    /// A small deterministic generator (no extra dependency for tests).
    fn lcg(state: &mut u64) -> f64 {
        *state = state.wrapping_mul(6_364_136_223_846_793_005).wrapping_add(1_442_695_040_888_963_407);
        (*state >> 11) as f64 / (1u64 << 53) as f64
    }

    #[test]
    fn output_is_always_finite_bounded_and_rate_limited() {
        let mut l = live();
        let peak = l.profile().peak_force_n;
        let max_step = l.profile().max_force_rate_n_per_s * DT;
        let mut s = 7u64;
        let specials = [f64::NAN, f64::INFINITY, f64::NEG_INFINITY, 1e300, -1e300, 0.0];
        let mut prev = Vector3::zeros();
        for tick in 0..200_000 {
            if tick % 10 == 0 {
                l.pose_received();
            }
            let mut comp = || {
                let r = lcg(&mut s);
                if r < 0.05 {
                    specials[(r * 120.0) as usize % specials.len()]
                } else {
                    (r - 0.5) * 40.0
                }
            };
            let f = l.step(Vector3::new(comp(), comp(), comp()), DT);
            assert!(f.iter().all(|v| v.is_finite()), "tick {tick}: {f}");
            assert!(f.norm() <= peak + 1e-12, "tick {tick}: |F| = {}", f.norm());
            assert!((f - prev).norm() <= max_step + 1e-12, "tick {tick}: jump {}", (f - prev).norm());
            prev = f;
        }
        assert!(l.rejected_requests() > 0);
    }

    #[test]
    fn a_new_attempt_on_the_same_device_ramps_down_and_keeps_the_heat() {
        // A session reset releases the device: no step from the force it rendered, and the
        // motors stay as warm as they were (a reset must not restore the peak budget).
        let mut l = live();
        let max_step = l.profile().max_force_rate_n_per_s * DT;
        for _ in 0..3000 {
            l.pose_received();
            l.step(Vector3::new(0.0, 0.0, -2.0), DT);
        }
        let (before, heat) = (l.output_n(), l.thermal_load());
        assert!(before.norm() > 0.8 && heat > 0.1);
        l.release();
        let mut prev = before;
        for _ in 0..100 {
            let f = l.step(Vector3::new(0.0, 0.0, -2.0), DT); // no pose since the release: stale
            assert!((f - prev).norm() <= max_step + 1e-12, "a step of {} N", (f - prev).norm());
            prev = f;
        }
        assert!(prev.norm() < 1e-12, "ramped to rest");
        assert!(l.thermal_load() > 0.9 * heat, "the motors did not cool by a reset");
        l.reset();
        assert!(l.output_n().norm() == 0.0 && l.thermal_load() == 0.0);
    }

    #[test]
    fn sustained_force_falls_to_the_continuous_rating() {
        let mut l = live();
        let p = l.profile().clone();
        let push = Vector3::new(0.0, 0.0, -10.0);
        let mut at_1s = 0.0;
        for tick in 1..=10_000 {
            l.pose_received();
            let f = l.step(push, DT);
            if tick == 1000 {
                at_1s = f.norm();
            }
        }
        assert!((at_1s - p.peak_force_n).abs() < 1e-9, "the peak is allowed at first, got {at_1s}");
        let end = l.output_n().norm();
        assert!((end - p.continuous_force_n).abs() < 0.05, "after 10 s: {end} N");
        // Resting cools the device and restores the peak.
        for _ in 0..20_000 {
            l.pose_received();
            l.step(Vector3::zeros(), DT);
        }
        assert!((l.allowed_force_n() - p.peak_force_n).abs() < 1e-9);
    }

    #[test]
    fn the_continuous_budget_is_the_first_order_motor_model() {
        // Held from cold, the peak lasts `peak_hold_s` (1.1 s for the Touch), then the force
        // settles at the continuous rating, and the thermal state never passes the budget.
        let mut l = live();
        let p = l.profile().clone();
        let hold = p.peak_hold_s();
        assert!((hold - 1.096).abs() < 0.01, "peak hold {hold} s");
        let push = Vector3::new(0.0, 3.0, -4.0);
        let mut last_peak_tick = 0;
        for tick in 1..=30_000 {
            l.pose_received();
            let f = l.step(push, DT);
            if (f.norm() - p.peak_force_n).abs() < 1e-9 {
                last_peak_tick = tick;
            }
            assert!(l.thermal_load() <= 1.0 + 1e-12, "tick {tick}: load {}", l.thermal_load());
        }
        let held = f64::from(last_peak_tick) * DT;
        // The 16.5 ms ramp up to the peak heats less than the peak would: it starts the hold later.
        assert!((held - hold - 0.008).abs() < 0.006, "the peak was held {held} s, the model says {hold} s");
        assert!((l.output_n().norm() - p.continuous_force_n).abs() < 1e-3, "{}", l.output_n().norm());
        // At or below the continuous force the budget is never used up: the force is never cut.
        let mut l = live();
        let at_rating = Vector3::new(p.continuous_force_n, 0.0, 0.0);
        for _ in 0..120_000 {
            l.pose_received();
            assert!((l.step(at_rating, DT) - at_rating).norm() < 1e-9 || l.output_n().norm() < p.continuous_force_n);
        }
        assert!((l.output_n().norm() - p.continuous_force_n).abs() < 1e-9, "{}", l.output_n().norm());
    }

    #[test]
    fn stale_input_ramps_the_force_to_zero_and_fresh_input_resumes() {
        let mut l = live();
        let push = Vector3::new(2.0, 0.0, 0.0);
        for _ in 0..100 {
            l.pose_received();
            l.step(push, DT);
        }
        assert!((l.output_n().norm() - 2.0).abs() < 1e-9);
        // No pose for 50 ms: the force holds, then ramps down at the rate limit.
        let mut history = Vec::new();
        for _ in 0..100 {
            history.push(l.step(push, DT).norm());
        }
        assert!(history[45] > 1.99, "held while fresh");
        assert!(l.is_stale());
        let zero_at = history.iter().position(|&f| f == 0.0).expect("reaches zero");
        assert!((50..=62).contains(&zero_at), "2 N at 200 N/s takes 10 ms after 50 ms; got {zero_at} ms");
        l.pose_received();
        assert!(l.step(push, DT).norm() > 0.0);
    }

    #[test]
    fn nothing_is_rendered_before_the_first_pose_and_bad_dt_holds() {
        let mut l = ForceLimiter::new(DeviceProfile::default()).unwrap();
        assert_eq!(l.step(Vector3::new(1.0, 1.0, 1.0), DT), Vector3::zeros());
        l.pose_received();
        let f = l.step(Vector3::new(1.0, 0.0, 0.0), DT);
        for dt in [f64::NAN, 0.0, -1.0, f64::INFINITY] {
            assert_eq!(l.step(Vector3::new(3.0, 0.0, 0.0), dt), f);
        }
    }

    #[test]
    fn invalid_profiles_are_rejected() {
        let p = DeviceProfile { continuous_force_n: 5.0, ..DeviceProfile::default() };
        assert!(ForceLimiter::new(p).is_err());
        let p = DeviceProfile { max_force_rate_n_per_s: f64::NAN, ..DeviceProfile::default() };
        assert!(ForceLimiter::new(p).is_err());
        let p = DeviceProfile { peak_force_n: 0.0, ..DeviceProfile::default() };
        assert!(ForceLimiter::new(p).is_err());
    }
}
