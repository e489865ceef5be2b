//! Who the surgeon is (skill, style, what they take the cue to mean) and what they perceive.

use serde::{Deserialize, Serialize};

use crate::error::{SimError, SimResult};
use crate::session::SessionState;
use crate::volume::layer::Layer;

// The hand and habits every surgeon shares (the defaults of the style fields they name). They
// are the virtual surgeon's tuning, not measured values: no source was found for a stylus grip's
// mass or an arm's endpoint stiffness while drilling (van Beek et al. 2015 fitted 0.554 kg and
// 135 N/m to one trial at a haptic handle in a relaxed posture, which the `impedance` operator of
// `dhg study` uses instead: `dhg.operators.models`).
/// Effective mass of hand and stylus at the stylus tip (kg): the default of
/// [`SurgeonStyle::hand_mass_kg`]; the project's choice.
pub const HAND_MASS_KG: f64 = 0.4;
/// How stiffly the arm follows an intended position (N/m), for the approach and holding; the
/// default of [`SurgeonStyle::arm_stiffness_n_per_m`]; the project's choice.
pub const TRACK_STIFFNESS_N_PER_M: f64 = 300.0;
/// How stiffly the arm holds the drill on its aim across the path (N/m); the default of
/// [`SurgeonStyle::lateral_stiffness_n_per_m`]; the project's choice.
pub const LATERAL_STIFFNESS_N_PER_M: f64 = 250.0;
/// Tip depth at which a surgeon without a plan expects the first cortex to give (m): about
/// 3.5 mm of cortex less a 2.5 mm burr's reach; the project's choice, between the phantom's
/// 1.8 mm metaphyseal and 4.5 mm diaphyseal cortex (`dhg.bone.phantom`).
pub const GENERIC_BREAKTHROUGH_DEPTH_M: f64 = 2.2e-3;
// The push and the yielding below are the virtual surgeon's tuning too, the project's choice.
/// Time constant (s) with which the arm's aim follows the felt hand position.
pub const AIM_FOLLOW_S: f64 = 0.5;
/// How much harder than the resistance they feel (N, one reaction delay ago) a subject pushes.
pub const PUSH_MARGIN_N: f64 = 0.4;
/// Most axial push any subject applies, however strongly a guidance cue asks for more (N).
pub const MAX_PUSH_N: f64 = 3.0;
/// How fast a surgeon who yields to the guidance settles onto what it asks (s).
pub const YIELD_SETTLE_S: f64 = 0.2;
/// How fast the lean a cue built up fades once the cue is gone (1/s): a remembered instruction
/// fades, and a model biased in one direction cannot wind the push up for ever.
pub const CUE_LEAK_PER_S: f64 = 0.2;

/// A subject's skill group.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Skill {
    /// An experienced surgeon.
    Expert,
    /// A trainee.
    Novice,
}

/// What the surgeon was told the guidance means.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum CueMeaning {
    /// The paper's force-matching cue: lean into a cue that pushes the drill back, ease off one
    /// that pulls it in.
    Match,
    /// Guidance that shapes the motion (corridor, brake, shaped): ease off where it resists, go
    /// with it where it pulls.
    Yield,
    /// Nothing: the cue acts on the hand only through the arm's impedance, as any force does.
    Felt,
}

impl CueMeaning {
    /// Parses `"match"`, `"yield"` or `"felt"`.
    ///
    /// # Errors
    /// Any other name.
    pub fn from_name(name: &str) -> SimResult<Self> {
        match name {
            "match" => Ok(Self::Match),
            "yield" => Ok(Self::Yield),
            "felt" => Ok(Self::Felt),
            _ => Err(SimError::InvalidOption {
                name: "cue_meaning",
                value: name.to_owned(),
                allowed: "'match', 'yield', 'felt'",
            }),
        }
    }
}

/// One subject's style and motor parameters (SI units; forces are device newtons). The Python
/// package's `dhg.core.surgeon.SurgeonStyle` carries the same fields, with their documentation.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
#[allow(clippy::struct_excessive_bools)] // two independent traits of a subject
pub struct SurgeonStyle {
    /// Skill group.
    pub skill: Skill,
    /// Most the subject pushes in cortical bone (N on the device).
    pub push_cortical_n: f64,
    /// Most the subject pushes in cancellous bone and marrow (N).
    pub push_soft_n: f64,
    /// Preferred feed rate where the bone allows it (m/s).
    pub feed_m_s: f64,
    /// How briskly the push is adjusted towards the preferred feed (1 = an expert's).
    pub feed_gain: f64,
    /// Delay between a change in what they feel and their response (s).
    pub reaction_delay_s: f64,
    /// Arm co-contraction: damping of sudden hand motion (N·s/m).
    pub hand_damping_n_s_per_m: f64,
    /// Amplitude of physiological tremor (m).
    pub tremor_m: f64,
    /// Tremor frequency (Hz).
    pub tremor_hz: f64,
    /// Signal-dependent noise: SD of the push as a fraction of the push.
    pub noise_fraction: f64,
    /// Lateral wander of the aim (SD, m).
    pub drift_m: f64,
    /// Eases off as the cortex thins.
    pub anticipates_breakthrough: bool,
    /// How far before the planned breakthrough depth the subject eases off (m).
    pub anticipation_m: f64,
    /// Rate of pauses while feeding (1/s).
    pub hesitations_per_s: f64,
    /// Length of a pause (s).
    pub hesitation_s: f64,
    /// Above this tip temperature the subject stops feeding to let the drill cool (°C).
    pub caution_temp_c: f64,
    /// How far before B the subject aims to stop (m; negative = past B).
    pub stop_margin_m: f64,
    /// Spindle speed used (rpm).
    pub spindle_rpm: f64,
    /// How briskly the subject leans into a force-matching cue (1/s).
    pub cue_follow_per_s: f64,
    /// Stiffness of the arm around the point it pushes towards (N/m).
    pub arm_stiffness_n_per_m: f64,
    /// Fraction of the cortical push kept while easing off before the planned breakthrough.
    pub ease_fraction: f64,
    /// Effective mass of hand, arm and stylus at the stylus tip (kg).
    pub hand_mass_kg: f64,
    /// How stiffly the arm holds the drill on its aim across the path (N/m).
    pub lateral_stiffness_n_per_m: f64,
}

