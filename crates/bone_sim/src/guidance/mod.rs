//! Guidance: the share of the rendered force that DHG adds to the bone's, computed in the 1 kHz
//! loop of every session (offline and in `dhg-serve` alike) in one of four modes.
//!
//! - [`GuidanceMode::Paper`]: the paper's force-matching cue (Fekri et al. 2021, section 2.4).
//!   Each model reply sets a target, the predicted expert force minus the trainee's force
//!   feedback at that moment; the share follows `gain · target`, clamped to `max_n` and moved at
//!   most `max_rate_n_per_s`, so a new target is a ramp and a lost model a fade-out.
//! - [`GuidanceMode::Corridor`]: a guidance virtual fixture (Rosenberg 1993; Abbott, Marayong &
//!   Okamura 2007): a compliant corridor around the planned line A→B. Beyond a deadband, a
//!   spring–damper pulls the tip back towards the line, at right angles to the drill axis only:
//!   it never pushes or holds the drill along its axis. Capped at `max_n`.
//! - [`GuidanceMode::Brake`]: a breakthrough watcher in the force loop (after the force-drop
//!   detection of Ong & Bouazza-Marouf 1999, which stops a drill within about 1 mm). When the
//!   cortex starts to give, the guidance renders a hold along the axis against further advance,
//!   a stiff spring–damper from where the tip was, capped by a force that decays over a few
//!   hundred milliseconds, so the hand surging on meets resistance before any human reaction
//!   (150–250 ms) could act. Plus the model's axial cue read as motion guidance, over the last
//!   `warning_span_m` before the predicted breakthrough: where the expert pushed less than the
//!   trainee (the paper's cue would pull the drill in), a resistance of that size; where the
//!   expert pushed harder, nothing. This mode never pushes the drill forward. (Passing the
//!   paper's cue where it pushes back, "the expert pressed harder", would ask a trainee who
//!   yields to resistance to stop in every cortex: measured, such novices never entered the
//!   bone. Rendering the resisting cue everywhere made them crawl: 55 s instead of 5 s through
//!   the first cortex.)
//! - [`GuidanceMode::Shaped`]: corridor + brake + a warning as the predicted breakthrough nears:
//!   a soft resistive ramp along the axis over the last `warning_span_m` before it, growing to
//!   `warning_n`. A ramp rather than a vibration: the Touch renders a low force faithfully but a
//!   vibration strong enough to notice through the stylus costs force the limits are better spent
//!   on, and a gentle rise in resistance asks for what experts do there, ease off (Wallace et al.
//!   2019: controlled advancement, 0.9 mm of plunge against 4.2 mm).
//!
//! In every mode the gain scales the whole share (0: no guidance), and the share fades out over
//! `fade_s` when the model is lost (no reply younger than `timeout_s`), as the paper's cue does.
//! The session's device limiter bounds the sum of bone force and share, so no mode can leave the
//! device's limits. The guide allocates nothing and takes no locks.

mod fading;
mod params;
#[cfg(test)]
mod tests;

use nalgebra::{Point3, Vector3};

pub use fading::{Fading, FadingParams, FadingSchedule};
pub use params::GuidanceParams;

use crate::error::{SimError, SimResult};
use crate::path::PlannedPath;
use crate::volume::rounding;

/// Largest accepted guidance gain: the project's bound, not from a source. The paper's cue is
/// gain × (expert − trainee) force, and every share is clamped to the device's limits whatever the
/// gain, so the bound only keeps a mistyped gain from saturating every cue.
pub const MAX_GAIN: f64 = 4.0;

/// The default [`GuidanceParams::warning_feed_m_s`] (m/s), the safe feed: half a novice's
/// preferred feed (0.7–1.1 mm/s in `dhg.operators.styles.sample_style`), within the 0.3–0.6 mm/s
/// at which controlled advancement through a far cortex keeps the plunge under a millimetre
/// (Wallace et al. 2019). The warning resists only the feed into bone beyond it (in full at
/// twice it), as assistance given as needed (Marchal-Crespo & Reinkensmeyer 2008): a trainee
/// already that slow, or a drill that cuts cortex no faster (a 4.5 mm burr: 0.1 mm/s typical),
/// feels nothing. Tuned on seeds 3–8: a warning by position alone held trainees who yield to it
/// still in the last millimetre of cortex (3 of 6 reached B against 5 of 6 unguided); one in
/// proportion to the feed below it cost a 4.5 mm drill 43 s (4 of 6 reached B), this one 26 s
/// (5 of 6), with the 2.5 mm plunge still cut by 70 % or more (docs/results.md).
pub const WARNING_FEED_M_S: f64 = 0.5e-3;

