//! A drilling session: one trainee's drill on one (copy-on-write) bone, advanced in fixed 1 ms
//! ticks.
//!
//! Each tick takes the stylus pose (burr centre in the world frame, orientation whose +z is the
//! drill axis, drill on/off, spindle speed) and returns the force for the device. The force
//! comes from a god-object proxy of the burr:
//! - the proxy stays outside the remaining bone; a spring–damper between the device and the proxy
//!   gives the force. With the drill off, bone feels like a rigid surface;
//! - with the drill on and bone in the cutting cap, the proxy advances along the axis at the feed
//!   the cutting law gives for the thrust, `F = C·n^a·f^b·ρ^c`. The thrust is the push the hand
//!   makes on the bone: the coupling's axial stretch, scaled to physical newtons, and never more
//!   than the device actually renders (in equilibrium the hand pushes exactly as hard as the
//!   device pushes back, so a derating device never drives a feed its force does not cut). The
//!   burr erodes the bone around it (the removal model), and the proxy advances sideways as walls
//!   erode;
//! - the stretch is the device's compliance, not the drill's: a real drill is rigid in the hand.
//!   So the tip never runs into it. Where the bone gives way (the cap's density drops: leaving
//!   the cortex), the tip advances no faster than the hand moves or than the bone it was in
//!   allowed, and the stretch the softer bone no longer holds is moved into a *registration
//!   offset* between stylus and tip: the force drops, the hand, no longer held, surges, and the
//!   tip goes with it. The same holds in free space: a stretch released by a surface that stops
//!   holding it (the edge of a bone) becomes offset, not travel. The offset is bled off while
//!   the hand withdraws in free space (workspace drift control, Conti & Khatib 2005, World
//!   Haptics: a small mismatch between hand and tool motion goes unnoticed);
//! - leaving the cortex is a breakthrough: the session reports it and measures the plunge, how
//!   far the tip runs past the point where it left the cortex before the trainee stops it. A
//!   breakthrough needs a burr that bored at least 0.8 mm into the cortex, whose cap now cuts
//!   much less dense material, with much less dense undrilled bone (or none) straight ahead:
//!   pulling back into its own bore (pecking, bouncing off the bone) or skidding off a curved
//!   surface is not one;
//! - every force passes the device's safety stage ([`ForceLimiter`]).
//!
//! A tick allocates nothing, takes no locks and does no I/O, as long as the bone's reserved
//! bricks suffice (see [`DrilledVolume::with_reserve`]).

use std::f64::consts::TAU;
use std::sync::Arc;

use nalgebra::{Point3, UnitQuaternion, Vector3};

use crate::contact::{BurrProbe, CuttingZone, CAP_COS};
use crate::cutting::CuttingLaw;
use crate::device::{DeviceProfile, ForceLimiter};
use crate::error::{positive, SimError, SimResult};
use crate::guidance::{Fading, FadingParams, GuidanceMode, GuidanceParams, Guide, GuideInput};
use crate::path::PlannedPath;
use crate::record::{Record, RECORD_PERIOD_TICKS, TICK_S};
use crate::removal::{Burr, Cut, MAX_BURR_RADIUS_M, MIN_BURR_RADIUS_M};
use crate::thermal::{Thermal, ThermalParams};
use crate::volume::drilled::DrilledVolume;
use crate::volume::layer::Layer;
use crate::volume::Volume;

