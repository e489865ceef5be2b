//! From Hounsfield units to material properties: density, stiffness, erodibility, X-ray attenuation.
//!
//! HU are stored per voxel as `i16` clamped to the 12-bit CT range [`HU_MIN`, `HU_MAX`]; every
//! derived property is tabulated once per (layer, HU) so the drilling hot path does a table lookup,
//! never a `powf`.

use super::layer::Layer;
use crate::error::{finite, non_negative, positive, SimError, SimResult};

/// Lowest stored HU (air).
pub const HU_MIN: i16 = -1024;
/// Highest stored HU (12-bit CT ceiling).
pub const HU_MAX: i16 = 3071;
const HU_LEVELS: usize = (HU_MAX as i32 - HU_MIN as i32 + 1) as usize;

/// The configurable HU → density → stiffness / erodibility mapping.
///
/// Defaults:
/// - Segmentation thresholds: cortical > 700 HU, cancellous 150–700 HU (the ranges commonly used
///   for femoral CT segmentation, and the ones this project's issue specifies).
/// - Apparent density `ρ = a + b·HU` with `a = 0`, `b = 1 kg/m³ per HU` (`ρ_app ≈ HU/1000` g/cm³,
///   a first approximation; replace with the fit of your scanner's calibration phantom).
/// - Elastic modulus `E = C·ρ^p` with ρ in g/cm³: `C = 6850 MPa`, `p = 1.49`, the femoral-neck
///   law of Morgan, Bayraktar & Keaveny (2003), J. Biomech. 36:897.
/// - Erosion: a burr removes material at a rate inversely proportional to E (stiffer bone cuts
///   slower), scaled linearly with spindle speed; calibrated so that fully dense cortical bone
///   (ρ = 1850 kg/m³) loses one voxel's material in 0.4 s of contact at 1000 rpm.
/// - Marrow is soft tissue (yellow marrow ≈ 930 kg/m³) that a burr clears almost at once.
/// - X-ray attenuation `μ = μ_water·(1 + HU/1000)`, `μ_water = 19.3 m⁻¹` (water at 70 keV,
///   NIST XCOM, Hubbell & Seltzer 2004).
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
// Python and the wire name the fields as here; a missing field takes its default, an unknown one
// is refused.
#[serde(default, deny_unknown_fields)]
pub struct HuMapping {
    /// HU above which bone is labelled cortical when labels come from thresholds.
    pub cortical_min_hu: f64,
    /// HU above which (and up to `cortical_min_hu`) bone is labelled cancellous.
    pub cancellous_min_hu: f64,
    /// Density intercept `a` (kg/m³).
    pub density_intercept_kg_m3: f64,
    /// Density slope `b` (kg/m³ per HU).
    pub density_slope_kg_m3_per_hu: f64,
    /// Floor on bone apparent density (kg/m³), so erodibility stays finite.
    pub min_bone_density_kg_m3: f64,
    /// Density of marrow (kg/m³).
    pub marrow_density_kg_m3: f64,
    /// Density marrow presents to the cutting law (kg/m³): it has almost no mineralised
    /// structure, so it cuts like the sparsest trabecular bone.
    pub marrow_cutting_density_kg_m3: f64,
    /// Modulus coefficient `C` (Pa, with ρ in g/cm³).
    pub modulus_coeff_pa: f64,
    /// Modulus exponent `p`.
    pub modulus_exponent: f64,
    /// Density (kg/m³) at which the reference erosion rate holds.
    pub erosion_reference_density_kg_m3: f64,
    /// Fraction of a voxel's material removed per second at the reference density and speed (1/s).
    pub erosion_rate_ref_per_s: f64,
    /// Spindle speed (rpm) at which `erosion_rate_ref_per_s` holds.
    pub erosion_reference_rpm: f64,
    /// Exponent of the spindle-speed dependence of erosion.
    pub erosion_speed_exponent: f64,
    /// Erosion rate of marrow at the reference speed (1/s).
    pub marrow_erosion_rate_per_s: f64,
    /// Cap on any erosion rate at the reference speed (1/s).
    pub max_erosion_rate_per_s: f64,
    /// Linear attenuation of water (1/m) for the X-ray views.
    pub water_attenuation_per_m: f64,
}

