//! Fading: the per-trainee gain schedule over attempts (assist as needed, with probes).

use super::check_gain;
use crate::error::{non_negative, positive, SimError, SimResult};

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
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize, schemars::JsonSchema)]
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

/// The largest error an attempt counts, in tolerances: far beyond any real attempt's (a plunge of
/// 1 m against a 1 mm tolerance is 1000), it keeps the update finite.
const MAX_ERROR_RATIO: f64 = 1e6;

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

/// A fading schedule as the session info (`fading`) and `DrillingSession.fading` report it.
#[derive(Debug, Clone, PartialEq, serde::Serialize, schemars::JsonSchema)]
pub struct FadingSchedule {
    /// The schedule's parameters.
    pub params: FadingParams,
    /// Attempts finished so far.
    pub attempts: u32,
    /// The assistance the next guided attempt gets (0..=`max_gain`).
    pub assistance: f64,
    /// This attempt's gain (0 in a probe).
    pub gain: f64,
    /// Whether this attempt is a guidance-free probe.
    pub probe: bool,
    /// The last attempt's error (1: at the tolerance); null before the first.
    pub last_error: Option<f64>,
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

    /// The schedule as the session info reports it.
    #[must_use]
    pub fn schedule(&self) -> FadingSchedule {
        FadingSchedule {
            params: self.params.clone(),
            attempts: self.attempts,
            assistance: self.assistance,
            gain: self.gain(),
            probe: self.is_probe(),
            last_error: self.last_error.is_finite().then_some(self.last_error),
        }
    }

    /// Ends an attempt with its largest plunge and lateral deviation (m); returns the next
    /// attempt's gain. Non-finite errors count as the tolerance (no change of evidence).
    pub fn finish_attempt(&mut self, plunge_m: f64, max_deviation_m: f64) -> f64 {
        let p = &self.params;
        // Bounded, so that a tiny tolerance or a huge error cannot make 0 · inf = NaN of the gain.
        let ratio = |v: f64, tol: f64| if v.is_finite() { (v.max(0.0) / tol).min(MAX_ERROR_RATIO) } else { 1.0 };
        let e = ratio(plunge_m, p.plunge_tolerance_m).max(ratio(max_deviation_m, p.deviation_tolerance_m));
        self.last_error = e;
        let next = p.forget * self.assistance + p.learn * e;
        // learn · e may overflow to inf (then the most assistance); a NaN would keep it as it is.
        self.assistance = if next.is_nan() { self.assistance } else { next.clamp(0.0, p.max_gain) };
        self.attempts += 1;
        self.gain()
    }
}