/// Cutting-zone density (kg/m³) at or below which the cap counts as empty: any real bone or
/// marrow in the cap engages the cutting law.
const EMPTY_CAP_KG_M3: f64 = 2.0;
/// A breakthrough: the cutting cap's density, and the undrilled bone's straight ahead, fall
/// below this fraction of the cortical density it was cutting (into softer bone, marrow or
/// nothing).
const BREAKTHROUGH_DENSITY_FRACTION: f64 = 0.4;
/// Cutting density (kg/m³) the cortex must reach in the cutting cap before a breakthrough can
/// be detected (a grazing first contact is not "in the cortex" yet).
const BREAKTHROUGH_ARM_KG_M3: f64 = 400.0;
/// A proxy this far (m) behind the deepest point where it cut this cortex, along the drill axis,
/// has been withdrawn: its cut there does not deepen the bore, and an empty cap there is no exit.
const WITHDRAWN_M: f64 = 0.1e-3;
/// Depth (m) the burr must have bored into a cortex, along its axis, before that cortex can give
/// way. The cap arms about 0.3 mm before the burr touches, so crossing the phantom's thinnest
/// cortex (1 mm, at the head) bores about 1.3 mm; novices skidding on the curved lateral cortex of
/// the phantom bored up to 0.5 mm before the cap emptied.
const MIN_BORE_M: f64 = 0.8e-3;
/// A plunge is the uncontrolled advance after a breakthrough. It ends once the tip has advanced
/// slower than this over the last [`PLUNGE_WINDOW_TICKS`] ticks. Controlled feeds are 0.5–4 mm/s;
/// plunges run at tens of mm/s.
const PLUNGE_END_SPEED_M_S: f64 = 5e-3;
/// The window (ticks) over which a plunge's speed is judged: 100 ms, one period of 10 Hz tremor,
/// so a trembling hand that holds still reads as still.
pub const PLUNGE_WINDOW_TICKS: usize = 100;
/// A plunge is not judged over by its speed sooner than this many ticks (200 ms) after the
/// breakthrough. No hand catches a tip that got away sooner than its voluntary reaction to the
/// give, 150–250 ms for a novice's response to a force perturbation (the range the operator
/// models use, `dhg.operators.models`; the virtual experts react in 100–160 ms), so a slow first window
/// is the cortex still giving way
/// under a push that has not yet carried the tip on, not a tip back under control. (Judged from
/// the first window, a light push that gathered speed after 100 ms was once reported as a
/// 0.28 mm plunge for 2.6 mm of travel.)
pub const PLUNGE_MIN_TICKS: usize = 200;
/// Fastest spindle speed a pose may ask for (rpm): the edge of what the cutting and thermal laws
/// are fitted on (thrust on 1000–1500 rpm, Orelaja et al. 2020; temperature trends on
/// 188–1820 rpm, Augustin et al. 2008, Arch. Orthop. Trauma Surg. 128:71). Orthopaedic twist
/// drills run at about 1000–1500 rpm; a pose asking for more is refused, as the laws say nothing
/// there and extrapolating heat from them gives non-physical temperatures.
pub const MAX_SPINDLE_RPM: f64 = 2000.0;
/// Largest coordinate (m) a pose's position may have. The world frame is the patient frame of the
/// CT: anything further than 10 m from its origin is no stylus position.
pub const MAX_POSITION_M: f64 = 10.0;
/// The bone gives way where the cap's density falls below this fraction of the bone the burr
/// has just come through; smaller dips (a textured bone, the burr crossing voxels) are cut as
/// they come.
const GIVE_FRACTION: f64 = 0.8;
/// How much faster than the hand (m/s) the tip may move in free motion: a proxy sliding along a
/// surface as its walls erode moves at mm/s; one released by an edge leaps at up to 1 m/s.
const RELEASE_SLACK_M_S: f64 = 0.02;
/// Fraction of the hand's withdrawal, in free space, by which the registration offset is bled
/// off each tick (the tip then withdraws 25 % slower than the hand until the offset is gone).
const OFFSET_BLEED: f64 = 0.25;

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
#[derive(Debug, Clone, PartialEq)]
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

