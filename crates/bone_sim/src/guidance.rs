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

use nalgebra::{Point3, Vector3};

use crate::error::{non_negative, positive, SimError, SimResult};
use crate::path::PlannedPath;

/// Largest accepted guidance gain.
pub const MAX_GAIN: f64 = 4.0;

/// The default [`GuidanceParams::warning_feed_m_s`] (m/s): half a novice's preferred feed
/// (0.7–1.1 mm/s in `dhg.operators.styles.sample_style`), near the 0.3–0.6 mm/s at which controlled
/// advancement through a far cortex keeps the plunge under a millimetre (Wallace et al. 2019).
/// Tuned on seeds 3–8: a warning by position alone held trainees who yield to it still in the
/// last millimetre of cortex (3 of 6 reached B against 5 of 6 unguided; docs/results.md).
pub const WARNING_FEED_M_S: f64 = 0.5e-3;

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

/// Guidance limits and force laws (device newtons, SI units).
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct GuidanceParams {
    /// Largest paper-cue and corridor share (N); the Touch's continuous force by default, so
    /// they can be held indefinitely.
    pub max_n: f64,
    /// Fastest change of the paper cue's share (N/s).
    pub max_rate_n_per_s: f64,
    /// Age after which a model reply counts as lost and guidance fades out (s).
    pub timeout_s: f64,
    /// Time over which the other modes' share fades in and out with the model (s).
    pub fade_s: f64,
    /// Half-width of the corridor in which no lateral force acts (m).
    pub corridor_deadband_m: f64,
    /// Corridor stiffness beyond the deadband (N/m).
    pub corridor_stiffness_n_per_m: f64,
    /// Corridor damping of lateral motion beyond the deadband (N·s/m).
    pub corridor_damping_n_s_per_m: f64,
    /// Integral action of the corridor (s): beyond the deadband the pull also grows with the
    /// offset held over time, by stiffness × ∫ offset dt / this, so an arm that holds the tip
    /// off the line against the spring is pulled further over seconds; inside the deadband the
    /// integral leaks with this time constant. 0: no integral action (a spring–damper).
    pub corridor_integral_s: f64,
    /// Corridor stiffness per depth bin along A→B (N/m), from the experts' lateral spread
    /// (`dhg.learning.profiles`: stiff where they agree, compliant where they vary); the last bin holds
    /// beyond the path, the first before A. Empty: `corridor_stiffness_n_per_m` everywhere.
    pub corridor_profile_n_per_m: Vec<f64>,
    /// Width of a corridor profile bin (m).
    pub corridor_profile_bin_m: f64,
    /// Most the brake holds at the moment the cortex gives (N).
    pub brake_hold_n: f64,
    /// Time constant with which the brake's hold decays (s).
    pub brake_decay_s: f64,
    /// Stiffness of the brake's hold against advance past where the cortex gave (N/m).
    pub brake_stiffness_n_per_m: f64,
    /// Damping of the brake against forward motion (N·s/m).
    pub brake_damping_n_s_per_m: f64,
    /// Largest warning resistance, reached at the predicted breakthrough (N).
    pub warning_n: f64,
    /// How far before the predicted breakthrough the warning ramp starts (m).
    pub warning_span_m: f64,
    /// Near the predicted breakthrough, the warning and the model's easing cue ask the trainee to
    /// slow down: at a feed along the axis of this (m/s) or faster they resist in full, slower in
    /// proportion, and not at all on a tip that is still, so a trainee who yields as asked is
    /// slowed and never held still in the cortex. 0: in full at any speed (a resistance by
    /// position alone).
    pub warning_feed_m_s: f64,
    /// `shaped`: the heat hold engages when the tip is within this of the session's necrosis
    /// threshold (°C below it).
    pub heat_margin_c: f64,
    /// `shaped`: the heat hold lets go once the tip has cooled this far below where it engaged (°C).
    pub heat_release_c: f64,
    /// `shaped`: most the heat hold resists advance with (N).
    pub heat_hold_n: f64,
}