/// Time constant of the low-pass through which every damper of the guide (the corridor's, the
/// brake's) sees the tip's velocity (s): 5 ms, a 32 Hz corner. The velocity is a finite
/// difference of the 1 kHz tip, which moves in steps as voxels go: a damper on it chatters (Colgate & Brown 1994: velocity from differenced position must be filtered
/// before a virtual damper acts on it). Unfiltered, the brake's 20 N·s/m turned that into swings
/// of the cue above 0.1 N at hundreds of hertz, which a hand feels as a buzz: an operator told
/// that a buzz means "pause, the bone is hot" paused at 7 of 10 breakthroughs (seeds 3–12,
/// `brake`, up to 0.41 s). The spring parts act at once; the dampers gain a few milliseconds.
pub const VELOCITY_FILTER_S: f64 = 5e-3;

/// Time constant of the feed the warning and the brake's model cue compare with
/// `warning_feed_m_s` (s); the project's choice, for the reason below. The tip can advance in steps, tick by tick 0 or tens of mm/s, never
/// the 0.5–1 mm/s of a feed, so a law that scales by feed needs the feed over tens of
/// milliseconds. Read from the 1 kHz tip velocity, the warning flickered between nothing and its
/// full force from one tick to the next, a buzz in the handle.
pub const FEED_FILTER_S: f64 = 50e-3;

/// What the guidance share renders.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Default, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum GuidanceMode {
    /// The paper's force-matching cue: predicted expert force − the trainee's force.
    Paper,
    /// A lateral corridor around the planned path.
    Corridor,
    /// A hold along the axis when the cortex gives, and the model's cue where it resists.
    Brake,
    /// Corridor + brake + a warning ramp before the predicted breakthrough (the default).
    #[default]
    Shaped,
}

impl GuidanceMode {
    /// Every mode, in the order the docs list them.
    pub const ALL: [GuidanceMode; 4] = [Self::Paper, Self::Corridor, Self::Brake, Self::Shaped];
    /// The allowed names, as error messages quote them.
    pub const NAMES: &'static str = "paper, corridor, brake, shaped";

    /// The mode's name on the wire and in Python.
    #[must_use]
    pub fn name(self) -> &'static str {
        match self {
            Self::Paper => "paper",
            Self::Corridor => "corridor",
            Self::Brake => "brake",
            Self::Shaped => "shaped",
        }
    }

    /// The mode called `name`.
    ///
    /// # Errors
    /// `InvalidOption` for any other name.
    pub fn from_name(name: &str) -> SimResult<Self> {
        Self::ALL.into_iter().find(|m| m.name() == name).ok_or_else(|| SimError::InvalidOption {
            name: "guidance mode",
            value: name.to_owned(),
            allowed: Self::NAMES,
        })
    }

    fn corridor(self) -> bool {
        matches!(self, Self::Corridor | Self::Shaped)
    }

    fn brake(self) -> bool {
        matches!(self, Self::Brake | Self::Shaped)
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

/// What the guide needs to know about the drill this tick.
#[derive(Debug, Clone, Copy)]
pub struct GuideInput<'a> {
    /// The drill tip (m).
    pub tip_m: Point3<f64>,
    /// The tip's velocity (m/s).
    pub tip_velocity_m_s: Vector3<f64>,
    /// The feed into bone this tick (m/s along the axis): how fast the burr cuts its way on,
    /// 0 while it cuts nothing (in air, in its own bore, with the drill off). What the warning
    /// and the brake's model cue ask to slow down.
    pub cutting_feed_m_s: f64,
    /// The drill axis (unit).
    pub axis: Vector3<f64>,
    /// The planned path.
    pub path: &'a PlannedPath,
    /// Where along A→B the first cortex is predicted to give (m of tip depth), if known.
    pub breakthrough_depth_m: Option<f64>,
    /// Whether the first cortex has given way already.
    pub broken_through: bool,
    /// Whether a cortex began to give way this tick (the session's breakthrough watcher).
    pub giving: bool,
    /// The drill-tip temperature (°C).
    pub temperature_c: f64,
    /// The session's necrosis threshold (°C; 47 by default).
    pub necrosis_threshold_c: f64,
}

#[derive(Debug, Clone, Copy)]
struct Hold {
    from_m: Point3<f64>,
    axis: Vector3<f64>,
    age_s: f64,
}

