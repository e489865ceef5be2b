//! Drill-tip temperature: a lumped thermal model,
//! `C · dT/dt = η · (M·ω + F·v) − (T − T_body) / R_th`,
//! integrated exactly for a constant heat input over each tick (unconditionally stable).
//!
//! Heat comes from the cutting torque `M` at angular speed `ω` and from the thrust `F` at feed `v`.
//! With the cutting law's sub-linear feed exponent, faster feeding cuts each millimetre in less
//! time, so the peak temperature is lower. That is the trend reported for bone drilling (see the
//! review by Pandey & Panda 2013, J. Clin. Orthop. Trauma 4:15). When the drill stops, the tip
//! cools towards body temperature with time constant `R_th·C`.
//!
//! Thermal dose is reported as the time spent above 47 °C, the threshold for thermal necrosis of
//! bone (Eriksson & Albrektsson 1983, J. Prosthet. Dent. 50:101: 47 °C for 1 min).

use crate::error::{finite, positive, SimError, SimResult};

/// Parameters of the lumped model, this project's calibration to Augustin et al. (2008, Arch.
/// Orthop. Trauma Surg. 128:71: 2.5, 3.2 and 4.5 mm drills at 188–1820 rpm and 24–196 mm/min
/// through pig femur cortex without irrigation): the heat fraction η sets the tip above 47 °C
/// only for the 4.5 mm drill at 1140 and 1820 rpm (at 56 mm/min through 5 mm of dense cortex), as
/// they measured, and within their 31–56 °C; `C` and `R_th` make a stopped drill cool with a
/// 15 s time constant. `docs/fidelity.md` tables the measured figures beside theirs.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
// Python and the wire name the fields as here; a missing field takes its default, an unknown one
// is refused.
#[serde(default, deny_unknown_fields)]
pub struct ThermalParams {
    /// Lumped heat capacity of the tip region (J/K).
    pub heat_capacity_j_per_k: f64,
    /// Thermal resistance to the body (K/W).
    pub thermal_resistance_k_per_w: f64,
    /// Fraction η of the cutting power that heats the tip region.
    pub heat_fraction: f64,
    /// Body (and initial) temperature (°C).
    pub body_temperature_c: f64,
    /// Necrosis threshold for the thermal dose (°C).
    pub necrosis_threshold_c: f64,
}

impl Default for ThermalParams {
    fn default() -> Self {
        Self {
            heat_capacity_j_per_k: 0.5,
            thermal_resistance_k_per_w: 30.0,
            heat_fraction: 0.16,
            body_temperature_c: 37.0,
            necrosis_threshold_c: 47.0,
        }
    }
}

impl ThermalParams {
    /// Checks every field.
    ///
    /// # Errors
    /// Non-finite or non-positive values, or a heat fraction above 1.
    pub fn validate(&self) -> SimResult<()> {
        positive("heat_capacity_j_per_k", self.heat_capacity_j_per_k)?;
        positive("thermal_resistance_k_per_w", self.thermal_resistance_k_per_w)?;
        positive("heat_fraction", self.heat_fraction)?;
        if self.heat_fraction > 1.0 {
            return Err(SimError::InvalidParameter {
                name: "heat_fraction",
                value: self.heat_fraction,
                reason: "must be in (0, 1]",
            });
        }
        finite("body_temperature_c", self.body_temperature_c)?;
        finite("necrosis_threshold_c", self.necrosis_threshold_c)?;
        Ok(())
    }
}

/// The tip's thermal state.
#[derive(Debug, Clone, PartialEq)]
pub struct Thermal {
    params: ThermalParams,
    /// Current temperature (°C).
    pub temperature_c: f64,
    /// Highest temperature so far (°C).
    pub peak_c: f64,
    /// Time spent above the necrosis threshold (s).
    pub time_above_threshold_s: f64,
}

impl Thermal {
    /// At body temperature.
    ///
    /// # Errors
    /// Invalid parameters.
    pub fn new(params: ThermalParams) -> SimResult<Self> {
        params.validate()?;
        let t = params.body_temperature_c;
        Ok(Self { params, temperature_c: t, peak_c: t, time_above_threshold_s: 0.0 })
    }

    /// The parameters.
    #[must_use]
    pub fn params(&self) -> &ThermalParams {
        &self.params
    }

    /// Advances `dt_s` with cutting torque `torque_n_m` at `omega_rad_s` and thrust `thrust_n` at
    /// feed `feed_m_s`. Non-finite or negative powers count as zero.
    pub fn step(&mut self, torque_n_m: f64, omega_rad_s: f64, thrust_n: f64, feed_m_s: f64, dt_s: f64) {
        let p = &self.params;
        let power = (torque_n_m * omega_rad_s + thrust_n * feed_m_s) * p.heat_fraction;
        let power = if power.is_finite() { power.max(0.0) } else { 0.0 };
        let tau = p.thermal_resistance_k_per_w * p.heat_capacity_j_per_k;
        let t_inf = p.body_temperature_c + power * p.thermal_resistance_k_per_w;
        self.temperature_c = t_inf + (self.temperature_c - t_inf) * (-dt_s / tau).exp();
        self.peak_c = self.peak_c.max(self.temperature_c);
        if self.temperature_c > p.necrosis_threshold_c {
            self.time_above_threshold_s += dt_s;
        }
    }

    /// Back to body temperature, peak and dose cleared.
    pub fn reset(&mut self) {
        let t = self.params.body_temperature_c;
        self.temperature_c = t;
        self.peak_c = t;
        self.time_above_threshold_s = 0.0;
    }
}

#[cfg(test)]
#[allow(clippy::float_cmp)] // exact values are intended here
mod tests {
    use super::*;

    #[test]
    fn heats_while_cutting_cools_after_and_counts_the_dose() {
        let mut th = Thermal::new(ThermalParams::default()).unwrap();
        let omega = 1250.0 * std::f64::consts::TAU / 60.0;
        for _ in 0..20_000 {
            th.step(0.032, omega, 17.0, 1.5e-3, 1e-3);
        }
        let hot = th.temperature_c;
        assert!(hot > 50.0, "20 s of cortical cutting should pass 47 °C, got {hot}");
        assert!(th.time_above_threshold_s > 5.0);
        for _ in 0..30_000 {
            th.step(0.0, 0.0, 0.0, 0.0, 1e-3);
        }
        assert!(th.temperature_c < hot - 10.0 && th.temperature_c > 37.0);
        assert_eq!(th.peak_c, hot);
        // Steady state is T_body + η·P·R.
        let mut th = Thermal::new(ThermalParams::default()).unwrap();
        for _ in 0..1000 {
            th.step(0.0, 0.0, 1.0, 1.0, 1.0);
        }
        assert!((th.temperature_c - (37.0 + 0.16 * 30.0)).abs() < 1e-6);
    }

    #[test]
    fn bad_power_is_ignored_and_bad_params_rejected() {
        let mut th = Thermal::new(ThermalParams::default()).unwrap();
        th.step(f64::NAN, 1.0, f64::INFINITY, 1.0, 1e-3);
        assert_eq!(th.temperature_c, 37.0);
        let bad = ThermalParams { heat_fraction: 1.5, ..ThermalParams::default() };
        assert!(Thermal::new(bad).is_err());
    }
}