#[derive(Debug, Clone)]
struct Breakthrough {
    in_cortex: bool,
    /// Highest cutting density seen while cutting this cortex (kg/m³).
    cortex_density_kg_m3: f64,
    /// The bore's bottom: the deepest level (along the drill axis) cut since engaging this
    /// cortex, under where the burr last cut at that level.
    cut_m: Point3<f64>,
    /// Where the proxy first engaged this cortex.
    engage_m: Point3<f64>,
    /// Where the tip was when the cortex gave way.
    point_m: Point3<f64>,
    /// The drill axis at the breakthrough: the plunge is measured along it.
    plunge_axis: Vector3<f64>,
    /// Ticks since the breakthrough.
    plunge_ticks: usize,
    /// The tip's advance past `point_m` along `plunge_axis` over the last
    /// [`PLUNGE_WINDOW_TICKS`] ticks, a ring indexed by `plunge_ticks`.
    advance_m: [f64; PLUNGE_WINDOW_TICKS],
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

/// A trainee's drilling session.
#[derive(Debug, Clone)]
pub struct DrillingSession {
    config: SessionConfig,
    bone: DrilledVolume,
    path: PlannedPath,
    probe: BurrProbe,
    limiter: ForceLimiter,
    thermal: Thermal,
    pose: Option<Pose>,
    proxy_m: Point3<f64>,
    /// The registered device position last tick (stylus − offset), for the coupling's damping.
    prev_device_m: Point3<f64>,
    prev_proxy_m: Point3<f64>,
    /// The stylus position last tick, as the pose gave it: the hand's own motion.
    prev_stylus_m: Point3<f64>,
    /// Registration offset (m): stylus − where the tip's motion puts the hand.
    offset_m: Vector3<f64>,
    /// The density of the bone the burr has just come through (kg/m³): the highest cap density
    /// seen, forgotten over a burr radius of axial travel. A cap suddenly much softer than it is
    /// bone giving way.
    recent_density_kg_m3: f64,
    /// The tip's velocity over the last tick (m/s).
    tip_velocity_m_s: Vector3<f64>,
    /// Whether a cortex began to give way this tick (for the guidance brake).
    giving: bool,
    /// The guidance share's modes and state.
    guide: Guide,
    /// Tip depth (m) at which the planning CT shows the burr leaving the first cortex.
    planned_breakthrough_m: Option<f64>,
    /// The trainee's gain schedule over attempts, if fading.
    fading: Option<Fading>,
    /// This attempt's largest plunge and lateral deviation inside the bone (m), for fading.
    attempt_worst_m: (f64, f64),
    breakthrough: Breakthrough,
    state: SessionState,
}

impl DrillingSession {
    /// A session drilling `volume` along `path`.
    ///
    /// # Errors
    /// An invalid configuration.
    pub fn new(volume: Arc<Volume>, path: PlannedPath, config: SessionConfig) -> SimResult<Self> {
        config.validate()?;
        let probe = BurrProbe::new(volume.grid(), config.burr_radius_m);
        let limiter = ForceLimiter::new(config.device.clone())?;
        let thermal = Thermal::new(config.thermal.clone())?;
        let entry = path.entry_m();
        let state = Self::initial_state(&path, &thermal);
        Ok(Self {
            config,
            bone: DrilledVolume::new(volume),
            path,
            probe,
            limiter,
            thermal,
            pose: None,
            proxy_m: entry,
            prev_device_m: entry,
            prev_proxy_m: entry,
            prev_stylus_m: entry,
            offset_m: Vector3::zeros(),
            recent_density_kg_m3: 0.0,
            tip_velocity_m_s: Vector3::zeros(),
            giving: false,
            guide: Guide::new(GuidanceParams::default(), GuidanceMode::Paper, 0.0),
            planned_breakthrough_m: None,
            fading: None,
            attempt_worst_m: (0.0, 0.0),
            breakthrough: Breakthrough::default(),
            state,
        }
        .with_planned_breakthrough())
    }