impl Default for GuidanceParams {
    fn default() -> Self {
        Self {
            max_n: 0.88,
            max_rate_n_per_s: 8.0,
            timeout_s: 0.35,
            fade_s: 0.25,
            // The experts' lateral spread on the phantom is 0.3 mm mean, 0.8 mm at most
            // (docs/benchmarks.md): inside 0.5 mm the corridor leaves the hand alone.
            corridor_deadband_m: 0.5e-3,
            // 0.88 N at 2.7 mm off the line: at most the Touch's 400 N/m, so it is rendered stably.
            corridor_stiffness_n_per_m: 400.0,
            corridor_damping_n_s_per_m: 2.0,
            // An arm that holds the tip off the line against the spring is pulled further over
            // about a second, as assistance that grows with a persisting error does (Wolbrecht et
            // al. 2008, adaptive assist-as-needed with forgetting): tuning seeds 3-8, instructed
            // operator, max offset across the path -45 % -> -52 % against no guidance (impedance
            // -61 % -> -62 %); 2 s and 3 s did less (docs/results.md).
            corridor_integral_s: 1.0,
            corridor_profile_n_per_m: Vec::new(),
            corridor_profile_bin_m: 1e-3,
            // About the push of a hand drilling cortex on the Touch (1.6–2.7 N), so a surge is
            // met at once; within the 3.3 N peak; decaying with 0.4 s, so it outlasts a novice's
            // 0.25–0.40 s reaction and is down to a tenth within a second.
            brake_hold_n: 2.2,
            brake_decay_s: 0.4,
            brake_stiffness_n_per_m: 400.0,
            brake_damping_n_s_per_m: 20.0,
            warning_n: 0.35,
            warning_span_m: 1.0e-3,
            warning_feed_m_s: WARNING_FEED_M_S,
            // The expert of `dhg synth` pauses with the drill off 2 °C short of 47 °C and goes on
            // once 2 °C cooler (surgeons.py, caution_temp_c), as intermittent drilling lets the bone
            // cool (Pandey & Panda 2013 review the effect of drilling pauses); at a stop the tip
            // cools with the thermal model's 15 s time constant (about 5 s for those 2 °C).
            heat_margin_c: 2.0,
            heat_release_c: 2.0,
            // Off by default: at 1.5 N (under the 1.6–2.7 N a hand pushes through cortex) it slowed
            // the feed instead of pausing it, and a slower feed heats each millimetre more; with a
            // 4.5 mm drill it cost completion and, for the instructed trainee, time above 47 °C
            // (docs/results.md, "A heat hold"). Settable per session for studies.
            heat_hold_n: 0.0,
        }
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
        positive("guidance timeout_s", self.timeout_s)?;
        positive("guidance fade_s", self.fade_s)?;
        non_negative("guidance corridor_deadband_m", self.corridor_deadband_m)?;
        non_negative("guidance corridor_stiffness_n_per_m", self.corridor_stiffness_n_per_m)?;
        non_negative("guidance corridor_damping_n_s_per_m", self.corridor_damping_n_s_per_m)?;
        non_negative("guidance corridor_integral_s", self.corridor_integral_s)?;
        positive("guidance corridor_profile_bin_m", self.corridor_profile_bin_m)?;
        for &k in &self.corridor_profile_n_per_m {
            non_negative("guidance corridor_profile_n_per_m", k)?;
        }
        non_negative("guidance brake_hold_n", self.brake_hold_n)?;
        positive("guidance brake_decay_s", self.brake_decay_s)?;
        non_negative("guidance brake_stiffness_n_per_m", self.brake_stiffness_n_per_m)?;
        non_negative("guidance brake_damping_n_s_per_m", self.brake_damping_n_s_per_m)?;
        non_negative("guidance warning_n", self.warning_n)?;
        positive("guidance warning_span_m", self.warning_span_m)?;
        non_negative("guidance warning_feed_m_s", self.warning_feed_m_s)?;
        non_negative("guidance heat_margin_c", self.heat_margin_c)?;
        positive("guidance heat_release_c", self.heat_release_c)?;
        non_negative("guidance heat_hold_n", self.heat_hold_n).map(|_| ())
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
    share_n: Vector3<f64>,
}

#[derive(Debug, Clone, Copy)]
struct HeatHold {
    from_m: Point3<f64>,
    axis: Vector3<f64>,
    engaged_c: f64,
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

