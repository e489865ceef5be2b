//! The paper's 10 Hz record: nine features, in one fixed order, defined here once.
//!
//! Python reads [`FEATURES`] through the binding (`dhg.core.features`), datasets store it in their
//! card, and `docs/frames.md` tables it. Never reorder: trained models depend on it.

/// One feature of the record: its column name (with unit suffix) and unit.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Feature {
    /// Column name.
    pub name: &'static str,
    /// SI unit ("1" for a dimensionless id).
    pub unit: &'static str,
    /// What it is.
    pub description: &'static str,
}

/// Number of features in a record.
pub const FEATURE_COUNT: usize = 9;

/// The features in record order (Fekri et al. 2021, section 2.2).
pub const FEATURES: [Feature; FEATURE_COUNT] = [
    Feature { name: "force_x_n", unit: "N", description: "feedback force on the device (guidance excluded), world x" },
    Feature { name: "force_y_n", unit: "N", description: "feedback force on the device (guidance excluded), world y" },
    Feature { name: "force_z_n", unit: "N", description: "feedback force on the device (guidance excluded), world z" },
    Feature { name: "tip_x_m", unit: "m", description: "drill tip (burr centre, proxy), world x" },
    Feature { name: "tip_y_m", unit: "m", description: "drill tip (burr centre, proxy), world y" },
    Feature { name: "tip_z_m", unit: "m", description: "drill tip (burr centre, proxy), world z" },
    Feature { name: "layer", unit: "1", description: "anatomical layer id at the burr's front point" },
    Feature { name: "depth_m", unit: "m", description: "penetration depth of the tip along A→B, from A" },
    Feature { name: "temperature_c", unit: "°C", description: "drill-tip temperature" },
];

/// Ticks between records (1 kHz ticks, 10 Hz records).
pub const RECORD_PERIOD_TICKS: u64 = 100;

/// The fixed tick of a drilling session (s).
pub const TICK_S: f64 = 1e-3;

/// One 10 Hz record.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Record {
    /// Session time at the record (s).
    pub time_s: f64,
    /// The nine features, in [`FEATURES`] order.
    pub features: [f64; FEATURE_COUNT],
    /// Whether the drill was running.
    pub drill_on: bool,
}

#[cfg(test)]
#[allow(clippy::float_cmp)] // exact values are intended here
mod tests {
    use super::*;

    #[test]
    fn feature_order_is_the_papers() {
        let names: Vec<_> = FEATURES.iter().map(|f| f.name).collect();
        assert_eq!(
            names,
            [
                "force_x_n",
                "force_y_n",
                "force_z_n",
                "tip_x_m",
                "tip_y_m",
                "tip_z_m",
                "layer",
                "depth_m",
                "temperature_c"
            ]
        );
        assert_eq!(RECORD_PERIOD_TICKS as f64 * TICK_S, 0.1);
    }
}