    fn initial_state(path: &PlannedPath, thermal: &Thermal) -> SessionState {
        let entry = path.entry_m();
        SessionState {
            time_s: 0.0,
            ticks: 0,
            device_m: entry,
            tip_m: entry,
            axis: path.direction(),
            drill_on: false,
            spindle_rpm: 0.0,
            in_contact: false,
            cutting: false,
            layer: Layer::Outside,
            depth_m: 0.0,
            deviation_m: 0.0,
            feed_m_s: 0.0,
            thrust_n: 0.0,
            torque_n_m: 0.0,
            cutting_density_kg_m3: 0.0,
            force_n: Vector3::zeros(),
            temperature_c: thermal.temperature_c,
            peak_temperature_c: thermal.peak_c,
            time_above_47_s: 0.0,
            breakthroughs: 0,
            plunging: false,
            plunge_depth_m: 0.0,
            removed_mass_kg: 0.0,
            stale: true,
            rejected_poses: 0,
            registration_offset_m: Vector3::zeros(),
            device_thermal_load: 0.0,
            guidance_n: Vector3::zeros(),
            feedback_n: Vector3::zeros(),
            model_available: false,
        }
    }

    /// The configuration.
    #[must_use]
    pub fn config(&self) -> &SessionConfig {
        &self.config
    }

    /// The current state.
    #[must_use]
    pub fn state(&self) -> &SessionState {
        &self.state
    }

    /// The bone as drilled.
    #[must_use]
    pub fn bone(&self) -> &DrilledVolume {
        &self.bone
    }

    /// The planned path.
    #[must_use]
    pub fn path(&self) -> &PlannedPath {
        &self.path
    }

    /// Reserves room for `bricks` drilled bricks (a fresh, undrilled bone), so that ticks do not
    /// allocate until the session has drilled that much.
    pub fn reserve_bricks(&mut self, bricks: usize) {
        self.bone = DrilledVolume::with_reserve(self.bone.volume().clone(), bricks);
    }

    /// Changes the burr (drill tip) radius (m) from the next tick on, as when the trainee swaps
    /// bits: the bone drilled so far and the proxy's position stay. Allocation-free.
    ///
    /// # Errors
    /// A radius outside (0, [`MAX_BURR_RADIUS_M`]]; the session is unchanged.
    pub fn set_burr_radius(&mut self, radius_m: f64) -> SimResult<()> {
        check_burr_radius(radius_m)?;
        self.probe = BurrProbe::new(self.bone.volume().grid(), radius_m);
        self.config.burr_radius_m = radius_m;
        self.planned_breakthrough_m = self.planned_breakthrough();
        Ok(())
    }

    /// Sets a new planned path (depth and deviation are measured against it from now on).
    /// Allocation-free.
    pub fn set_path(&mut self, path: PlannedPath) {
        self.path = path;
        self.planned_breakthrough_m = self.planned_breakthrough();
    }

    fn with_planned_breakthrough(mut self) -> Self {
        self.planned_breakthrough_m = self.planned_breakthrough();
        self
    }

    /// The step (m) at which the planned path's layers are read, as a surgeon reads them off the
    /// planning CT (`dhg.bone.planning.planned_breakthrough_depth_m` samples the same).
    pub const PLAN_STEP_M: f64 = 0.25e-3;

    fn planned_breakthrough(&self) -> Option<f64> {
        self.path
            .first_cortex_exit_m(self.bone.volume(), Self::PLAN_STEP_M)
            .map(|exit| exit - self.config.burr_radius_m)
    }

    /// The tip depth (m) at which the planning CT shows the burr leaving the first cortex on
    /// the path (the cortex's end less the burr radius: the front leads the centre), if any.
    #[must_use]
    pub fn planned_breakthrough_depth_m(&self) -> Option<f64> {
        self.planned_breakthrough_m
    }

    /// Sets the guidance mode and gain (see [`crate::guidance`]). Gain 0 renders no guidance.
    ///
    /// # Errors
    /// A gain outside `0..=4` (nothing changes then).
    pub fn set_guidance(&mut self, mode: GuidanceMode, gain: f64) -> SimResult<()> {
        crate::guidance::check_gain(gain)?;
        self.guide.set_mode(mode);
        self.guide.set_gain(gain);
        Ok(())
    }

    /// Replaces the guidance limits and force laws.
    ///
    /// # Errors
    /// Invalid params (nothing changes then).
    pub fn set_guidance_params(&mut self, params: GuidanceParams) -> SimResult<()> {
        self.guide.set_params(params)
    }