/// One session's guidance (no allocation; runs on the tick thread).
#[derive(Debug, Clone)]
pub struct Guide {
    params: GuidanceParams,
    mode: GuidanceMode,
    gain: f64,
    target_n: Vector3<f64>,
    target_age_s: f64,
    paper_n: Vector3<f64>,
    fade: f64,
    hold: Option<Hold>,
    was_giving: bool,
    heat: Option<HeatHold>,
    /// The corridor's integral of the offset beyond its deadband (m·s), across the path.
    corridor_integral_m_s: Vector3<f64>,
    /// The tip's velocity through [`VELOCITY_FILTER_S`] (m/s): what the laws damp.
    velocity_m_s: Vector3<f64>,
    /// The feed into bone through [`FEED_FILTER_S`] (m/s): what the warning reads.
    feed_m_s: f64,
    share_n: Vector3<f64>,
}

#[derive(Debug, Clone, Copy)]
struct HeatHold {
    from_m: Point3<f64>,
    axis: Vector3<f64>,
    engaged_c: f64,
    /// Time since it engaged (s): the heat cue's phase.
    age_s: f64,
}

impl Guide {
    /// A guide with no model target yet.
    #[must_use]
    pub fn new(params: GuidanceParams, mode: GuidanceMode, gain: f64) -> Self {
        Self {
            params,
            mode,
            gain,
            target_n: Vector3::zeros(),
            target_age_s: f64::INFINITY,
            paper_n: Vector3::zeros(),
            fade: 0.0,
            hold: None,
            was_giving: false,
            heat: None,
            corridor_integral_m_s: Vector3::zeros(),
            velocity_m_s: Vector3::zeros(),
            feed_m_s: 0.0,
            share_n: Vector3::zeros(),
        }
    }

    /// Back to no target and no share, keeping params, mode and gain.
    pub fn reset(&mut self) {
        // Field by field: the params (a profile is a Vec) stay where they are, so a reset on the
        // tick thread allocates nothing.
        self.target_n = Vector3::zeros();
        self.target_age_s = f64::INFINITY;
        self.paper_n = Vector3::zeros();
        self.fade = 0.0;
        self.hold = None;
        self.was_giving = false;
        self.heat = None;
        self.corridor_integral_m_s = Vector3::zeros();
        self.velocity_m_s = Vector3::zeros();
        self.feed_m_s = 0.0;
        self.share_n = Vector3::zeros();
    }

    /// The limits and laws.
    #[must_use]
    pub fn params(&self) -> &GuidanceParams {
        &self.params
    }

    /// Replaces the limits and laws.
    ///
    /// # Errors
    /// Invalid params (nothing changes then).
    pub fn set_params(&mut self, params: GuidanceParams) -> SimResult<()> {
        params.validate()?;
        self.params = params;
        Ok(())
    }

    /// Sets the mode (the share then changes at the rates each part allows).
    pub fn set_mode(&mut self, mode: GuidanceMode) {
        self.mode = mode;
    }

    /// The mode.
    #[must_use]
    pub fn mode(&self) -> GuidanceMode {
        self.mode
    }

    /// Sets the gain (already checked with [`check_gain`]).
    pub fn set_gain(&mut self, gain: f64) {
        self.gain = gain;
    }

    /// The gain.
    #[must_use]
    pub fn gain(&self) -> f64 {
        self.gain
    }

    /// A model reply: the paper's guidance (N), predicted expert force − the trainee's force.
    /// Non-finite targets are ignored. Returns what the paper cue will aim at, `gain · target`
    /// clamped to `max_n`.
    pub fn set_target(&mut self, guidance_n: Vector3<f64>) -> Vector3<f64> {
        if guidance_n.iter().all(|x| x.is_finite()) {
            self.target_n = guidance_n;
            self.target_age_s = 0.0;
        }
        self.clamped(self.target_n * self.gain)
    }

    /// Whether the newest model reply is still fresh.
    #[must_use]
    pub fn is_live(&self) -> bool {
        self.target_age_s <= self.params.timeout_s
    }

    /// The share rendered on the last step (N).
    #[must_use]
    pub fn share_n(&self) -> Vector3<f64> {
        self.share_n
    }

    /// Whether the brake is holding.
    #[must_use]
    pub fn is_braking(&self) -> bool {
        self.hold.is_some()
    }

    /// Whether the heat cue and hold are on (`shaped`: the tip is hot and has not cooled yet).
    #[must_use]
    pub fn is_heat_holding(&self) -> bool {
        self.heat.is_some()
    }

    fn clamped(&self, v: Vector3<f64>) -> Vector3<f64> {
        let n = v.norm();
        if n > self.params.max_n {
            v * (self.params.max_n / n)
        } else {
            v
        }
    }

