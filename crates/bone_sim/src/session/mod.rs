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

mod breakthrough;
mod config;
mod coupling;
mod state;

use std::sync::Arc;

use nalgebra::{Point3, Vector3};

pub use config::{check_burr_radius, SessionConfig};
pub use state::{Pose, SessionState, TickOutput};

use crate::contact::BurrProbe;
use crate::device::ForceLimiter;
use crate::error::{SimError, SimResult};
use crate::guidance::{Fading, FadingParams, GuidanceMode, GuidanceParams, Guide, GuideInput};
use crate::path::PlannedPath;
use crate::record::{Record, RECORD_PERIOD_TICKS, TICK_S};
use crate::thermal::Thermal;
use crate::volume::drilled::DrilledVolume;
use crate::volume::layer::Layer;
use crate::volume::Volume;
use breakthrough::Breakthrough;

// The breakthrough detector's and the proxy's thresholds below are the project's tuning on the
// phantom and the virtual surgeons (no source gives them); each says what it separates. The
// published figures they are checked against (plunge depths, feeds) are in docs/fidelity.md.
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
    /// The tick that makes the next 10 Hz record: 100, 200, … unless the engine moved it to keep
    /// a server's sessions on one 100 ms grid ([`set_next_record_in`](Self::set_next_record_in)).
    next_record_tick: u64,
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
            next_record_tick: RECORD_PERIOD_TICKS,
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

    /// The stylus pose the last tick used (the newest valid one), if one has arrived.
    #[must_use]
    pub fn pose(&self) -> Option<&Pose> {
        self.pose.as_ref()
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
    /// planning CT (Python reads it as `dhg.core.path.PLAN_STEP_M`, the default step of
    /// `dhg.bone.planning`'s readings).
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
        self.next_record_tick = RECORD_PERIOD_TICKS;
        self.state = Self::initial_state(&self.path, &self.thermal);
    }

    /// Makes the `ticks`-th tick from now (1 to 2 × [`RECORD_PERIOD_TICKS`]) the next to make a
    /// 10 Hz record, and every [`RECORD_PERIOD_TICKS`]-th after it; a fresh or reset session
    /// records at ticks 100, 200, …. The records themselves are unchanged, only which ticks
    /// make them: the engine puts every session's records on one 100 ms grid, so that their
    /// model queries reach the model together and share its forward passes
    /// (`docs/decisions/0028-records-on-one-grid.md`).
    ///
    /// # Errors
    /// `ticks` outside 1 to 2 × [`RECORD_PERIOD_TICKS`] (nothing changes then).
    pub fn set_next_record_in(&mut self, ticks: u64) -> SimResult<()> {
        if !(1..=2 * RECORD_PERIOD_TICKS).contains(&ticks) {
            return Err(SimError::InvalidParameter {
                name: "ticks to the next record",
                value: ticks as f64,
                reason: "must be 1 to twice RECORD_PERIOD_TICKS (200)",
            });
        }
        self.next_record_tick = self.state.ticks + ticks;
        Ok(())
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
            cutting_feed_m_s: if self.pose.is_some() { self.state.feed_m_s } else { 0.0 },
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
        let due = s.ticks == self.next_record_tick;
        if due {
            self.next_record_tick += RECORD_PERIOD_TICKS;
        }
        let record = due.then(|| Record {
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
}