    /// The guidance state.
    #[must_use]
    pub fn guide(&self) -> &Guide {
        &self.guide
    }

    /// A model reply: the predicted expert force (N). Sets the paper's guidance, predicted −
    /// the trainee's current force feedback, and returns it as mixed (gain applied, clamped).
    pub fn set_prediction(&mut self, predicted_n: Vector3<f64>) -> Vector3<f64> {
        self.guide.set_target(predicted_n - self.state.feedback_n)
    }

    /// Fades the guidance gain over attempts ([`Fading`]), or with `None` stops fading (the gain
    /// then stays as it is). Starts the schedule: this attempt's gain is its first.
    ///
    /// # Errors
    /// Invalid params (nothing changes then).
    pub fn set_fading(&mut self, params: Option<FadingParams>) -> SimResult<()> {
        self.fading = params.map(Fading::new).transpose()?;
        if let Some(f) = &self.fading {
            self.guide.set_gain(f.gain());
        }
        Ok(())
    }

    /// The fading schedule, if any.
    #[must_use]
    pub fn fading(&self) -> Option<&Fading> {
        self.fading.as_ref()
    }

    /// Restores the undrilled bone and a fresh state (as after [`new`](Self::new)); O(drilled
    /// bricks). The device goes on as it was: its force ramps down to rest at the rate limit and
    /// its motors keep their heat ([`reset_device`](Self::reset_device) also rests the device).
    /// With fading, an attempt that drilled (the stylus was felt) ends here and sets the next
    /// attempt's gain.
    pub fn reset(&mut self) {
        if let (Some(f), Some(_)) = (self.fading.as_mut(), self.pose) {
            let (plunge_m, deviation_m) = self.attempt_worst_m;
            self.guide.set_gain(f.finish_attempt(plunge_m, deviation_m));
        }
        self.attempt_worst_m = (0.0, 0.0);
        self.bone.reset();
        // The same device goes on: its force ramps down at the rate limit, its motors stay warm.
        self.limiter.release();
        self.thermal.reset();
        self.pose = None;
        let entry = self.path.entry_m();
        (self.proxy_m, self.prev_proxy_m, self.prev_device_m, self.prev_stylus_m) = (entry, entry, entry, entry);
        self.offset_m = Vector3::zeros();
        self.recent_density_kg_m3 = 0.0;
        self.tip_velocity_m_s = Vector3::zeros();
        self.giving = false;
        self.guide.reset();
        self.breakthrough = Breakthrough::default();
        self.state = Self::initial_state(&self.path, &self.thermal);
    }

    /// [`reset`](Self::reset), and the device at rest too (zero force, cold motors): for a
    /// session that a different device (a new client) takes over.
    pub fn reset_device(&mut self) {
        self.reset();
        self.limiter.reset();
    }

