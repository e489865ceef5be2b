//! What goes into a tick (the stylus pose) and what comes out (the force, the 10 Hz record, the
//! session's state).

use nalgebra::{Point3, UnitQuaternion, Vector3};

use super::{MAX_POSITION_M, MAX_SPINDLE_RPM};
use crate::record::Record;
use crate::volume::layer::Layer;

/// One stylus sample.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Pose {
    /// Burr centre (m, world frame).
    pub position_m: Point3<f64>,
    /// Tool orientation; its +z axis is the drill axis, pointing in the drilling direction.
    pub orientation: UnitQuaternion<f64>,
    /// Whether the drill is running.
    pub drill_on: bool,
    /// Spindle speed (rpm, >= 0).
    pub spindle_rpm: f64,
}

impl Pose {
    /// A pose from raw values (quaternion `w, x, y, z`, normalised here). Never fails: check
    /// [`is_valid`](Self::is_valid), which [`DrillingSession::tick`] does for every pose.
    #[must_use]
    pub fn new(position_m: [f64; 3], quat_wxyz: [f64; 4], drill_on: bool, spindle_rpm: f64) -> Self {
        let q = nalgebra::Quaternion::new(quat_wxyz[0], quat_wxyz[1], quat_wxyz[2], quat_wxyz[3]);
        Self {
            position_m: Point3::from(position_m),
            // A zero or NaN quaternion normalises to NaN, which `is_valid` rejects.
            orientation: UnitQuaternion::new_unchecked(q / q.norm()),
            drill_on,
            spindle_rpm,
        }
    }

    /// Whether the pose is physical: every coordinate within ±[`MAX_POSITION_M`] (so finite),
    /// the orientation a unit quaternion, and the speed within `0..=`[`MAX_SPINDLE_RPM`].
    #[must_use]
    pub fn is_valid(&self) -> bool {
        self.position_m.iter().all(|v| v.abs() <= MAX_POSITION_M)
            && self.orientation.coords.iter().all(|v| v.is_finite())
            && (self.orientation.norm() - 1.0).abs() < 1e-6
            && (0.0..=MAX_SPINDLE_RPM).contains(&self.spindle_rpm)
    }

    /// The drill axis (unit, world frame).
    #[must_use]
    pub fn axis(&self) -> Vector3<f64> {
        self.orientation * Vector3::z()
    }
}

/// What a session reports about itself (SI units; forces on the device unless marked physical).
/// Serialised as it is (vectors as `[x, y, z]`, the layer as its id), which is the dict Python's
/// `DrillingSession.state` returns.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
#[allow(clippy::struct_excessive_bools)] // a report: each flag is an independent fact
pub struct SessionState {
    /// Session time (s).
    pub time_s: f64,
    /// Ticks run.
    pub ticks: u64,
    /// Where the device is (m).
    pub device_m: Point3<f64>,
    /// The drill tip: the proxy's burr centre (m).
    pub tip_m: Point3<f64>,
    /// Drill axis (unit).
    pub axis: Vector3<f64>,
    /// Whether the drill is running.
    pub drill_on: bool,
    /// Spindle speed (rpm).
    pub spindle_rpm: f64,
    /// Whether the burr touches bone.
    pub in_contact: bool,
    /// Whether the drill is cutting along its axis this tick.
    pub cutting: bool,
    /// Anatomical layer at the burr's front point.
    pub layer: Layer,
    /// Penetration depth along A→B (m).
    pub depth_m: f64,
    /// Distance from the planned segment (m).
    pub deviation_m: f64,
    /// Feed rate along the axis while cutting (m/s).
    pub feed_m_s: f64,
    /// Physical thrust estimate (N).
    pub thrust_n: f64,
    /// Physical cutting torque estimate (N·m).
    pub torque_n_m: f64,
    /// Density in the cutting cap (kg/m³).
    pub cutting_density_kg_m3: f64,
    /// The force sent to the device (N).
    pub force_n: Vector3<f64>,
    /// Drill-tip temperature (°C).
    pub temperature_c: f64,
    /// Highest temperature so far (°C).
    pub peak_temperature_c: f64,
    /// Time above 47 °C (s).
    pub time_above_47_s: f64,
    /// Breakthroughs so far: the drill point leaving cortical bone for something much softer
    /// (cancellous bone, marrow, or no bone at all).
    pub breakthroughs: u32,
    /// Whether a plunge is under way.
    pub plunging: bool,
    /// Depth of the current or last plunge past its breakthrough point (m).
    pub plunge_depth_m: f64,
    /// Bone mass removed (kg).
    pub removed_mass_kg: f64,
    /// Whether the input is stale (no pose for longer than the device allows).
    pub stale: bool,
    /// Poses rejected as invalid (non-finite or out-of-range position or speed, a zero
    /// quaternion; see [`Pose::is_valid`]).
    pub rejected_poses: u64,
    /// Registration offset (m): how far the stylus sits ahead of where the tip's motion put it,
    /// from stretches the bone stopped holding (see the module docs). The tip follows
    /// `device_m − registration_offset_m`.
    pub registration_offset_m: Vector3<f64>,
    /// The device motors' thermal load, `0..=1` ([`ForceLimiter::thermal_load`]).
    pub device_thermal_load: f64,
    /// The guidance share added to the bone's force this tick (N; see [`crate::guidance`]).
    pub guidance_n: Vector3<f64>,
    /// The bone's part of the rendered force: `force_n − guidance_n` (N). The 10 Hz record's
    /// force is this, so a guided session's records hold what the bone did.
    pub feedback_n: Vector3<f64>,
    /// Whether a model reply younger than the guidance timeout is in use.
    pub model_available: bool,
}

/// What one tick produced.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TickOutput {
    /// The force to send to the device (N, world frame).
    pub force_n: Vector3<f64>,
    /// The 10 Hz record, on every 100th tick.
    pub record: Option<Record>,
}
