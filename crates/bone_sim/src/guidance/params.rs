//! The guidance laws' limits and constants, each with its source.

use super::WARNING_FEED_M_S;
use crate::error::{non_negative, positive, SimResult};

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
    /// The safe feed (m/s). Near the predicted breakthrough, the warning and the model's easing
    /// cue ask the trainee to slow down to it: they resist the feed into bone beyond it, from
    /// nothing at this feed to in full at twice it, and not at all on a slower feed, a still
    /// tip, or a tip moving through its own bore, so a trainee who yields as asked is slowed and
    /// never held still in the cortex. 0: in full at any speed (a resistance by position alone).
    pub warning_feed_m_s: f64,
    /// `shaped`: the heat hold engages when the tip is within this of the session's necrosis
    /// threshold (°C below it).
    pub heat_margin_c: f64,
    /// `shaped`: the heat hold lets go once the tip has cooled this far below where it engaged (°C).
    pub heat_release_c: f64,
    /// `shaped`: most the heat hold resists advance with (N).
    pub heat_hold_n: f64,
    /// `shaped`: amplitude of the heat cue, a vibration along the drill axis while the tip is
    /// hot (the heat hold's span: from `heat_margin_c` short of the threshold until cooled
    /// `heat_release_c`) (N). 0: no heat cue.
    pub heat_buzz_n: f64,
    /// `shaped`: frequency of the heat cue's vibration (Hz).
    pub heat_buzz_hz: f64,
}

/// The Touch's continuous force and stiffness (N, N/m), the profile's (`DeviceProfile::geomagic_touch`).
const TOUCH_CONTINUOUS_N: f64 = crate::device::TOUCH_CONTINUOUS_FORCE_N;
const TOUCH_STIFFNESS_N_PER_M: f64 = crate::device::TOUCH_STIFFNESS_N_PER_M;

impl Default for GuidanceParams {
    fn default() -> Self {
        Self {
            // The Touch's continuous force (3D Systems' specification, `DeviceProfile`): a share
            // the device can hold indefinitely.
            max_n: TOUCH_CONTINUOUS_N,
            // Derived, not from a source: the whole 0.88 N in 0.11 s, about one 10 Hz model
            // period (Fekri et al. 2021's record rate), so a reply's step is spread over the
            // interval until the next one instead of felt as a jolt.
            max_rate_n_per_s: 8.0,
            // Derived: three missed 10 Hz replies and 50 ms more count as a lost model.
            timeout_s: 0.35,
            // The project's choice, not from a source: a quarter second, faster than the 0.35 s
            // timeout that starts it, slow enough not to be a step.
            fade_s: 0.25,
            // The experts' lateral spread on the phantom is 0.3 mm mean, 0.8 mm at most
            // (docs/benchmarks.md): inside 0.5 mm the corridor leaves the hand alone.
            corridor_deadband_m: 0.5e-3,
            // 0.88 N at 2.7 mm off the line: at most the Touch's 400 N/m, so it is rendered stably.
            corridor_stiffness_n_per_m: TOUCH_STIFFNESS_N_PER_M,
            // The project's choice, not from a source: a tenth of the brake's, enough to take the
            // spring's overshoot off a 0.4 kg hand without dragging a lateral correction.
            corridor_damping_n_s_per_m: 2.0,
            // An arm that holds the tip off the line against the spring is pulled further over
            // about a second, as assistance that grows with a persisting error does (Wolbrecht et
            // al. 2008, adaptive assist-as-needed with forgetting): tuning seeds 3-8, instructed
            // operator, max offset across the path -44 % -> -52 % against no guidance (impedance
            // -61 % -> -62 %); 2 s and 3 s did less (docs/results.md).
            corridor_integral_s: 1.0,
            corridor_profile_n_per_m: Vec::new(),
            corridor_profile_bin_m: 1e-3,
            // About the push of a hand drilling cortex on the Touch (1.6–2.7 N), so a surge is
            // met at once; within the 3.3 N peak; decaying with 0.4 s, so it outlasts a novice's
            // 0.25–0.40 s reaction and is down to a tenth within a second.
            brake_hold_n: 2.2,
            brake_decay_s: 0.4,
            // The Touch's 400 N/m stiffness limit (`DeviceProfile`), rendered stably.
            brake_stiffness_n_per_m: TOUCH_STIFFNESS_N_PER_M,
            // The arm damping of `docs/fidelity.md`'s hand-held plunge model (the project's
            // choice): the brake resists a surge as the arm itself would.
            brake_damping_n_s_per_m: 20.0,
            // Tuned, not from a source: under half the continuous 0.88 N and well under the
            // 1.6–2.7 N a hand pushes through cortex, so it is felt without stopping the cut
            // (docs/results.md, "A warning that lets a slow drill through").
            warning_n: 0.35,
            // The last millimetre before the planned breakthrough: the project's choice, not from
            // a source (docs/results.md).
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
            // A cue that asks for the pause instead of forcing it: a vibration, which a hand
            // tells apart from every other guidance force (those change slowly) and which moves
            // the tip by microns (0.3 N at 100 Hz on a 0.4 kg hand: 2 µm). Vibration through a
            // handle is a warning channel of its own in teleoperation and virtual environments
            // (Kontarinis & Howe 1995); at 100 Hz, well within what a 1 kHz servo renders and
            // what the hand's Pacinian receptors sense (Bolanowski et al. 1988). Its meaning must
            // be taught: "pause with the drill off until it stops" (docs/results.md, "A heat cue").
            heat_buzz_n: 0.3,
            heat_buzz_hz: 100.0,
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
        non_negative("guidance heat_hold_n", self.heat_hold_n)?;
        non_negative("guidance heat_buzz_n", self.heat_buzz_n)?;
        positive("guidance heat_buzz_hz", self.heat_buzz_hz).map(|_| ())
    }
}