    /// Whether the heat hold is holding (`shaped`: the tip is hot and has not cooled yet).
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
                        f -= input.axis * (ease_n * self.slow_down(input));
                    }
                }
                if mode == GuidanceMode::Shaped {
                    f += self.warning(input);
                    f += self.heat_hold(input);
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
            let bin = (rel.dot(&d) / p.corridor_profile_bin_m).floor().max(0.0) as usize;
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

    /// The heat hold: once the tip comes within `heat_margin_c` of the necrosis threshold, a
    /// resistance against advance past where it was then (the brake's spring and damper, capped
    /// at `heat_hold_n`), until the tip has cooled `heat_release_c` below where it engaged. It asks
    /// for the pause that lets the bone cool; it never pushes the drill forward.
    fn heat_hold(&mut self, input: &GuideInput<'_>) -> Vector3<f64> {
        let p = &self.params;
        let t = input.temperature_c;
        if !t.is_finite() {
            return Vector3::zeros();
        }
        match self.heat {
            None if t >= input.necrosis_threshold_c - p.heat_margin_c => {
                self.heat = Some(HeatHold { from_m: input.tip_m, axis: input.axis, engaged_c: t });
            }
            Some(h) if t <= h.engaged_c - p.heat_release_c => self.heat = None,
            _ => {}
        }
        let Some(h) = self.heat else { return Vector3::zeros() };
        self.resist_advance(input, h.from_m, h.axis, p.heat_hold_n * self.gain)
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
        -input.axis * (p.warning_n * ramp * self.slow_down(input) * self.gain)
    }

    /// How much of a slow-down request near the breakthrough applies at the tip's feed: 1 at
    /// `warning_feed_m_s` or faster, in proportion below, 0 on a still or withdrawing tip.
    fn slow_down(&self, input: &GuideInput<'_>) -> f64 {
        let feed = self.params.warning_feed_m_s;
        if feed <= 0.0 {
            return 1.0;
        }
        (input.tip_velocity_m_s.dot(&input.axis) / feed).clamp(0.0, 1.0)
    }
}

/// How the guidance gain fades over a trainee's attempts: assistance as needed, with
/// guidance-free probe attempts.
///
/// After each attempt the assistance follows the trainee's error with forgetting,
/// `a ← clamp(forget · a + learn · e, 0, max_gain)`, the error-based update with a forgetting
/// factor of Emken et al. 2007 (motor adaptation as error and effort) that Emken et al. 2008
/// used to let a robot's assistance fall as stepping improved. The error `e` is the worse of
/// the attempt's plunge and maximum lateral deviation, each over its tolerance. Assistance
/// therefore decays while the guided trainee drills within tolerance and rises when they do not;
/// at equilibrium `a = learn · e / (1 − forget)`. Every `probe_every`-th attempt renders no
/// guidance (a probe, after the guidance hypothesis: Schmidt & Bjork 1992; Marchal-Crespo &
/// Reinkensmeyer 2008), so the trainee's own skill is measured and they do not come to rely on it.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct FadingParams {
    /// Gain of the first attempt (0..=`MAX_GAIN`).
    pub start_gain: f64,
    /// Most assistance the schedule gives (0..=`MAX_GAIN`).
    pub max_gain: f64,
    /// Fraction of the assistance kept from one attempt to the next (0..1).
    pub forget: f64,
    /// Assistance added per unit of error (≥ 0).
    pub learn: f64,
    /// Plunge within tolerance (m): about the 1 mm that force-drop auto-stop drills leave
    /// (Ong & Bouazza-Marouf 1999) and controlled advancement reached (0.9 mm, Wallace et al. 2019).
    pub plunge_tolerance_m: f64,
    /// Maximum lateral deviation within tolerance (m): the task's 3 mm.
    pub deviation_tolerance_m: f64,
    /// Every this many attempts one is a guidance-free probe (0: none).
    pub probe_every: u32,
}

impl Default for FadingParams {
    fn default() -> Self {
        // forget 0.7 and learn 0.2: a trainee at 1.5 times the tolerance keeps gain 1 (0.2·1.5/0.3);
        // one at the tolerance sees it fall towards 0.67, one at half of it towards 0.33.
        Self {
            start_gain: 1.0,
            max_gain: 1.0,
            forget: 0.7,
            learn: 0.2,
            plunge_tolerance_m: 1.0e-3,
            deviation_tolerance_m: 3.0e-3,
            probe_every: 4,
        }
    }
}

impl FadingParams {
    /// Checks every field.
    ///
    /// # Errors
    /// A value out of its range.
    pub fn validate(&self) -> SimResult<()> {
        check_gain(self.start_gain)?;
        check_gain(self.max_gain)?;
        if !(self.forget.is_finite() && (0.0..1.0).contains(&self.forget)) {
            return Err(SimError::InvalidParameter {
                name: "fading forget",
                value: self.forget,
                reason: "must be within 0..1",
            });
        }
        non_negative("fading learn", self.learn)?;
        positive("fading plunge_tolerance_m", self.plunge_tolerance_m)?;
        positive("fading deviation_tolerance_m", self.deviation_tolerance_m).map(|_| ())
    }
}