    /// Advances one 1 ms tick. `pose` is the newest stylus sample, or `None` if none arrived
    /// this tick; an invalid pose counts as none (and is counted). Without fresh poses the last
    /// one is held, and after the device's stale time the force ramps to zero.
    pub fn tick(&mut self, pose: Option<&Pose>) -> TickOutput {
        let dt = TICK_S;
        match pose {
            Some(p) if p.is_valid() => {
                if self.pose.is_none() {
                    // First contact with the stylus: the proxy starts where the device is.
                    self.proxy_m = p.position_m;
                    self.prev_proxy_m = p.position_m;
                    self.prev_device_m = p.position_m;
                    self.prev_stylus_m = p.position_m;
                    self.offset_m = Vector3::zeros();
                }
                self.pose = Some(*p);
                self.limiter.pose_received();
            }
            Some(_) => self.state.rejected_poses += 1,
            None => {}
        }
        self.giving = false;
        let desired = if let Some(pose) = self.pose {
            self.simulate(&pose, dt)
        } else {
            self.thermal.step(0.0, 0.0, 0.0, 0.0, dt);
            Vector3::zeros()
        };
        let input = GuideInput {
            tip_m: self.state.tip_m,
            tip_velocity_m_s: self.tip_velocity_m_s,
            axis: self.state.axis,
            path: &self.path,
            breakthrough_depth_m: self.planned_breakthrough_m,
            broken_through: self.state.breakthroughs > 0,
            giving: self.giving,
            temperature_c: self.thermal.temperature_c,
            necrosis_threshold_c: self.thermal.params().necrosis_threshold_c,
        };
        let share_n = self.guide.step(&input, dt);
        let force_n = self.limiter.step(desired + share_n, dt);
        let s = &mut self.state;
        s.ticks += 1;
        s.time_s = s.ticks as f64 * dt;
        s.force_n = force_n;
        s.guidance_n = share_n;
        s.feedback_n = force_n - share_n;
        s.model_available = self.guide.is_live();
        s.stale = self.limiter.is_stale();
        s.temperature_c = self.thermal.temperature_c;
        s.peak_temperature_c = self.thermal.peak_c;
        s.time_above_47_s = self.thermal.time_above_threshold_s;
        s.removed_mass_kg = self.bone.removed_mass_kg();
        s.registration_offset_m = self.offset_m;
        s.device_thermal_load = self.limiter.thermal_load();
        let worst = &mut self.attempt_worst_m;
        worst.0 = worst.0.max(s.plunge_depth_m);
        if s.depth_m > 0.0 {
            worst.1 = worst.1.max(s.deviation_m);
        }
        let feedback_n = s.feedback_n;
        let record = (s.ticks % RECORD_PERIOD_TICKS == 0).then(|| Record {
            time_s: s.time_s,
            features: [
                feedback_n.x,
                feedback_n.y,
                feedback_n.z,
                s.tip_m.x,
                s.tip_m.y,
                s.tip_m.z,
                f64::from(s.layer.id()),
                s.depth_m,
                s.temperature_c,
            ],
            drill_on: s.drill_on,
        });
        TickOutput { force_n, record }
    }

