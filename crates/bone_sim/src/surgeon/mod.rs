//! The virtual surgeon: a human-like operator that drills the planned path at 1 kHz.
//!
//! It models a hand holding the stylus: a mass with arm damping, driven by the push the surgeon
//! intends and pushed back by the device force. What the surgeon *does* depends on what they
//! *perceived* one reaction delay ago. The phases are:
//!
//! 1. approach: a minimum-jerk reach (Flash & Hogan 1985) from a resting point to 3 mm before A;
//! 2. align and spin up the drill;
//! 3. feed: the push is regulated towards a preferred feed but never exceeds a layer-dependent
//!    ceiling (firm in cortical bone, light in cancellous bone and marrow); surgeons who
//!    anticipate the breakthrough ease off as the cortex thins, and all stop to let the drill
//!    cool above their caution temperature; novices hesitate;
//! 4. breakthrough: once the surgeon feels the cortex give (after the reaction delay), they hold
//!    and pull back 1 mm. A late reaction and a loose arm make a deeper plunge;
//! 5. stop near B and switch the drill off.
//!
//! Human motor behaviour: physiological tremor of 8–12 Hz (Elble 1990), signal-dependent noise on
//! the push (Harris & Wolpert 1998), lateral drift of the aim (an Ornstein–Uhlenbeck wander), a
//! reaction delay, and an arm that pushes by aiming just ahead of where the hand was felt (an
//! equilibrium point, Feldman 1986; Bizzi et al. 1992). Styles are drawn per subject by the
//! Python package (`dhg.operators.styles.sample_style`); this module is the surgeon's 1 kHz step, so that
//! an offline study drills at the core's speed, and a remote trainee (`dhg trainee`) steps the
//! same code per received state.
//!
//! Randomness comes from a seeded `ChaCha8` generator: an attempt is a function of its seed.

use nalgebra::{Point3, Vector3};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::StandardNormal;

mod geometry;
mod senses;
mod style;
#[cfg(test)]
mod tests;

pub use geometry::axis_quaternion;
use geometry::{basis, min_jerk};
use senses::VibrationSense;
pub use style::{
    CueMeaning, Perception, Skill, SurgeonStyle, AIM_FOLLOW_S, CUE_LEAK_PER_S, GENERIC_BREAKTHROUGH_DEPTH_M,
    HAND_MASS_KG, LATERAL_STIFFNESS_N_PER_M, MAX_PUSH_N, MAX_REACTION_DELAY_S, PUSH_MARGIN_N, TRACK_STIFFNESS_N_PER_M,
    YIELD_SETTLE_S,
};

use crate::error::{SimError, SimResult};
use crate::path::PlannedPath;
use crate::record::{Record, TICK_S};
use crate::session::{DrillingSession, Pose};
use crate::volume::layer::Layer;

/// Longest attempt a virtual surgeon takes (s): an hour. The paper's attempts take minutes
/// (Fekri et al. 2021), and the task's rules give up at 240 s ([`crate::skill::TaskRules`]); the
/// bound keeps a mistyped duration from sizing an attempt's buffers by it.
pub const MAX_ATTEMPT_S: f64 = 3600.0;
// The approach and the reaction to a breakthrough below are the virtual surgeon's tuning, the
// project's choice (its reaction delays, which have a source, come with its style from
// `dhg.operators.styles`).
/// Where the hand starts along A→B (m): 25 mm before the entry.
pub const START_S_M: f64 = -25e-3;
/// Where the approach ends and the drill is aligned (m along A→B): 3 mm before the entry.
const ALIGNED_S_M: f64 = -3e-3;
/// SD of the hand's starting offset across the path (m).
const START_SPREAD_M: f64 = 3e-3;
/// How slowly the aim wanders (s): the Ornstein–Uhlenbeck time constant of the lateral drift.
const DRIFT_TAU_S: f64 = 1.5;
/// Window over which the surgeon perceives the feed rate (ticks, 50 ms).
const SPEED_WINDOW_TICKS: usize = 50;
/// How long the surgeon holds and pulls back after feeling a breakthrough (s).
const RETRACT_S: f64 = 0.25;
/// How far the surgeon pulls back after feeling a breakthrough (m).
const RETRACT_M: f64 = 1e-3;
/// How much cooler than their caution temperature the drill must get before a cautious surgeon
/// feeds again (°C).
const COOL_HYSTERESIS_C: f64 = 2.0;
/// How long the surgeon holds still at the stop before finishing (s).
const STOP_HOLD_S: f64 = 0.5;