impl FadingParams {
    /// Params from a JSON object; missing fields take their defaults.
    ///
    /// # Errors
    /// `Payload` for an unknown field or a wrong type; `InvalidParameter` for a value out of range.
    pub fn from_json(v: &serde_json::Value) -> SimResult<Self> {
        let p: Self = serde_json::from_value(v.clone())
            .map_err(|e| SimError::Payload { message: "fading", reason: e.to_string() })?;
        p.validate()?;
        Ok(p)
    }
}

/// One trainee's fading schedule: the attempt count, the assistance and this attempt's gain.
#[derive(Debug, Clone, PartialEq)]
pub struct Fading {
    params: FadingParams,
    attempts: u32,
    assistance: f64,
    last_error: f64,
}

impl Fading {
    /// A schedule at its first attempt.
    ///
    /// # Errors
    /// Invalid params.
    pub fn new(params: FadingParams) -> SimResult<Self> {
        params.validate()?;
        let assistance = params.start_gain.min(params.max_gain);
        Ok(Self { params, attempts: 0, assistance, last_error: f64::NAN })
    }

    /// The params.
    #[must_use]
    pub fn params(&self) -> &FadingParams {
        &self.params
    }

    /// Attempts finished so far.
    #[must_use]
    pub fn attempts(&self) -> u32 {
        self.attempts
    }

    /// The assistance the next guided attempt gets.
    #[must_use]
    pub fn assistance(&self) -> f64 {
        self.assistance
    }

    /// The last finished attempt's normalised error (NaN before the first).
    #[must_use]
    pub fn last_error(&self) -> f64 {
        self.last_error
    }

    /// Whether the current attempt is a guidance-free probe.
    #[must_use]
    pub fn is_probe(&self) -> bool {
        let n = self.params.probe_every;
        n > 0 && (self.attempts + 1) % n == 0
    }

    /// The gain of the current attempt: 0 on a probe, else the assistance.
    #[must_use]
    pub fn gain(&self) -> f64 {
        if self.is_probe() {
            0.0
        } else {
            self.assistance
        }
    }

    /// The schedule as JSON: params, attempts, assistance, this attempt's gain, whether it is a
    /// probe, and the last attempt's error (null before the first).
    #[must_use]
    pub fn to_json(&self) -> serde_json::Value {
        serde_json::json!({
            "params": self.params,
            "attempts": self.attempts,
            "assistance": self.assistance,
            "gain": self.gain(),
            "probe": self.is_probe(),
            "last_error": if self.last_error.is_finite() { Some(self.last_error) } else { None },
        })
    }

    /// Ends an attempt with its largest plunge and lateral deviation (m); returns the next
    /// attempt's gain. Non-finite errors count as the tolerance (no change of evidence).
    pub fn finish_attempt(&mut self, plunge_m: f64, max_deviation_m: f64) -> f64 {
        let p = &self.params;
        let ratio = |v: f64, tol: f64| if v.is_finite() { v.max(0.0) / tol } else { 1.0 };
        let e = ratio(plunge_m, p.plunge_tolerance_m).max(ratio(max_deviation_m, p.deviation_tolerance_m));
        self.last_error = e;
        self.assistance = (p.forget * self.assistance + p.learn * e).clamp(0.0, p.max_gain);
        self.attempts += 1;
        self.gain()
    }
}

#[cfg(test)]
#[allow(clippy::float_cmp)] // exact zeros are intended here
mod tests {
    use super::*;

    fn path() -> PlannedPath {
        PlannedPath::new(Point3::origin(), Point3::new(0.0, 0.0, 0.08)).unwrap()
    }