    /// One tick of the proxy, removal, thermal and breakthrough models; returns the force the
    /// coupling asks for (before the safety stage).
    fn simulate(&mut self, pose: &Pose, dt: f64) -> Vector3<f64> {
        let cfg = &self.config;
        let axis = pose.axis();
        let rpm = if pose.drill_on { pose.spindle_rpm } else { 0.0 };
        let hand_step = pose.position_m - self.prev_stylus_m;
        self.prev_stylus_m = pose.position_m;
        let hand_speed_ax = (hand_step.dot(&axis) / dt).max(0.0);
        let k = cfg.coupling_stiffness_n_per_m;
        let scale = cfg.force_scale();
        let diameter_m = 2.0 * cfg.burr_radius_m;
        let device = pose.position_m - self.offset_m;
        let goal = device - self.proxy_m;
        let push_ax = goal.dot(&axis);
        let zone = self.probe.cutting_zone(&self.bone, &self.proxy_m, &axis);
        let rho = zone.density_kg_m3;
        let cutting = rpm > 0.0 && rho > EMPTY_CAP_KG_M3 && push_ax > 0.0;
        let start_m = self.proxy_m;
        let mut feed = 0.0;
        let mut thrust = 0.0;
        if cutting {
            // The thrust is the hand's push on the bone: the coupling's stretch, but never more
            // than the device renders along the axis (what the hand actually pushes against).
            let rendered_ax = (-self.limiter.output_n().dot(&axis)).max(0.0);
            thrust = (k * push_ax).min(rendered_ax) / scale;
            let law = &cfg.cutting;
            self.recent_density_kg_m3 = self.recent_density_kg_m3.max(rho);
            let f_law = law.feed_for_thrust_m_s(rpm, thrust, rho, diameter_m);
            // Where a cortex gives way (the cap, and the undrilled bone straight ahead, much
            // softer than the bone the burr has just come through, while it cuts a cortex or
            // plunges out of one), the tip goes no faster than the hand, or than that bone would
            // let this thrust feed it. A cap that reads less bone for other reasons (a burr
            // tilting or wandering on the surface, its own bore) is cut as it comes.
            let recent = self.recent_density_kg_m3;
            let giving_way = self.breakthrough.in_cortex || self.state.plunging;
            let gives = giving_way && zone.ahead_pristine_density_kg_m3 < GIVE_FRACTION * recent;
            let giving = if gives { rho.max(GIVE_FRACTION * recent) } else { rho };
            let f_recent = law.feed_for_thrust_m_s(rpm, thrust, giving, diameter_m);
            let f = f_law.min(f_recent.max(hand_speed_ax));
            let advance = (f * dt).min(push_ax).min(cfg.max_proxy_speed_m_s * dt);
            self.proxy_m += axis * advance;
            feed = advance / dt;
            if f_law > f {
                // The softer bone resists this feed with less than the stretch pushes: the
                // stretch it no longer holds becomes registration offset, so the force drops to
                // the bone's resistance and the hand, no longer held, carries the tip on.
                let holds_m = law.thrust_n(rpm, feed, rho, diameter_m) * scale / k;
                let released = (push_ax - advance - holds_m).max(0.0);
                self.offset_m += axis * released;
                self.giving |= released > 0.0;
            }
            let lateral = goal - axis * push_ax;
            self.proxy_m = self.god_move(self.proxy_m, lateral, Some((axis, CAP_COS)), dt);
        } else {
            let moved = self.god_move(self.proxy_m, goal, None, dt);
            self.proxy_m = self.follow_the_hand(moved, hand_step);
        }
        let cfg = &self.config;
        let advance_ax = (self.proxy_m - start_m).dot(&axis);
        let device = pose.position_m - self.offset_m;
        let spring = self.proxy_m - device;
        let push_phys = k * spring.norm() / scale;
        if rpm > 0.0 {
            let contact = if cutting { 1.0 } else { (push_phys / cfg.lateral_cut_reference_n).min(1.0) };
            if contact > 0.0 {
                let radius_m = self.probe.cutting_radius_m(self.bone.volume().grid());
                let burr = Burr { center_m: self.proxy_m, radius_m };
                let cut = Cut { spindle_rpm: rpm, dt_s: dt, contact };
                // A burr moving along its axis clears what it swept. Burr, cut and axis are valid
                // by construction; an error here would change nothing.
                let _ = if advance_ax > 0.0 {
                    self.bone.remove_advancing(&burr, &cut, &axis, advance_ax)
                } else {
                    self.bone.remove(&burr, &cut)
                };
            }
        }
        self.recent_density_kg_m3 *= (-advance_ax.abs() / cfg.burr_radius_m).exp();
        // Coupling: spring to the proxy, damping on the relative velocity while apart.
        let v_device = (device - self.prev_device_m) / dt;
        let v_proxy = (self.proxy_m - self.prev_proxy_m) / dt;
        self.tip_velocity_m_s = v_proxy;
        self.prev_device_m = device;
        self.prev_proxy_m = self.proxy_m;
        let apart = spring.norm() > 1e-7;
        let force =
            spring * k + if apart { (v_proxy - v_device) * cfg.coupling_damping_n_s_per_m } else { Vector3::zeros() };

        let torque = if cutting { cfg.cutting.torque_n_m(rpm, feed, rho, diameter_m) } else { 0.0 };
        let thrust = if cutting && feed > 0.0 { thrust } else { 0.0 };
        self.thermal.step(torque, rpm * TAU / 60.0, thrust, feed, dt);
        self.track_breakthrough(rpm, cutting, &zone, &axis);

        let front = self.proxy_m + axis * self.probe.radius_m();
        let s = &mut self.state;
        s.device_m = pose.position_m;
        s.tip_m = self.proxy_m;
        s.axis = axis;
        s.drill_on = pose.drill_on;
        s.spindle_rpm = pose.spindle_rpm;
        s.in_contact = apart || zone.density_kg_m3 > EMPTY_CAP_KG_M3;
        s.cutting = cutting;
        s.layer = self.bone.volume().layer_at(&front).unwrap_or(Layer::Outside);
        s.depth_m = self.path.depth_m(&self.proxy_m);
        s.deviation_m = self.path.deviation_m(&self.proxy_m);
        s.feed_m_s = feed;
        s.thrust_n = thrust;
        s.torque_n_m = torque;
        s.cutting_density_kg_m3 = zone.density_kg_m3;
        force
    }