/// What the surgeon means to do this tick.
#[derive(Debug, Clone, Copy, PartialEq)]
enum Intent {
    /// Hold the hand at this position along the path (m from A).
    Hold(f64),
    /// Push (the feed phase's regulated push).
    Push,
    /// The attempt is over.
    Finished,
}

/// Where the surgeon is in the attempt.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Phase {
    /// Reaching towards the entry.
    Approach,
    /// Aligned before the entry, spinning the drill up.
    Align,
    /// Drilling along the path.
    Feed,
    /// Holding at the end with the drill off.
    Stop,
    /// Finished.
    Done,
}

impl Phase {
    /// The phase's name: `approach`, `align`, `feed`, `stop` or `done`.
    #[must_use]
    pub fn name(self) -> &'static str {
        match self {
            Self::Approach => "approach",
            Self::Align => "align",
            Self::Feed => "feed",
            Self::Stop => "stop",
            Self::Done => "done",
        }
    }
}

/// What the surgeon remembers of one tick, for acting on it a reaction delay later.
#[derive(Debug, Clone, Copy)]
struct Felt {
    seen: Perception,
    /// The guidance cue along A→B (N).
    cue_axial_n: f64,
    /// The device force along A→B (N).
    force_axial_n: f64,
    /// The hand's position along A→B (m).
    hand_s_m: f64,
    /// Whether a vibration was felt in the cue (the heat cue).
    buzz: bool,
}

impl Felt {
    /// Nothing felt yet: the history before the first tick.
    const EMPTY: Self = Self {
        seen: Perception {
            depth_m: 0.0,
            temperature_c: 0.0,
            layer: Layer::Outside,
            breakthroughs: 0,
            plunge_depth_m: 0.0,
        },
        cue_axial_n: 0.0,
        force_axial_n: 0.0,
        hand_s_m: 0.0,
        buzz: false,
    };
}

/// Checks an attempt's duration (s) and planned breakthrough depth (m; `None`: the generic one),
/// and returns the depth.
fn check_attempt(max_duration_s: f64, breakthrough_depth_m: Option<f64>) -> SimResult<f64> {
    if !(max_duration_s.is_finite() && max_duration_s > 0.0 && max_duration_s <= MAX_ATTEMPT_S) {
        return Err(SimError::InvalidParameter {
            name: "max_duration_s (s)",
            value: max_duration_s,
            reason: "must be positive and at most MAX_ATTEMPT_S (3600 s)",
        });
    }
    let depth = breakthrough_depth_m.unwrap_or(GENERIC_BREAKTHROUGH_DEPTH_M);
    if !depth.is_finite() {
        return Err(SimError::NonFinite { what: "breakthrough_depth_m (m)", value: depth });
    }
    Ok(depth)
}

/// The virtual surgeon's decisions and hand, one 1 kHz tick at a time (see the module docs).
#[derive(Debug, Clone)]
#[allow(clippy::struct_excessive_bools)] // the hand's independent states
pub struct SurgeonController {
    style: SurgeonStyle,
    rng: ChaCha8Rng,
    entry: Point3<f64>,
    d: Vector3<f64>,
    e1: Vector3<f64>,
    e2: Vector3<f64>,
    quat: [f64; 4],
    length_m: f64,
    breakthrough_depth_m: f64,
    yields: bool,
    reads_cue: bool,
    max_ticks: usize,
    delay: usize,
    u0: f64,
    v0: f64,
    approach_s: f64,
    align_s: f64,
    tremor_phase: [f64; 3],
    w_tremor: f64,
    k_ou: f64,
    ou_kick: f64,
    // The hand in path coordinates: s along A→B, (u, v) across, and their velocities.
    s: f64,
    u: f64,
    v: f64,
    vs: f64,
    vu: f64,
    vv: f64,
    drift_u: f64,
    drift_v: f64,
    noise_state: f64,
    push: f64,
    lean: f64,
    aim_s: f64,
    stop_s: f64,
    phase: Phase,
    phase_t0: f64,
    hold_s: Option<f64>,
    pause_until: f64,
    cooling: bool,
    /// Pausing with the drill off because a heat cue is felt (a surgeon told what it means).
    heat_pause: bool,
    /// The hand's vibration sense, reading the cue along the axis.
    touch: VibrationSense,
    retract_until: f64,
    seen_breakthroughs: u32,
    drill_on: bool,
    drill_on_t: Option<f64>,
    drill_off_t: Option<f64>,
    max_plunge_m: f64,
    /// The last `delay + SPEED_WINDOW_TICKS + 1` ticks, by tick modulo its length.
    history: Vec<Felt>,
    tick: usize,
    /// The device force and guidance share of the last tick driven by [`Self::drill_until_record`].
    last_force_n: Vector3<f64>,
    last_cue_n: Vector3<f64>,
}

