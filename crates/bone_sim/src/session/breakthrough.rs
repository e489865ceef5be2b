//! Breakthrough detection and the plunge that follows it.

use nalgebra::{Point3, Vector3};

use super::{
    DrillingSession, BREAKTHROUGH_ARM_KG_M3, BREAKTHROUGH_DENSITY_FRACTION, MIN_BORE_M, PLUNGE_END_SPEED_M_S,
    PLUNGE_MIN_TICKS, PLUNGE_WINDOW_TICKS, WITHDRAWN_M,
};
use crate::contact::CuttingZone;
use crate::record::TICK_S;
use crate::volume::layer::Layer;

#[derive(Debug, Clone)]
pub(super) struct Breakthrough {
    pub(super) in_cortex: bool,
    /// Highest cutting density seen while cutting this cortex (kg/m³).
    pub(super) cortex_density_kg_m3: f64,
    /// The bore's bottom: the deepest level (along the drill axis) cut since engaging this
    /// cortex, under where the burr last cut at that level.
    pub(super) cut_m: Point3<f64>,
    /// Where the proxy first engaged this cortex.
    pub(super) engage_m: Point3<f64>,
    /// Where the tip was when the cortex gave way.
    pub(super) point_m: Point3<f64>,
    /// The drill axis at the breakthrough: the plunge is measured along it.
    pub(super) plunge_axis: Vector3<f64>,
    /// Ticks since the breakthrough.
    pub(super) plunge_ticks: usize,
    /// The tip's advance past `point_m` along `plunge_axis` over the last
    /// [`PLUNGE_WINDOW_TICKS`] ticks, a ring indexed by `plunge_ticks`.
    pub(super) advance_m: [f64; PLUNGE_WINDOW_TICKS],
}

impl Default for Breakthrough {
    fn default() -> Self {
        Self {
            in_cortex: false,
            cortex_density_kg_m3: 0.0,
            cut_m: Point3::origin(),
            engage_m: Point3::origin(),
            point_m: Point3::origin(),
            plunge_axis: Vector3::z(),
            plunge_ticks: 0,
            advance_m: [0.0; PLUNGE_WINDOW_TICKS],
        }
    }
}

impl DrillingSession {
    pub(super) fn track_breakthrough(&mut self, rpm: f64, cutting: bool, zone: &CuttingZone, axis: &Vector3<f64>) {
        let bt = &mut self.breakthrough;
        let s = &mut self.state;
        let density = zone.density_kg_m3;
        if bt.in_cortex && rpm > 0.0 {
            let soft = BREAKTHROUGH_DENSITY_FRACTION * bt.cortex_density_kg_m3;
            // The cap cuts little, straight ahead lies much softer undrilled bone (or none), and
            // the burr is at the bottom of its bore: it is at an exit of the cortex, not back in
            // its own bore or withdrawn out of it.
            let at_bottom = (self.proxy_m - bt.cut_m).dot(axis) > -WITHDRAWN_M;
            if at_bottom && density < soft && zone.ahead_pristine_density_kg_m3 < soft {
                bt.in_cortex = false;
                // Only a burr that bored into the cortex breaks through it; a shallow cut that
                // ends so is a skid off a curved surface.
                if (bt.cut_m - bt.engage_m).dot(axis) >= MIN_BORE_M {
                    bt.point_m = self.proxy_m;
                    bt.plunge_axis = *axis;
                    bt.plunge_ticks = 0;
                    s.breakthroughs += 1;
                    s.plunging = true;
                    self.giving = true;
                    s.plunge_depth_m = 0.0;
                }
            }
        }
        let engaging = cutting && zone.layer == Layer::Cortical && density >= BREAKTHROUGH_ARM_KG_M3;
        // A cortex already broken through is behind the burr until it is a bore's depth past
        // where it gave way: what it cuts before that (the rim of an oblique exit, back in its
        // own bore after pulling back) is the same cortex.
        let past_last = s.breakthroughs == 0 || (self.proxy_m - bt.point_m).dot(&bt.plunge_axis) > MIN_BORE_M;
        if s.plunging && engaging && past_last {
            // Cutting cortex again, past the first: the plunge is over, and this is a new cortex.
            s.plunging = false;
        }
        // Arm on real engagement with cortex, not while the last plunge is still running (the
        // rest of the same cortex giving way is the same breakthrough). A drill stopped and
        // restarted in its bore (cooling pauses) goes on with the same bore.
        if engaging && !s.plunging && past_last {
            if !bt.in_cortex {
                bt.cortex_density_kg_m3 = 0.0;
                bt.cut_m = self.proxy_m;
                bt.engage_m = self.proxy_m;
            }
            bt.in_cortex = true;
            bt.cortex_density_kg_m3 = bt.cortex_density_kg_m3.max(density);
        }
        // The bore's bottom: the deepest level cut since engaging.
        if bt.in_cortex && cutting {
            let along = (self.proxy_m - bt.cut_m).dot(axis);
            if along > -WITHDRAWN_M {
                bt.cut_m = self.proxy_m - axis * along.min(0.0);
            }
        }
        if s.plunging {
            let advance = (self.proxy_m - bt.point_m).dot(&bt.plunge_axis);
            s.plunge_depth_m = s.plunge_depth_m.max(advance);
            let slot = bt.plunge_ticks % PLUNGE_WINDOW_TICKS;
            let window_ago = bt.advance_m[slot];
            bt.advance_m[slot] = advance;
            bt.plunge_ticks += 1;
            // The plunge ends when the drill stops, or when the tip has been back under control
            // (advancing slower than a controlled feed) over a whole window, judged no sooner
            // than a hand can have reacted.
            let slow = bt.plunge_ticks > PLUNGE_MIN_TICKS
                && advance - window_ago < PLUNGE_END_SPEED_M_S * PLUNGE_WINDOW_TICKS as f64 * TICK_S;
            if rpm <= 0.0 || slow {
                s.plunging = false;
            }
        }
    }
}