    fn input(path: &PlannedPath, tip: Point3<f64>, v: Vector3<f64>) -> GuideInput<'_> {
        GuideInput {
            tip_m: tip,
            tip_velocity_m_s: v,
            axis: Vector3::z(),
            path,
            breakthrough_depth_m: Some(0.01),
            broken_through: false,
            giving: false,
            temperature_c: 37.0,
            necrosis_threshold_c: 47.0,
        }
    }

    fn live(mode: GuidanceMode) -> Guide {
        let mut g = Guide::new(GuidanceParams::default(), mode, 1.0);
        g.set_target(Vector3::zeros());
        for _ in 0..300 {
            let p = path();
            g.step(&input(&p, Point3::new(0.0, 0.0, 0.005), Vector3::zeros()), 1e-3);
            g.set_target(Vector3::zeros());
        }
        g
    }

    #[test]
    fn the_paper_cue_ramps_clamps_and_fades_out_when_the_model_goes_quiet() {
        let p = GuidanceParams::default();
        let path = path();
        let at = input(&path, Point3::new(0.0, 0.0, 0.005), Vector3::zeros());
        let mut m = Guide::new(p.clone(), GuidanceMode::Paper, 1.0);
        let aimed = m.set_target(Vector3::new(5.0, 0.0, 0.0));
        assert!((aimed.norm() - p.max_n).abs() < 1e-12, "the target as mixed is clamped: {aimed}");
        let first = m.step(&at, 1e-3);
        assert!((first.x - p.max_rate_n_per_s * 1e-3).abs() < 1e-12, "a step is a ramp: {first}");
        let mut last = first;
        for _ in 0..300 {
            last = m.step(&at, 1e-3);
        }
        assert!((last.norm() - p.max_n).abs() < 1e-9, "clamped to max_n: {last}");
        let mut prev = last.norm();
        for _ in 0..1000 {
            let now = m.step(&at, 1e-3).norm();
            assert!(prev - now <= p.max_rate_n_per_s * 1e-3 + 1e-12);
            prev = now;
        }
        assert!(!m.is_live() && prev < 1e-12, "faded out: {prev}");
    }

    #[test]
    fn zero_gain_mixes_nothing_and_bad_gains_and_modes_are_refused() {
        let path = path();
        for mode in GuidanceMode::ALL {
            let mut m = Guide::new(GuidanceParams::default(), mode, 0.0);
            for _ in 0..500 {
                m.set_target(Vector3::new(0.5, 0.5, -0.5));
                let mut i = input(&path, Point3::new(0.004, 0.0, 0.0095), Vector3::new(0.0, 0.0, 0.05));
                i.giving = true;
                assert_eq!(m.step(&i, 1e-3), Vector3::zeros(), "{mode:?}");
            }
        }
        assert!(check_gain(-0.1).is_err() && check_gain(f64::NAN).is_err() && check_gain(4.5).is_err());
        assert_eq!(check_gain(0.5), Ok(0.5));
        assert!(GuidanceMode::from_name("stiff").unwrap_err().to_string().contains("paper, corridor, brake, shaped"));
        for m in GuidanceMode::ALL {
            assert_eq!(GuidanceMode::from_name(m.name()), Ok(m));
        }
    }

    #[test]
    fn the_corridor_acts_only_across_the_axis_beyond_its_deadband_and_is_capped() {
        let path = path();
        let mut g = live(GuidanceMode::Corridor);
        let p = g.params().clone();
        let mut last = 0.0;
        for off_mm in [0.0, 0.3, 0.5, 0.8, 1.5, 3.0, 10.0, 50.0] {
            let tip = Point3::new(off_mm * 1e-3, 0.0, 0.02);
            let f = g.step(&input(&path, tip, Vector3::new(0.0, 0.0, 0.003)), 1e-3);
            g.set_target(Vector3::zeros());
            assert!(f.z.abs() < 1e-12, "{off_mm} mm: a force {f} along the drill axis");
            if off_mm * 1e-3 <= p.corridor_deadband_m {
                assert_eq!(f, Vector3::zeros(), "{off_mm} mm is inside the deadband");
            } else {
                assert!(f.x < 0.0 && f.y.abs() < 1e-12, "{off_mm} mm: {f} does not point back to the line");
                assert!(f.norm() >= last - 1e-12 && f.norm() <= p.max_n + 1e-12, "{off_mm} mm: {f}");
            }
            last = f.norm();
        }
        assert!((last - p.max_n).abs() < 1e-9, "far off the path the corridor is capped: {last}");
    }

    #[test]
    fn a_corridor_profile_sets_the_stiffness_per_depth() {
        let path = path();
        let mut g = live(GuidanceMode::Corridor);
        let mut p = g.params().clone();
        p.corridor_damping_n_s_per_m = 0.0;
        p.corridor_integral_s = 0.0;
        p.corridor_profile_n_per_m = vec![400.0, 100.0];
        p.corridor_profile_bin_m = 5e-3;
        g.set_params(p.clone()).unwrap();
        // 1.5 mm off the line (1 mm past the deadband): 0.4 N in the first 5 mm, 0.1 N after, and
        // the last bin's stiffness beyond the path's end.
        for (z, want) in [(-0.002, 0.4), (0.002, 0.4), (0.007, 0.1), (0.5, 0.1)] {
            let f = g.step(&input(&path, Point3::new(1.5e-3, 0.0, z), Vector3::zeros()), 1e-3);
            assert!((f.x + want).abs() < 1e-9 && f.z.abs() < 1e-12, "z {z}: {f}");
        }
        p.corridor_profile_n_per_m = vec![f64::NAN];
        assert!(g.set_params(p).is_err(), "a NaN stiffness was accepted");
    }

    #[test]
    fn the_corridor_pull_grows_with_an_offset_held_capped_and_leaks_away_inside_the_deadband() {
        let path = path();
        let mut g = live(GuidanceMode::Corridor);
        let mut p = g.params().clone();
        p.corridor_damping_n_s_per_m = 0.0;
        p.corridor_integral_s = 1.0;
        g.set_params(p.clone()).unwrap();
        let at = |g: &mut Guide, off_m: f64| {
            let f = g.step(&input(&path, Point3::new(off_m, 0.0, 0.02), Vector3::zeros()), 1e-3);
            g.set_target(Vector3::zeros());
            assert!(f.z.abs() < 1e-12 && f.y.abs() < 1e-12 && f.x <= 0.0, "{f}");
            -f.x
        };
        // 1 mm past the deadband at 400 N/m: 0.4 N of spring at once, and after 0.5 s held there
        // 0.4 N × (1 + 0.5 s / 1 s) = 0.6 N.
        let off = p.corridor_deadband_m + 1e-3;
        let first = at(&mut g, off);
        assert!((first - 0.4).abs() < 1e-3, "{first}");
        let mut half = 0.0;
        for _ in 1..500 {
            half = at(&mut g, off);
        }
        assert!((half - 0.6).abs() < 2e-3, "after 0.5 s: {half}");
        // Held on, the integral winds up no further than the device's continuous limit.
        for _ in 0..5000 {
            assert!(at(&mut g, off) <= p.max_n + 1e-12);
        }
        assert!((at(&mut g, off) - p.max_n).abs() < 1e-9);
        // Back inside the deadband there is no force, and the held error leaks away: after 5 s
        // there the same offset meets the spring, e^-5 of the wound-up pull (at most 0.88 N) and
        // the new tick's 0.4 mN.
        for _ in 0..5000 {
            assert_eq!(at(&mut g, 0.0), 0.0);
        }
        let again = at(&mut g, off);
        assert!(again > 0.4 && again < 0.4 + 0.88 * 0.0068 + 0.4e-3, "the integral did not leak: {again}");
        // A reset forgets it at once.
        for _ in 0..1000 {
            at(&mut g, off);
        }
        g.reset();
        g.set_target(Vector3::zeros());
        // (0.3 s on the line for the cue to fade back in after the reset: a leak alone would
        // leave 74 % of the pull.)
        for _ in 0..300 {
            at(&mut g, 0.0);
        }
        let after_reset = at(&mut g, off);
        assert!((after_reset - 0.4).abs() < 1e-3, "{after_reset}");
        p.corridor_integral_s = -1.0;
        assert!(g.set_params(p).is_err(), "a negative integral time was accepted");
    }

    #[test]
    fn the_brake_holds_at_once_never_pushes_forward_and_lets_go() {
        let path = path();
        let mut g = live(GuidanceMode::Brake);
        let p = g.params().clone();
        // The cortex gives at z = 10 mm; the tip surges on at 50 mm/s.
        let mut z = 0.01;
        let mut max_hold = 0.0_f64;
        for tick in 0..2000 {
            let mut i = input(&path, Point3::new(0.0, 0.0, z), Vector3::new(0.0, 0.0, 0.05));
            i.giving = tick < 30;
            let f = g.step(&i, 1e-3);
            g.set_target(Vector3::zeros());
            assert!(f.z <= 0.0, "tick {tick}: the brake pushed forward: {f}");
            assert!(f.x == 0.0 && f.y == 0.0);
            if tick == 1 {
                assert!(f.z < -0.05, "no hold within 2 ms of the give: {f}");
            }
            max_hold = max_hold.max(-f.z);
            z += 0.05e-3;
        }
        // The spring–damper's resistance grows as the tip runs on, under a cap that decays.
        assert!(max_hold <= p.brake_hold_n + 1e-12 && max_hold > 0.6 * p.brake_hold_n, "hold {max_hold} N");
        assert!(!g.is_braking(), "the hold is over after 2 s");
        // And the model's axial cue, within the warning span before the predicted breakthrough
        // (10 mm here): where the expert pushed less (the paper's cue pulls in), a resistance as
        // large (the tip advancing faster than `warning_feed_m_s`); where the expert pushed
        // harder, nothing.
        let near = input(&path, Point3::new(0.0, 0.0, 0.0095), Vector3::new(0.0, 0.0, 1e-3));
        for _ in 0..300 {
            g.set_target(Vector3::new(0.0, 0.0, 0.5)); // the expert pushed 0.5 N less
            assert!(g.step(&near, 1e-3).z <= 0.0);
        }
        assert!((g.share_n().z + 0.5).abs() < 1e-6, "{}", g.share_n());
        // Elsewhere, nothing: well before the breakthrough, and once the cortex is through.
        let early = input(&path, Point3::new(0.0, 0.0, 0.005), Vector3::zeros());
        let mut through = input(&path, Point3::new(0.0, 0.0, 0.03), Vector3::zeros());
        through.broken_through = true;
        for i in [&early, &through] {
            g.set_target(Vector3::new(0.0, 0.0, 0.5));
            assert!(g.step(i, 1e-3).z.abs() < 1e-12, "{}", g.share_n());
        }
        for _ in 0..300 {
            g.set_target(Vector3::new(0.0, 0.0, -0.5)); // the expert pushed 0.5 N harder
            g.step(&near, 1e-3);
        }
        assert!(g.share_n().z.abs() < 1e-12, "{}", g.share_n());
    }

    #[test]
    fn the_shaped_warning_ramps_up_before_the_predicted_breakthrough() {
        let path = path();
        let mut g = live(GuidanceMode::Shaped);
        let p = g.params().clone();
        // A tip advancing at 1 mm/s, faster than `warning_feed_m_s`: the warning in full.
        let at = |g: &mut Guide, depth: f64, broken: bool| {
            let mut i = input(&path, Point3::new(0.0, 0.0, depth), Vector3::new(0.0, 0.0, 1e-3));
            i.broken_through = broken;
            let f = g.step(&i, 1e-3);
            g.set_target(Vector3::zeros());
            f.z
        };
        assert_eq!(at(&mut g, 0.008, false), 0.0);
        let half = at(&mut g, 0.0095, false);
        assert!((half + 0.5 * p.warning_n).abs() < 1e-9, "{half}");
        assert!((at(&mut g, 0.0101, false) + p.warning_n).abs() < 1e-9);
        assert_eq!(at(&mut g, 0.0101, true), 0.0, "once through, no warning");
    }

    #[test]
    fn the_warning_asks_to_slow_down_and_never_holds_a_still_tip() {
        let path = path();
        let mut g = live(GuidanceMode::Shaped);
        let p = g.params().clone();
        let tip = Point3::new(0.0, 0.0, 0.0101); // past the ramp: the full warning
        let mut at = |v: f64| {
            let f = g.step(&input(&path, tip, Vector3::new(0.0, 0.0, v)), 1e-3).z;
            g.set_target(Vector3::zeros());
            f
        };
        assert!((at(2.0 * p.warning_feed_m_s) + p.warning_n).abs() < 1e-9, "fast: in full");
        assert!((at(0.5 * p.warning_feed_m_s) + 0.5 * p.warning_n).abs() < 1e-9, "half the feed: half");
        assert_eq!(at(0.0), 0.0, "a still tip is not held");
        assert_eq!(at(-1e-3), 0.0, "nor one pulled back");
        // With warning_feed_m_s = 0 the warning is by position alone.
        let mut by_position = live(GuidanceMode::Shaped);
        by_position.set_params(GuidanceParams { warning_feed_m_s: 0.0, ..p.clone() }).unwrap();
        let still = by_position.step(&input(&path, tip, Vector3::zeros()), 1e-3).z;
        assert!((still + p.warning_n).abs() < 1e-9, "{still}");
    }

    #[test]
    fn the_heat_hold_resists_advance_while_hot_until_the_tip_has_cooled() {
        let path = path();
        let mut g = live(GuidanceMode::Shaped);
        assert_eq!(g.params().heat_hold_n, 0.0, "off by default");
        g.set_params(GuidanceParams { heat_hold_n: 1.5, ..GuidanceParams::default() }).unwrap();
        let p = g.params().clone();
        // Tip at 5 mm (no warning there), advancing at 1 mm/s.
        let at = |g: &mut Guide, z: f64, vz: f64, t: f64| {
            let mut i = input(&path, Point3::new(0.0, 0.0, z), Vector3::new(0.0, 0.0, vz));
            i.temperature_c = t;
            let f = g.step(&i, 1e-3);
            g.set_target(Vector3::zeros());
            f
        };
        assert_eq!(at(&mut g, 0.005, 1e-3, 44.9), Vector3::zeros(), "cooler than 45 °C: nothing");
        assert!(!g.is_heat_holding());
        let f = at(&mut g, 0.005, 1e-3, 45.0);
        assert!(g.is_heat_holding(), "engages 2 °C short of 47 °C");
        assert!((f.z + p.brake_damping_n_s_per_m * 1e-3).abs() < 1e-12 && f.x == 0.0 && f.y == 0.0, "{f}");
        // Pushed on past where it engaged: the spring, capped; backing off: nothing (never forward).
        let far = at(&mut g, 0.009, 0.0, 46.0);
        assert!((far.z + p.heat_hold_n).abs() < 1e-12, "{far}");
        assert_eq!(at(&mut g, 0.004, -1e-3, 46.0), Vector3::zeros());
        // Still holding at 43.1 °C (engaged at 45); released at 43.
        assert!(at(&mut g, 0.006, 0.0, 43.1).z < 0.0);
        assert_eq!(at(&mut g, 0.006, 0.0, 43.0), Vector3::zeros());
        assert!(!g.is_heat_holding());
        // The other modes have no heat hold; a reset drops it.
        let mut c = live(GuidanceMode::Brake);
        c.set_params(p.clone()).unwrap();
        assert_eq!(at(&mut c, 0.006, 1e-3, 50.0), Vector3::zeros());
        at(&mut g, 0.006, 1e-3, 46.0);
        g.reset();
        assert!(!g.is_heat_holding());
    }

    #[test]
    fn every_mode_fades_out_when_the_model_is_lost() {
        let path = path();
        for mode in GuidanceMode::ALL {
            let mut g = live(mode);
            g.set_target(Vector3::new(0.3, 0.0, 0.3));
            let i = input(&path, Point3::new(0.003, 0.0, 0.0099), Vector3::new(0.0, 0.0, 1e-3));
            let on = g.step(&i, 1e-3);
            assert!(on.norm() > 0.0, "{mode:?}");
            let mut f = on;
            for _ in 0..2000 {
                f = g.step(&i, 1e-3);
            }
            assert!(!g.is_live() && f == Vector3::zeros(), "{mode:?}: {f}");
        }
    }

    #[test]
    fn fading_assists_as_needed_and_probes_without_guidance() {
        let mut f = Fading::new(FadingParams::default()).unwrap();
        assert_eq!((f.attempts(), f.gain()), (0, 1.0));
        // Within tolerance (0.5 mm plunge, 1.5 mm off the line): the gain falls, attempt after attempt.
        let mut gains = vec![];
        for _ in 0..6 {
            f.finish_attempt(0.5e-3, 1.5e-3);
            gains.push(f.assistance());
        }
        assert!(gains.windows(2).all(|w| w[1] < w[0]), "{gains:?}");
        let p = FadingParams::default();
        let eq = p.learn * 0.5 / (1.0 - p.forget);
        assert!((gains[5] - eq).abs() < 0.1, "{gains:?} against the equilibrium {eq}");
        // Every 4th attempt is a probe: gain 0, whatever the assistance.
        let mut f = Fading::new(FadingParams::default()).unwrap();
        let probes: Vec<bool> = (0..8)
            .map(|_| {
                let probe = f.is_probe();
                assert_eq!(f.gain() == 0.0, probe);
                f.finish_attempt(0.5e-3, 0.0);
                probe
            })
            .collect();
        assert_eq!(probes, [false, false, false, true, false, false, false, true]);
        // A bad attempt (6 mm plunge) brings the assistance back up to the cap.
        let mut f = Fading::new(FadingParams { start_gain: 0.2, ..FadingParams::default() }).unwrap();
        f.finish_attempt(6e-3, 0.0);
        assert_eq!(f.assistance(), 1.0);
        assert!((f.last_error() - 6.0).abs() < 1e-12);
        // Non-finite measurements change nothing but the count; bad params are refused.
        let a = f.assistance();
        f.finish_attempt(f64::NAN, f64::INFINITY);
        assert!(f.assistance() <= a + 1e-12);
        for bad in [
            FadingParams { forget: 1.0, ..FadingParams::default() },
            FadingParams { learn: -1.0, ..FadingParams::default() },
            FadingParams { max_gain: 5.0, ..FadingParams::default() },
            FadingParams { plunge_tolerance_m: 0.0, ..FadingParams::default() },
        ] {
            assert!(matches!(Fading::new(bad), Err(SimError::InvalidParameter { .. })));
        }
    }
}