impl SurgeonController {
    /// A surgeon of `style` about to drill `path`, for at most `max_duration_s`, expecting the
    /// first cortex to give at tip depth `breakthrough_depth_m` (m; `None`: about 2.2 mm, the
    /// depth without a plan), and reading guidance as `cue_meaning` says. `seed` fixes every
    /// random draw of the attempt.
    ///
    /// # Errors
    /// An invalid style or a non-finite or non-positive duration.
    pub fn new(
        path: &PlannedPath,
        style: SurgeonStyle,
        seed: u64,
        max_duration_s: f64,
        breakthrough_depth_m: Option<f64>,
        cue_meaning: CueMeaning,
    ) -> SimResult<Self> {
        style.validate()?;
        let breakthrough_depth_m = check_attempt(max_duration_s, breakthrough_depth_m)?;
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let d = path.direction();
        let (e1, e2) = basis(&d);
        let max_ticks = (max_duration_s / TICK_S) as usize;
        let delay = ((style.reaction_delay_s / TICK_S).round_ties_even() as usize).max(1);
        let normal = |rng: &mut ChaCha8Rng| -> f64 { rng.sample(StandardNormal) };
        let u0 = START_SPREAD_M * normal(&mut rng);
        let v0 = START_SPREAD_M * normal(&mut rng);
        let approach_s = rng.gen_range(1.2..2.0);
        let align_s = rng.gen_range(0.3..0.7);
        let tau = std::f64::consts::TAU;
        let tremor_phase = [rng.gen_range(0.0..tau), rng.gen_range(0.0..tau), rng.gen_range(0.0..tau)];
        let k_ou = TICK_S / DRIFT_TAU_S;
        Ok(Self {
            w_tremor: tau * style.tremor_hz,
            ou_kick: style.drift_m * (2.0 * k_ou).sqrt(),
            k_ou,
            rng,
            entry: path.entry_m(),
            d,
            e1,
            e2,
            quat: axis_quaternion(&d),
            length_m: path.length_m(),
            breakthrough_depth_m,
            yields: cue_meaning == CueMeaning::Yield,
            reads_cue: cue_meaning != CueMeaning::Felt,
            max_ticks,
            delay,
            u0,
            v0,
            approach_s,
            align_s,
            tremor_phase,
            s: START_S_M,
            u: u0,
            v: v0,
            vs: 0.0,
            vu: 0.0,
            vv: 0.0,
            drift_u: 0.0,
            drift_v: 0.0,
            noise_state: 0.0,
            push: 0.0,
            lean: 0.0,
            aim_s: START_S_M,
            stop_s: 0.0,
            phase: Phase::Approach,
            phase_t0: 0.0,
            hold_s: None,
            pause_until: -1.0,
            cooling: false,
            heat_pause: false,
            touch: VibrationSense::default(),
            retract_until: -1.0,
            seen_breakthroughs: 0,
            drill_on: false,
            drill_on_t: None,
            drill_off_t: None,
            max_plunge_m: 0.0,
            history: vec![Felt::EMPTY; delay + SPEED_WINDOW_TICKS + 1],
            tick: 0,
            last_force_n: Vector3::zeros(),
            last_cue_n: Vector3::zeros(),
            style,
        })
    }

    /// The subject's style.
    #[must_use]
    pub fn style(&self) -> &SurgeonStyle {
        &self.style
    }

    /// Whether the surgeon has finished (stopped at B, or ran out of time).
    #[must_use]
    pub fn done(&self) -> bool {
        self.phase == Phase::Done || self.tick >= self.max_ticks
    }

    /// Where the surgeon is in the attempt.
    #[must_use]
    pub fn phase(&self) -> Phase {
        self.phase
    }

    /// Ticks stepped so far.
    #[must_use]
    pub fn ticks(&self) -> usize {
        self.tick
    }

    /// The most ticks the attempt may last.
    #[must_use]
    pub fn max_ticks(&self) -> usize {
        self.max_ticks
    }