impl SurgeonStyle {
    /// Checks that every value is finite and physically meaningful.
    ///
    /// # Errors
    /// [`SimError::NonFinite`] or [`SimError::InvalidParameter`] naming the field.
    pub fn validate(&self) -> SimResult<()> {
        let positive: [(&'static str, f64); 5] = [
            ("surgeon style feed_m_s (m/s)", self.feed_m_s),
            ("surgeon style hand_mass_kg (kg)", self.hand_mass_kg),
            ("surgeon style tremor_hz (Hz)", self.tremor_hz),
            ("surgeon style feed_gain", self.feed_gain),
            ("surgeon style hand_damping_n_s_per_m (N·s/m)", self.hand_damping_n_s_per_m),
        ];
        let non_negative: [(&'static str, f64); 14] = [
            ("surgeon style push_cortical_n (N)", self.push_cortical_n),
            ("surgeon style push_soft_n (N)", self.push_soft_n),
            ("surgeon style reaction_delay_s (s)", self.reaction_delay_s),
            ("surgeon style tremor_m (m)", self.tremor_m),
            ("surgeon style noise_fraction", self.noise_fraction),
            ("surgeon style drift_m (m)", self.drift_m),
            ("surgeon style anticipation_m (m)", self.anticipation_m),
            ("surgeon style hesitations_per_s (1/s)", self.hesitations_per_s),
            ("surgeon style hesitation_s (s)", self.hesitation_s),
            ("surgeon style spindle_rpm (rpm)", self.spindle_rpm),
            ("surgeon style cue_follow_per_s (1/s)", self.cue_follow_per_s),
            ("surgeon style arm_stiffness_n_per_m (N/m)", self.arm_stiffness_n_per_m),
            ("surgeon style ease_fraction", self.ease_fraction),
            ("surgeon style lateral_stiffness_n_per_m (N/m)", self.lateral_stiffness_n_per_m),
        ];
        for (what, value) in positive.iter().chain(&non_negative).copied().chain([
            ("surgeon style caution_temp_c (°C)", self.caution_temp_c),
            ("surgeon style stop_margin_m (m)", self.stop_margin_m),
        ]) {
            if !value.is_finite() {
                return Err(SimError::NonFinite { what, value });
            }
        }
        for (name, value) in positive {
            if value <= 0.0 {
                return Err(SimError::InvalidParameter { name, value, reason: "must be positive" });
            }
        }
        for (name, value) in non_negative {
            if value < 0.0 {
                return Err(SimError::InvalidParameter { name, value, reason: "must not be negative" });
            }
        }
        if self.reaction_delay_s > MAX_REACTION_DELAY_S {
            return Err(SimError::InvalidParameter {
                name: "surgeon style reaction_delay_s (s)",
                value: self.reaction_delay_s,
                reason: "must be at most MAX_REACTION_DELAY_S (2 s)",
            });
        }
        Ok(())
    }
}

/// The longest reaction delay a style may have (s). Human reactions to a felt or seen cue take
/// 0.1–0.4 s (the long-latency reflex from 0.1 s, Pruszynski & Scott 2012; the novices here
/// 0.15–0.40 s); 2 s is far beyond them, and it bounds the history the delay sizes (a tick each).
pub const MAX_REACTION_DELAY_S: f64 = 2.0;

/// What the surgeon perceives of the drill each tick: the part of the session's state a hand and
/// a screen convey.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Perception {
    /// Tip depth along A→B (m).
    pub depth_m: f64,
    /// Drill-tip temperature (°C).
    pub temperature_c: f64,
    /// The layer at the burr's front.
    pub layer: Layer,
    /// Breakthroughs so far.
    pub breakthroughs: u32,
    /// Depth of the current or last plunge (m).
    pub plunge_depth_m: f64,
}

impl Perception {
    /// What a surgeon perceives of a session in this state.
    #[must_use]
    pub fn of(state: &SessionState) -> Self {
        Self {
            depth_m: state.depth_m,
            temperature_c: state.temperature_c,
            layer: state.layer,
            breakthroughs: state.breakthroughs,
            plunge_depth_m: state.plunge_depth_m,
        }
    }
}