    /// Free motion (nothing is cut): the proxy moved from `self.proxy_m` to `moved` towards the
    /// device. It may follow the hand (`hand_step`, the stylus's motion this tick), and slide
    /// along a surface as slowly as a wall erodes, but not leap into a stretch that a surface
    /// stopped holding (the edge of a bone): the part of a move faster than the hand's by more
    /// than [`RELEASE_SLACK_M_S`] becomes registration offset. While the hand withdraws against
    /// the offset, the offset is bled off. Returns where the proxy ends.
    fn follow_the_hand(&mut self, moved: Point3<f64>, hand_step: Vector3<f64>) -> Point3<f64> {
        let from = self.proxy_m;
        let ran = (moved - from).norm();
        let allowed = hand_step.norm() + RELEASE_SLACK_M_S * TICK_S;
        let mut end = moved;
        if ran > allowed {
            // Back off along the path it came, to where it moved only as far as the hand did.
            let candidate = from + (moved - from) * (allowed / ran);
            let probe = |p: &Point3<f64>| self.probe.contact(&self.bone, p, None).points;
            end = if probe(&candidate) <= probe(&from) { candidate } else { from };
            self.offset_m += moved - end;
        }
        // Bleed the offset while the hand withdraws against it in free space.
        let offset = self.offset_m.norm();
        if offset > 0.0 && !self.state.plunging {
            let dir = self.offset_m / offset;
            let back = (-hand_step.dot(&dir)).max(0.0);
            if back > 0.0 && self.probe.contact(&self.bone, &end, None).points == 0 {
                let bleed = (OFFSET_BLEED * back).min(offset);
                self.offset_m -= dir * bleed;
            }
        }
        end
    }

    /// Moves the proxy from `from` by `delta` as far as the bone allows, sliding along surfaces.
    /// A move is refused when it brings more probe points into bone than the proxy already has
    /// (so a proxy that is already embedded can always back out).
    fn god_move(
        &self,
        from: Point3<f64>,
        delta: Vector3<f64>,
        ignore: Option<(Vector3<f64>, f64)>,
        dt: f64,
    ) -> Point3<f64> {
        let len = delta.norm();
        if len < 1e-12 {
            return from;
        }
        let h = self.bone.volume().grid().spacing_m();
        let max_step = 0.25 * h[0].min(h[1]).min(h[2]);
        let reach = len.min(self.config.max_proxy_speed_m_s * dt);
        let steps = (reach / max_step).ceil().clamp(1.0, 16.0);
        let step = delta * (reach / len / steps);
        let mut p = from;
        let mut inside = self.probe.contact(&self.bone, &p, ignore).points;
        for _ in 0..steps as usize {
            let candidate = self.probe.contact(&self.bone, &(p + step), ignore);
            if candidate.points == 0 || candidate.points <= inside {
                p += step;
                inside = candidate.points;
                continue;
            }
            let Some(normal) = candidate.normal() else { break };
            let into = step.dot(&normal);
            let slide = if into < 0.0 { step - normal * into } else { step };
            if slide.norm() < 1e-12 {
                break;
            }
            let slid = self.probe.contact(&self.bone, &(p + slide), ignore);
            if slid.points == 0 || slid.points <= inside {
                p += slide;
                inside = slid.points;
            } else {
                break;
            }
        }
        p
    }

    fn track_breakthrough(&mut self, rpm: f64, cutting: bool, zone: &CuttingZone, axis: &Vector3<f64>) {
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
