//! What is configurable about a session, and its checks.

use crate::cutting::CuttingLaw;
use crate::device::DeviceProfile;
use crate::error::{positive, SimError, SimResult};
use crate::removal::{MAX_BURR_RADIUS_M, MIN_BURR_RADIUS_M};
use crate::thermal::ThermalParams;

/// Everything configurable about a session.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
// Python and the wire name the fields as here; a missing field takes its default, an unknown one
// is refused.
#[serde(default, deny_unknown_fields)]
pub struct SessionConfig {
    /// Burr (drill tip) radius (m).
    pub burr_radius_m: f64,
    /// The haptic device.
    pub device: DeviceProfile,
    /// Device–proxy coupling stiffness (N/m); at most the device's `max_stiffness_n_per_m`.
    pub coupling_stiffness_n_per_m: f64,
    /// Device–proxy coupling damping on their relative velocity (N·s/m).
    pub coupling_damping_n_s_per_m: f64,
    /// Physical force (N) rendered as the device's peak force: the force scale is
    /// `device.peak_force_n / physical_full_scale_n` (0.11 for the Touch at 30 N).
    pub physical_full_scale_n: f64,
    /// Physical push (N) at which a burr pressed sideways erodes at its full rate.
    pub lateral_cut_reference_n: f64,
    /// Fastest the proxy may move (m/s); a faster device is followed over several ticks.
    pub max_proxy_speed_m_s: f64,
    /// Thrust and torque laws.
    pub cutting: CuttingLaw,
    /// Drill-tip thermal model.
    pub thermal: ThermalParams,
}

impl Default for SessionConfig {
    fn default() -> Self {
        let device = DeviceProfile::geomagic_touch();
        Self {
            burr_radius_m: 1.25e-3,
            coupling_stiffness_n_per_m: device.max_stiffness_n_per_m,
            device,
            coupling_damping_n_s_per_m: 1.0,
            physical_full_scale_n: 30.0,
            lateral_cut_reference_n: 10.0,
            max_proxy_speed_m_s: 1.0,
            cutting: CuttingLaw::default(),
            thermal: ThermalParams::default(),
        }
    }
}

/// Checks a burr radius (m): finite and in [[`MIN_BURR_RADIUS_M`], [`MAX_BURR_RADIUS_M`]].
///
/// # Errors
/// `InvalidParameter` naming `burr_radius_m`.
pub fn check_burr_radius(radius_m: f64) -> SimResult<f64> {
    positive("burr_radius_m", radius_m)?;
    if radius_m < MIN_BURR_RADIUS_M {
        return Err(SimError::InvalidParameter {
            name: "burr_radius_m",
            value: radius_m,
            reason: "must be at least 0.00025 m (a 0.5 mm drill)",
        });
    }
    if radius_m > MAX_BURR_RADIUS_M {
        return Err(SimError::InvalidParameter {
            name: "burr_radius_m",
            value: radius_m,
            reason: "must be at most 0.02 m",
        });
    }
    Ok(radius_m)
}

impl SessionConfig {
    /// Checks every field.
    ///
    /// # Errors
    /// Any invalid value, or a coupling stiffer than the device can render.
    pub fn validate(&self) -> SimResult<()> {
        check_burr_radius(self.burr_radius_m)?;
        self.device.validate()?;
        positive("coupling_stiffness_n_per_m", self.coupling_stiffness_n_per_m)?;
        if self.coupling_stiffness_n_per_m > self.device.max_stiffness_n_per_m {
            return Err(SimError::InvalidParameter {
                name: "coupling_stiffness_n_per_m",
                value: self.coupling_stiffness_n_per_m,
                reason: "must not exceed the device's max_stiffness_n_per_m",
            });
        }
        crate::error::non_negative("coupling_damping_n_s_per_m", self.coupling_damping_n_s_per_m)?;
        positive("physical_full_scale_n", self.physical_full_scale_n)?;
        positive("lateral_cut_reference_n", self.lateral_cut_reference_n)?;
        positive("max_proxy_speed_m_s", self.max_proxy_speed_m_s)?;
        self.cutting.validate()?;
        self.thermal.validate()
    }

    /// Device newtons per physical newton.
    #[must_use]
    pub fn force_scale(&self) -> f64 {
        self.device.peak_force_n / self.physical_full_scale_n
    }
}