    /// Advances by `dt_s` and returns the share to add to the bone's force (N).
    pub fn step(&mut self, input: &GuideInput<'_>, dt_s: f64) -> Vector3<f64> {
        if input.tip_velocity_m_s.iter().all(|x| x.is_finite()) {
            let v = input.tip_velocity_m_s;
            self.velocity_m_s += (v - self.velocity_m_s) * (dt_s / (VELOCITY_FILTER_S + dt_s));
        }
        if input.cutting_feed_m_s.is_finite() {
            self.feed_m_s += (input.cutting_feed_m_s - self.feed_m_s) * (dt_s / (FEED_FILTER_S + dt_s));
        }
        let filtered = GuideInput { tip_velocity_m_s: self.velocity_m_s, ..*input };
        let input = &filtered;
        let p = &self.params;
        self.target_age_s += dt_s;
        let live = self.is_live();
        // The paper cue: gain · target, clamped and rate-limited, fading out when the model is lost.
        let want = if live { self.clamped(self.target_n * self.gain) } else { Vector3::zeros() };
        let delta = want - self.paper_n;
        let max_step = p.max_rate_n_per_s * dt_s;
        let d = delta.norm();
        self.paper_n += if d > max_step { delta * (max_step / d) } else { delta };
        let step = dt_s / p.fade_s;
        self.fade = if live { (self.fade + step).min(1.0) } else { (self.fade - step).max(0.0) };

        // The brake arms when a cortex starts to give, once per give.
        if self.mode.brake() && input.giving && !self.was_giving && self.hold.is_none() {
            self.hold = Some(Hold { from_m: input.tip_m, axis: input.axis, age_s: 0.0 });
        }
        self.was_giving = input.giving;

        let share = match self.mode {
            GuidanceMode::Paper => self.paper_n,
            mode => {
                let mut f = Vector3::zeros();
                if mode.corridor() {
                    f += self.corridor(input, dt_s);
                }
                if mode.brake() {
                    f += self.brake(input, dt_s);
                    // The model's axial cue, read as motion guidance: where the expert pushed less
                    // than the trainee does (the paper's cue would pull the drill in), resist the
                    // push by as much; where the expert pushed harder, render nothing. Never forward.
                    // Only near the predicted breakthrough, where easing off is what experts do:
                    // elsewhere a trainee who yields to it crawls (measured: 55 s instead of 5 s
                    // through the first cortex, and 65 % fewer novices reaching B in 150 s).
                    let ease_n = self.paper_n.dot(&input.axis);
                    if ease_n > 0.0 && self.near_breakthrough(input) {
                        f -= input.axis * (ease_n * self.slow_down());
                    }
                }
                if mode == GuidanceMode::Shaped {
                    f += self.warning(input);
                    f += self.heat(input, dt_s);
                }
                f * self.fade
            }
        };
        self.share_n = if share.iter().all(|x| x.is_finite()) { share } else { Vector3::zeros() };
        self.share_n
    }

    /// The corridor's lateral force: towards the line A→B, at right angles to the drill axis.
    fn corridor(&mut self, input: &GuideInput<'_>, dt_s: f64) -> Vector3<f64> {
        let p = &self.params;
        let d = input.path.direction();
        let rel = input.tip_m - input.path.entry_m();
        let off = rel - d * rel.dot(&d);
        let dist = off.norm();
        let ti = p.corridor_integral_s;
        if dist <= p.corridor_deadband_m {
            if ti > 0.0 {
                self.corridor_integral_m_s *= (1.0 - dt_s / ti).max(0.0);
            }
            return Vector3::zeros();
        }
        let out = off / dist;
        let v_out = input.tip_velocity_m_s.dot(&out);
        let profile = &p.corridor_profile_n_per_m;
        let k = if profile.is_empty() {
            p.corridor_stiffness_n_per_m
        } else {
            let bin = rounding::floor(rel.dot(&d) / p.corridor_profile_bin_m).max(0.0) as usize;
            profile[bin.min(profile.len() - 1)]
        };
        let beyond = out * (dist - p.corridor_deadband_m);
        let mut f = -(beyond * k + out * (p.corridor_damping_n_s_per_m * v_out));
        if ti > 0.0 && k > 0.0 {
            // Anti-windup: the integral's own pull never exceeds the cap.
            self.corridor_integral_m_s += beyond * dt_s;
            let most = p.max_n * ti / k;
            let n = self.corridor_integral_m_s.norm();
            if n > most {
                self.corridor_integral_m_s *= most / n;
            }
            f -= self.corridor_integral_m_s * (k / ti);
        }
        f -= input.axis * f.dot(&input.axis);
        self.clamped(f * self.gain)
    }

