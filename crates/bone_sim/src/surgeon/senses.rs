//! What the surgeon's hand senses in the cue besides its force: a vibration (the heat cue).

use crate::record::TICK_S;

/// The hand's vibration sense, as the surgeon's model of it: the cue along the axis less its
/// low-pass (time constant, s; about 16 Hz) is the vibration felt.
const BUZZ_LOWPASS_S: f64 = 0.01;
/// Smallest swing of that vibration counted (N): a tenth of a newton through a handle is well
/// above the hand's vibration threshold (Bolanowski et al. 1988), and above the few hundredths of
/// a newton that tremor makes the corridor's damper render.
const BUZZ_MIN_N: f64 = 0.05;
/// Time constant of the count of the vibration's swings (s), and how many must be counted in it
/// for a buzz to be felt: a 100 Hz vibration swings 200 times a second (10 in 50 ms), a step in
/// the force (a brake engaging) once. About 30 ms to recognise; felt until the count falls to
/// half that (about 70 ms after the vibration ends), so that it does not flicker.
const BUZZ_WINDOW_S: f64 = 0.05;
const BUZZ_SWINGS: f64 = 5.0;

/// The hand's vibration sense: the cue along the axis less its low-pass, its swings counted over
/// about 50 ms. A buzz is felt from about 30 ms after a vibration starts until about 70 ms after
/// it ends; a step in the cue (a brake engaging) swings once and is never one.
#[derive(Debug, Clone, Default)]
pub(super) struct VibrationSense {
    /// The low-passed cue (N).
    lowpass_n: f64,
    /// The sign of the last counted swing.
    swing_sign: f64,
    /// Swings counted, decaying with `BUZZ_WINDOW_S`.
    swings: f64,
    /// Whether a buzz is felt now.
    felt: bool,
    /// Ticks on which one was felt.
    ticks_felt: usize,
}

impl VibrationSense {
    /// Whether the cue along the axis (N, this tick) carries a vibration.
    pub(super) fn feel(&mut self, cue_axial_n: f64) -> bool {
        self.lowpass_n += (cue_axial_n - self.lowpass_n) * TICK_S / BUZZ_LOWPASS_S;
        let swing = cue_axial_n - self.lowpass_n;
        self.swings *= 1.0 - TICK_S / BUZZ_WINDOW_S;
        if swing.abs() >= BUZZ_MIN_N {
            let sign = swing.signum();
            if sign * self.swing_sign <= 0.0 {
                self.swings += 1.0;
                self.swing_sign = sign;
            }
        }
        self.felt = if self.felt { self.swings >= 0.5 * BUZZ_SWINGS } else { self.swings >= BUZZ_SWINGS };
        self.ticks_felt += usize::from(self.felt);
        self.felt
    }

    /// How long a buzz was felt so far (s).
    pub(super) fn felt_s(&self) -> f64 {
        self.ticks_felt as f64 * TICK_S
    }
}