impl Default for HuMapping {
    fn default() -> Self {
        Self {
            cortical_min_hu: 700.0,
            cancellous_min_hu: 150.0,
            density_intercept_kg_m3: 0.0,
            density_slope_kg_m3_per_hu: 1.0,
            min_bone_density_kg_m3: 50.0,
            marrow_density_kg_m3: 930.0,
            marrow_cutting_density_kg_m3: 100.0,
            modulus_coeff_pa: 6850e6,
            modulus_exponent: 1.49,
            erosion_reference_density_kg_m3: 1850.0,
            erosion_rate_ref_per_s: 2.5,
            erosion_reference_rpm: 1000.0,
            erosion_speed_exponent: 1.0,
            marrow_erosion_rate_per_s: 1000.0,
            max_erosion_rate_per_s: 1000.0,
            water_attenuation_per_m: 19.3,
        }
    }
}

impl HuMapping {
    /// Checks every field.
    ///
    /// # Errors
    /// A non-finite field, a negative rate or density, or thresholds out of order.
    pub fn validate(&self) -> SimResult<()> {
        finite("cortical_min_hu", self.cortical_min_hu)?;
        finite("cancellous_min_hu", self.cancellous_min_hu)?;
        if self.cancellous_min_hu >= self.cortical_min_hu {
            return Err(SimError::InvalidParameter {
                name: "cancellous_min_hu",
                value: self.cancellous_min_hu,
                reason: "must be below cortical_min_hu",
            });
        }
        finite("density_intercept_kg_m3", self.density_intercept_kg_m3)?;
        finite("density_slope_kg_m3_per_hu", self.density_slope_kg_m3_per_hu)?;
        positive("min_bone_density_kg_m3", self.min_bone_density_kg_m3)?;
        positive("marrow_density_kg_m3", self.marrow_density_kg_m3)?;
        positive("marrow_cutting_density_kg_m3", self.marrow_cutting_density_kg_m3)?;
        positive("modulus_coeff_pa", self.modulus_coeff_pa)?;
        positive("modulus_exponent", self.modulus_exponent)?;
        positive("erosion_reference_density_kg_m3", self.erosion_reference_density_kg_m3)?;
        positive("erosion_rate_ref_per_s", self.erosion_rate_ref_per_s)?;
        positive("erosion_reference_rpm", self.erosion_reference_rpm)?;
        non_negative("erosion_speed_exponent", self.erosion_speed_exponent)?;
        positive("marrow_erosion_rate_per_s", self.marrow_erosion_rate_per_s)?;
        positive("max_erosion_rate_per_s", self.max_erosion_rate_per_s)?;
        non_negative("water_attenuation_per_m", self.water_attenuation_per_m)?;
        Ok(())
    }

    /// The layer a voxel of this HU gets when no segmentation is given (no marrow, no necrosis:
    /// those need anatomy, which the CT importer supplies).
    #[must_use]
    pub fn threshold_layer(&self, hu: f64) -> Layer {
        if hu > self.cortical_min_hu {
            Layer::Cortical
        } else if hu >= self.cancellous_min_hu {
            Layer::Cancellous
        } else {
            Layer::Outside
        }
    }

    /// Apparent density (kg/m³) of a voxel; 0 outside bone.
    #[must_use]
    pub fn density_kg_m3(&self, layer: Layer, hu: f64) -> f64 {
        match layer {
            Layer::Outside => 0.0,
            Layer::Marrow => self.marrow_density_kg_m3,
            Layer::Cortical | Layer::Cancellous | Layer::Necrosis => {
                (self.density_intercept_kg_m3 + self.density_slope_kg_m3_per_hu * hu).max(self.min_bone_density_kg_m3)
            }
        }
    }

    /// Density the cutting law sees (kg/m³): the apparent density of bone, and
    /// `marrow_cutting_density_kg_m3` for marrow.
    #[must_use]
    pub fn cutting_density_kg_m3(&self, layer: Layer, hu: f64) -> f64 {
        match layer {
            Layer::Marrow => self.marrow_cutting_density_kg_m3,
            _ => self.density_kg_m3(layer, hu),
        }
    }