    /// Time from drill start to drill stop (s), as far as the attempt has come.
    #[must_use]
    pub fn drilling_s(&self) -> f64 {
        let end = self.drill_off_t.unwrap_or(self.tick as f64 * TICK_S);
        end - self.drill_on_t.unwrap_or(0.0)
    }

    /// The push the surgeon means to make along A→B (N), before the lean into a cue: the feed
    /// controller's output, within the layer's ceiling.
    #[must_use]
    pub fn push_n(&self) -> f64 {
        self.push
    }

    /// The push added in response to the guidance cue (N).
    #[must_use]
    pub fn lean_n(&self) -> f64 {
        self.lean
    }

    /// The deepest plunge seen so far (m).
    #[must_use]
    pub fn max_plunge_m(&self) -> f64 {
        self.max_plunge_m
    }

    /// How long a vibration was felt in the cue so far (s): the heat cue's buzz, or anything
    /// else the hand would read as one (which a surgeon told what it means would pause for).
    #[must_use]
    pub fn buzz_felt_s(&self) -> f64 {
        self.touch.felt_s()
    }

    fn felt(&self, tick: usize) -> &Felt {
        &self.history[tick % self.history.len()]
    }

    fn felt_mut(&mut self, tick: usize) -> &mut Felt {
        let n = self.history.len();
        &mut self.history[tick % n]
    }

    /// The pose row (x, y, z, qw, qx, qy, qz, `drill_on`, `spindle_rpm`) for this tick, or `None`
    /// once the surgeon has finished. `now` is what the stylus reports this tick, `force_n` the
    /// whole force the device rendered last tick (N, world frame) and `cue_n` its guidance share
    /// (N), which the surgeon also reads as `cue_meaning` says.
    pub fn step(&mut self, now: &Perception, force_n: &Vector3<f64>, cue_n: &Vector3<f64>) -> Option<[f64; 9]> {
        if self.done() {
            return None;
        }
        let tick = self.tick;
        let t = tick as f64 * TICK_S;
        let d = self.d;
        let cue_axial_n = cue_n.dot(&d);
        let buzz = self.touch.feel(cue_axial_n);
        *self.felt_mut(tick) = Felt { seen: *now, cue_axial_n, force_axial_n: 0.0, hand_s_m: self.s, buzz };
        let delayed = tick.saturating_sub(self.delay);
        let seen = self.felt(delayed).seen;
        self.max_plunge_m = self.max_plunge_m.max(now.plunge_depth_m);
        self.wander();
        let intent_s = match self.intent(t, &seen) {
            Intent::Hold(s) => Some(s),
            Intent::Push => None,
            Intent::Finished => return None,
        };
        self.felt_mut(tick).force_axial_n = force_n.dot(&d);
        let drive = self.axial_drive(intent_s, delayed);
        let p = self.move_hand(t, drive, force_n);
        self.tick += 1;
        let (on, rpm) = if self.drill_on { (1.0, self.style.spindle_rpm) } else { (0.0, 0.0) };
        let q = self.quat;
        Some([p.x, p.y, p.z, q[0], q[1], q[2], q[3], on, rpm])
    }

    /// One tick of the aim's wander (Ornstein–Uhlenbeck) and of the signal-dependent push noise
    /// (low-passed ~5 Hz).
    fn wander(&mut self) {
        let (n_u, n_v, n_push): (f64, f64, f64) =
            (self.rng.sample(StandardNormal), self.rng.sample(StandardNormal), self.rng.sample(StandardNormal));
        self.drift_u += -self.k_ou * self.drift_u + self.ou_kick * n_u;
        self.drift_v += -self.k_ou * self.drift_v + self.ou_kick * n_v;
        self.noise_state += 0.03 * (n_push - self.noise_state);
    }