    /// The brake's hold along the axis: against advance only, decaying.
    fn brake(&mut self, input: &GuideInput<'_>, dt_s: f64) -> Vector3<f64> {
        let p = &self.params;
        let Some(hold) = self.hold.as_mut() else { return Vector3::zeros() };
        hold.age_s += dt_s;
        let cap = p.brake_hold_n * self.gain * (-hold.age_s / p.brake_decay_s).exp();
        if cap < 0.01 * p.brake_hold_n * self.gain.max(1e-9) || self.gain == 0.0 {
            self.hold = None;
            return Vector3::zeros();
        }
        let (from_m, axis) = (hold.from_m, hold.axis);
        self.resist_advance(input, from_m, axis, cap)
    }

    /// The brake's law, shared by the heat hold: against advance along `axis` past `from_m`, a
    /// spring and a damper on forward motion, scaled by the gain and capped at `cap_n`; never
    /// forward.
    fn resist_advance(
        &self,
        input: &GuideInput<'_>,
        from_m: Point3<f64>,
        axis: Vector3<f64>,
        cap_n: f64,
    ) -> Vector3<f64> {
        let p = &self.params;
        let past = (input.tip_m - from_m).dot(&axis).max(0.0);
        let v_fwd = input.tip_velocity_m_s.dot(&axis).max(0.0);
        let resist = (p.brake_stiffness_n_per_m * past + p.brake_damping_n_s_per_m * v_fwd) * self.gain;
        -axis * resist.min(cap_n)
    }

    /// The heat cue and hold: once the tip comes within `heat_margin_c` of the necrosis
    /// threshold, until it has cooled `heat_release_c` below where they engaged, a vibration along
    /// the axis (`heat_buzz_n` at `heat_buzz_hz`: the cue to pause with the drill off) and a
    /// resistance against advance past where the tip was then (the brake's spring and damper,
    /// capped at `heat_hold_n`, 0 by default). Neither pushes the drill on on average: the
    /// vibration has no mean, the hold never pushes forward.
    fn heat(&mut self, input: &GuideInput<'_>, dt_s: f64) -> Vector3<f64> {
        let p = &self.params;
        let t = input.temperature_c;
        if !t.is_finite() {
            return Vector3::zeros();
        }
        match self.heat {
            None if t >= input.necrosis_threshold_c - p.heat_margin_c => {
                self.heat = Some(HeatHold { from_m: input.tip_m, axis: input.axis, engaged_c: t, age_s: 0.0 });
            }
            Some(h) if t <= h.engaged_c - p.heat_release_c => self.heat = None,
            Some(ref mut h) => h.age_s += dt_s,
            None => {}
        }
        let Some(h) = self.heat else { return Vector3::zeros() };
        let buzz = p.heat_buzz_n * self.gain * (std::f64::consts::TAU * p.heat_buzz_hz * h.age_s).sin();
        self.resist_advance(input, h.from_m, h.axis, p.heat_hold_n * self.gain) - h.axis * buzz
    }

    /// Whether the tip is within `warning_span_m` before the predicted breakthrough, the cortex
    /// not yet through.
    fn near_breakthrough(&self, input: &GuideInput<'_>) -> bool {
        let Some(at) = input.breakthrough_depth_m else { return false };
        let depth = input.path.depth_m(&input.tip_m);
        !input.broken_through && depth >= at - self.params.warning_span_m
    }

    /// The warning: a resistance ramping up over the last span before the predicted breakthrough.
    fn warning(&self, input: &GuideInput<'_>) -> Vector3<f64> {
        let p = &self.params;
        let Some(at) = input.breakthrough_depth_m else { return Vector3::zeros() };
        if input.broken_through {
            return Vector3::zeros();
        }
        let depth = input.path.depth_m(&input.tip_m);
        let ramp = ((depth - (at - p.warning_span_m)) / p.warning_span_m).clamp(0.0, 1.0);
        -input.axis * (p.warning_n * ramp * self.slow_down() * self.gain)
    }

    /// How much of a slow-down request near the breakthrough applies at the feed into bone: 0
    /// up to `warning_feed_m_s` (the safe feed), rising to 1 at twice it; 0 on a tip that cuts
    /// nothing (still, withdrawing, or moving through its own bore).
    fn slow_down(&self) -> f64 {
        let feed = self.params.warning_feed_m_s;
        if feed <= 0.0 {
            return 1.0;
        }
        (self.feed_m_s / feed - 1.0).clamp(0.0, 1.0)
    }
}