    /// Elastic modulus (Pa) by the density power law; 0 outside bone and in marrow.
    #[must_use]
    pub fn modulus_pa(&self, layer: Layer, hu: f64) -> f64 {
        match layer {
            Layer::Outside | Layer::Marrow => 0.0,
            _ => self.modulus_coeff_pa * (self.density_kg_m3(layer, hu) / 1000.0).powf(self.modulus_exponent),
        }
    }

    /// Material fraction removed per second of full contact at the reference spindle speed (1/s).
    #[must_use]
    pub fn erosion_rate_ref_per_s(&self, layer: Layer, hu: f64) -> f64 {
        match layer {
            Layer::Outside => 0.0,
            Layer::Marrow => self.marrow_erosion_rate_per_s.min(self.max_erosion_rate_per_s),
            _ => {
                let ratio = self.erosion_reference_density_kg_m3 / self.density_kg_m3(layer, hu);
                (self.erosion_rate_ref_per_s * ratio.powf(self.modulus_exponent)).min(self.max_erosion_rate_per_s)
            }
        }
    }

    /// Linear X-ray attenuation (1/m).
    #[must_use]
    pub fn attenuation_per_m(&self, hu: f64) -> f64 {
        (self.water_attenuation_per_m * (1.0 + hu / 1000.0)).max(0.0)
    }

    /// Spindle-speed factor of the erosion rate (0 when the drill is off or reversed).
    #[must_use]
    pub fn speed_factor(&self, spindle_rpm: f64) -> f64 {
        if spindle_rpm > 0.0 {
            (spindle_rpm / self.erosion_reference_rpm).powf(self.erosion_speed_exponent)
        } else {
            0.0
        }
    }
}

/// Clamps a HU value into the stored range (NaN becomes air).
#[must_use]
pub fn clamp_hu(hu: f64) -> i16 {
    if hu.is_nan() {
        HU_MIN
    } else {
        hu.round().clamp(f64::from(HU_MIN), f64::from(HU_MAX)) as i16
    }
}

/// Per-(layer, HU) tables of the properties the hot paths need.
#[derive(Debug, Clone)]
pub struct MaterialTable {
    mapping: HuMapping,
    density_kg_m3: Vec<f32>,
    cutting_density_kg_m3: Vec<f32>,
    erosion_ref_per_s: Vec<f32>,
    attenuation_per_m: Vec<f32>,
}

impl MaterialTable {
    /// Tabulates `mapping` for every layer and stored HU.
    ///
    /// # Errors
    /// An invalid mapping.
    pub fn new(mapping: HuMapping) -> SimResult<Self> {
        mapping.validate()?;
        let mut density = Vec::with_capacity(Layer::COUNT * HU_LEVELS);
        let mut cutting = Vec::with_capacity(Layer::COUNT * HU_LEVELS);
        let mut erosion = Vec::with_capacity(Layer::COUNT * HU_LEVELS);
        for layer in Layer::ALL {
            for level in 0..HU_LEVELS {
                let hu = f64::from(HU_MIN) + level as f64;
                density.push(mapping.density_kg_m3(layer, hu) as f32);
                cutting.push(mapping.cutting_density_kg_m3(layer, hu) as f32);
                erosion.push(mapping.erosion_rate_ref_per_s(layer, hu) as f32);
            }
        }
        let attenuation =
            (0..HU_LEVELS).map(|level| mapping.attenuation_per_m(f64::from(HU_MIN) + level as f64) as f32).collect();
        Ok(Self {
            mapping,
            density_kg_m3: density,
            cutting_density_kg_m3: cutting,
            erosion_ref_per_s: erosion,
            attenuation_per_m: attenuation,
        })
    }

    /// The mapping this table was built from.
    #[must_use]
    pub fn mapping(&self) -> &HuMapping {
        &self.mapping
    }