    /// The phase machine at time `t` (s) on what was `seen` a reaction delay ago.
    fn intent(&mut self, t: f64, seen: &Perception) -> Intent {
        match self.phase {
            Phase::Approach => {
                let into = t - self.phase_t0;
                if into >= self.approach_s {
                    self.phase = Phase::Align;
                    self.phase_t0 = t;
                }
                Intent::Hold(START_S_M + (ALIGNED_S_M - START_S_M) * min_jerk(into, self.approach_s))
            }
            Phase::Align => {
                self.drill_on = true;
                if t - self.phase_t0 >= self.align_s {
                    self.phase = Phase::Feed;
                    self.phase_t0 = t;
                    self.push = 0.0;
                    self.drill_on_t = Some(t);
                }
                Intent::Hold(ALIGNED_S_M)
            }
            Phase::Feed => self.feed(t, seen).map_or(Intent::Push, Intent::Hold),
            Phase::Stop => {
                self.drill_on = false;
                self.drill_off_t.get_or_insert(t);
                if t - self.phase_t0 >= STOP_HOLD_S {
                    self.phase = Phase::Done;
                    return Intent::Finished;
                }
                Intent::Hold(self.stop_s)
            }
            Phase::Done => Intent::Finished,
        }
    }

    /// The arm's drive along the path (N): a spring to the intended position, or the push,
    /// bounded by the resistance felt a reaction delay ago (`delayed`, a tick).
    fn axial_drive(&mut self, intent_s: Option<f64>, delayed: usize) -> f64 {
        if let Some(intent) = intent_s {
            self.aim_s = self.s;
            return TRACK_STIFFNESS_N_PER_M * (intent - self.s);
        }
        // Nobody pushes much harder than the resistance they feel: a push that meets no
        // resistance (a device that has derated, a bone that gave way) is not kept up. The
        // lean into a guidance cue comes on top: it is what the subject was told to do.
        let style = &self.style;
        let then = self.felt(delayed);
        let felt_resistance = (-then.force_axial_n).max(0.0);
        let own = self.push.min(felt_resistance + PUSH_MARGIN_N);
        let mut push = (own + self.lean).clamp(0.0, MAX_PUSH_N);
        push *= 1.0 + style.noise_fraction * self.noise_state * 5.0;
        // The arm pushes towards an aim that moves on at the preferred feed and follows,
        // slowly, where the hand was felt one reaction delay ago: its stiffness resists travel
        // ahead of the aim, so a sudden give is caught after about push / stiffness. (An aim
        // that followed the felt position at once would make a delayed, unstable loop.)
        let hand_then = then.hand_s_m;
        self.aim_s += style.feed_m_s * TICK_S + (hand_then - self.aim_s) * TICK_S / AIM_FOLLOW_S;
        push - self.style.arm_stiffness_n_per_m * (self.s - self.aim_s).max(0.0)
    }

    /// The hand's mass, damping and lateral stiffness under `drive` (N, along the path) and the
    /// device force, one tick of semi-implicit Euler at 1 kHz; returns the stylus position (m).
    fn move_hand(&mut self, t: f64, drive: f64, force_n: &Vector3<f64>) -> Point3<f64> {
        let dt = TICK_S;
        let style = &self.style;
        let f_ax = force_n.dot(&self.d);
        let f_u = force_n.dot(&self.e1);
        let f_v = force_n.dot(&self.e2);
        let (damping, mass, k_lat) =
            (style.hand_damping_n_s_per_m, style.hand_mass_kg, style.lateral_stiffness_n_per_m);
        self.vs += (drive + f_ax - damping * self.vs) / mass * dt;
        let tremor = |phase: f64, amplitude: f64| amplitude * (self.w_tremor * t + phase).sin();
        let mut aim_u = self.drift_u + tremor(self.tremor_phase[0], style.tremor_m);
        let mut aim_v = self.drift_v + tremor(self.tremor_phase[1], style.tremor_m);
        if self.phase == Phase::Approach {
            let frac = 1.0 - min_jerk(t - self.phase_t0, self.approach_s);
            aim_u += self.u0 * frac;
            aim_v += self.v0 * frac;
        }
        self.vu += (k_lat * (aim_u - self.u) + f_u - damping * self.vu) / mass * dt;
        self.vv += (k_lat * (aim_v - self.v) + f_v - damping * self.vv) / mass * dt;
        self.s += self.vs * dt;
        self.u += self.vu * dt;
        self.v += self.vv * dt;
        let s_axial = self.s + tremor(self.tremor_phase[2], style.tremor_m * 0.3);
        self.entry + self.d * s_axial + self.e1 * self.u + self.e2 * self.v
    }

    /// The feed phase's decisions at time `t` (s) on what was perceived a reaction delay ago:
    /// the position to hold, or `None` to push with `self.push`.
    fn feed(&mut self, t: f64, seen: &Perception) -> Option<f64> {
        let style = &self.style;
        let dt = TICK_S;
        // Perceived tip speed over the last 50 ms (as of one reaction delay ago).
        let back = self.felt(self.tick.saturating_sub(self.delay + SPEED_WINDOW_TICKS)).seen.depth_m;
        let speed = (seen.depth_m - back) / (SPEED_WINDOW_TICKS as f64 * TICK_S);
        let cortical = seen.layer == Layer::Cortical;
        let mut ceiling = if cortical { style.push_cortical_n } else { style.push_soft_n };
        let easing = seen.depth_m > self.breakthrough_depth_m - style.anticipation_m;
        if style.anticipates_breakthrough && cortical && easing {
            ceiling = style.ease_fraction * style.push_cortical_n; // the cortex is thinning: ease off
        }
        if seen.breakthroughs > self.seen_breakthroughs {
            self.seen_breakthroughs = seen.breakthroughs;
            self.retract_until = t + RETRACT_S;
        }
        if seen.temperature_c > style.caution_temp_c {
            self.cooling = true;
        } else if self.cooling && seen.temperature_c < style.caution_temp_c - COOL_HYSTERESIS_C {
            self.cooling = false;
        }
        // Told what the heat cue means ("pause with the drill off until it stops"), a surgeon
        // who yields to guidance pauses while they feel it, as of a reaction delay ago.
        self.heat_pause = self.yields && self.felt(self.tick.saturating_sub(self.delay)).buzz;
        if style.hesitations_per_s > 0.0 && t > self.pause_until && self.rng.gen::<f64>() < style.hesitations_per_s * dt
        {
            self.pause_until = t + style.hesitation_s;
        }
        let resting = self.cooling || self.heat_pause;
        let intent = if t < self.retract_until || resting || t < self.pause_until {
            // Hold still (pulled back after a breakthrough): a pausing hand does not go limp.
            let back_m = if t < self.retract_until { RETRACT_M } else { 0.0 };
            let hold = *self.hold_s.get_or_insert(self.s - back_m);
            self.push = 0.0;
            self.lean = 0.0;
            Some(hold)
        } else {
            self.hold_s = None;
            // Integral control of the push towards the preferred feed, within the ceiling.
            self.push += 2.4 * style.feed_gain * (style.feed_m_s - speed) / style.feed_m_s * dt * ceiling;
            self.push = self.push.max(0.0).min(ceiling);
            // The cue as perceived a reaction delay ago.
            let cue_seen = self.felt(self.tick.saturating_sub(self.delay)).cue_axial_n;
            if !self.reads_cue {
                // felt only: the cue is in the force, which the arm's impedance answers
            } else if self.yields {
                // Yielding: give way by what the cue asks, after the reaction delay (a hand
                // settling onto the new force within about 0.2 s), not more.
                self.lean += (cue_seen - self.lean) * dt / YIELD_SETTLE_S;
            } else {
                // Matching: a cue along −d (pushing the drill back) means the expert pressed harder.
                self.lean += (-style.cue_follow_per_s * cue_seen - CUE_LEAK_PER_S * self.lean) * dt;
            }
            None
        };
        self.drill_on = !resting;
        if seen.depth_m >= self.length_m - style.stop_margin_m {
            self.phase = Phase::Stop;
            self.phase_t0 = t;
            self.hold_s = Some(self.s);
            self.stop_s = self.s;
        }
        intent
    }

    /// Drills `session` with this surgeon until the session writes its next 10 Hz record
    /// (returned), or until the surgeon finishes (`None`). The surgeon perceives the session's
    /// state each tick and feels the force it renders; with `guided`, it also reads the
    /// guidance share as its cue (without, the cue is zero). `on_tick` sees each tick's pose row
    /// and force (N).
    pub fn drill_until_record(
        &mut self,
        session: &mut DrillingSession,
        guided: bool,
        mut on_tick: impl FnMut(&[f64; 9], &Vector3<f64>),
    ) -> Option<Record> {
        loop {
            let now = Perception::of(session.state());
            let (force, cue) = (self.last_force_n, self.last_cue_n);
            let row = self.step(&now, &force, &cue)?;
            let pose = Pose::new([row[0], row[1], row[2]], [row[3], row[4], row[5], row[6]], row[7] > 0.5, row[8]);
            let out = session.tick(Some(&pose));
            self.last_force_n = out.force_n;
            self.last_cue_n = if guided { session.state().guidance_n } else { Vector3::zeros() };
            on_tick(&row, &out.force_n);
            if out.record.is_some() {
                return out.record;
            }
        }
    }
}