    #[inline]
    fn slot(layer: u8, hu: i16) -> usize {
        usize::from(layer) * HU_LEVELS + (i32::from(hu) - i32::from(HU_MIN)) as usize
    }

    /// Apparent density (kg/m³). `layer` must be a valid id and `hu` in range (the volume
    /// guarantees both).
    #[inline]
    #[must_use]
    pub fn density_kg_m3(&self, layer: u8, hu: i16) -> f32 {
        self.density_kg_m3[Self::slot(layer, hu)]
    }

    /// Density the cutting law sees (kg/m³).
    #[inline]
    #[must_use]
    pub fn cutting_density_kg_m3(&self, layer: u8, hu: i16) -> f32 {
        self.cutting_density_kg_m3[Self::slot(layer, hu)]
    }

    /// Erosion rate at the reference spindle speed (1/s).
    #[inline]
    #[must_use]
    pub fn erosion_ref_per_s(&self, layer: u8, hu: i16) -> f32 {
        self.erosion_ref_per_s[Self::slot(layer, hu)]
    }

    /// Linear attenuation (1/m).
    #[inline]
    #[must_use]
    pub fn attenuation_per_m(&self, hu: i16) -> f32 {
        self.attenuation_per_m[(i32::from(hu) - i32::from(HU_MIN)) as usize]
    }
}

#[cfg(test)]
#[allow(clippy::float_cmp)] // exact values are intended here
mod tests {
    use super::*;

    #[test]
    fn cortical_is_denser_stiffer_and_slower_to_erode_than_cancellous() {
        let m = HuMapping::default();
        let (cort, canc) = ((Layer::Cortical, 1800.0), (Layer::Cancellous, 300.0));
        assert!(m.density_kg_m3(cort.0, cort.1) > 4.0 * m.density_kg_m3(canc.0, canc.1));
        assert!(m.modulus_pa(cort.0, cort.1) > 10.0 * m.modulus_pa(canc.0, canc.1));
        assert!(m.erosion_rate_ref_per_s(cort.0, cort.1) * 10.0 < m.erosion_rate_ref_per_s(canc.0, canc.1));
        assert!(m.erosion_rate_ref_per_s(Layer::Marrow, 0.0) >= 100.0 * m.erosion_rate_ref_per_s(cort.0, cort.1));
        // Morgan 2003: E(1.85 g/cm³) = 6850·1.85^1.49 MPa ≈ 17.1 GPa.
        assert!((m.modulus_pa(Layer::Cortical, 1850.0) / 1e9 - 17.1).abs() < 0.2);
        // Calibration: dense cortical loses a voxel in 0.4 s at 1000 rpm.
        assert!((m.erosion_rate_ref_per_s(Layer::Cortical, 1850.0) - 2.5).abs() < 1e-9);
    }

    #[test]
    fn thresholds_and_table_agree_with_the_mapping() {
        let m = HuMapping::default();
        assert_eq!(m.threshold_layer(701.0), Layer::Cortical);
        assert_eq!(m.threshold_layer(700.0), Layer::Cancellous);
        assert_eq!(m.threshold_layer(149.0), Layer::Outside);
        let t = MaterialTable::new(m.clone()).unwrap();
        for (layer, hu) in [(Layer::Cortical, 1500i16), (Layer::Cancellous, 250), (Layer::Marrow, 0)] {
            let exact = m.erosion_rate_ref_per_s(layer, f64::from(hu));
            assert!((f64::from(t.erosion_ref_per_s(layer.id(), hu)) - exact).abs() < 1e-4 * exact);
        }
        assert_eq!(t.density_kg_m3(Layer::Outside.id(), HU_MAX), 0.0);
        assert_eq!(clamp_hu(f64::NAN), HU_MIN);
        assert_eq!(clamp_hu(1e9), HU_MAX);
    }

    #[test]
    fn invalid_mapping_is_rejected() {
        let bad = HuMapping { cancellous_min_hu: 800.0, ..HuMapping::default() };
        assert!(bad.validate().is_err());
        let bad = HuMapping { erosion_rate_ref_per_s: f64::NAN, ..HuMapping::default() };
        assert!(MaterialTable::new(bad).is_err());
    }
}
