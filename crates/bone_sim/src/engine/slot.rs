//! One session slot as the tick thread sees it: the drilling session (which renders its own
//! guidance and passes bone force + guidance through its device limits) and its pose input.

use std::time::Instant;

use nalgebra::Vector3;

use super::handoff::{Output, PoseSample};
use crate::error::SimResult;
use crate::guidance::{GuidanceMode, GuidanceParams};
use crate::path::PlannedPath;
use crate::protocol::{flags, ForceMsg, GuidanceMsg, StateMsg};
use crate::record::RECORD_PERIOD_TICKS;
use crate::session::{DrillingSession, SessionState};

/// A tick-side session slot.
#[derive(Debug)]
pub(crate) struct Slot {
    pub(crate) active: bool,
    pub(crate) generation: u32,
    pub(crate) session: DrillingSession,
    poses: triple_buffer::Output<PoseSample>,
    /// Whether the pose in `poses`' output buffer is newer than the last one ticked.
    fresh: bool,
    pose_seq: u32,
    pose_time_ns: u64,
    record_seq: u32,
    /// The attempt the records belong to: counted up (wrapping) at each activation and reset.
    attempt: u32,
    /// Ticks since the engine started, over every session the slot held (never reset).
    order: u64,
    voxel_m3: f64,
    /// The burr a fresh session starts with (m).
    default_burr_m: f64,
    /// Where the engine's 100 ms record grid starts (see [`super::ticks_to_grid`]).
    record_grid: Instant,
}

/// How far off the record grid (tick periods) a record may come before the next is moved towards
/// it: a session on the grid records within half a tick of its marks, one a stall put off it further.
const GRID_TOLERANCE_TICKS: f64 = 1.5;
/// The most (ticks) one record interval is shortened or lengthened to bring a session back to
/// the grid: a stall that skipped 40 ticks is made up within four records, while each window the
/// model reads keeps its records 90–110 ms apart. Why: `docs/decisions/0028-records-on-one-grid.md`.
const GRID_SLEW_TICKS: f64 = 10.0;

fn flags_of(s: &SessionState) -> u16 {
    let mut f = 0;
    for (on, bit) in [
        (s.drill_on, flags::DRILL_ON),
        (s.in_contact, flags::IN_CONTACT),
        (s.cutting, flags::CUTTING),
        (s.plunging, flags::PLUNGING),
        (s.stale, flags::STALE),
    ] {
        if on {
            f |= bit;
        }
    }
    f
}

fn v3(p: &nalgebra::Point3<f64>) -> Vector3<f64> {
    p.coords
}

impl Slot {
    pub(crate) fn new(
        session: DrillingSession,
        guidance: GuidanceParams,
        poses: triple_buffer::Output<PoseSample>,
        record_grid: Instant,
    ) -> SimResult<Self> {
        let mut session = session;
        session.set_guidance_params(guidance)?;
        let voxel_m3 = session.bone().volume().grid().voxel_volume_m3();
        let default_burr_m = session.config().burr_radius_m;
        Ok(Self {
            active: false,
            generation: 0,
            session,
            poses,
            fresh: false,
            pose_seq: 0,
            pose_time_ns: 0,
            record_seq: 0,
            attempt: 0,
            order: 0,
            voxel_m3,
            default_burr_m,
            record_grid,
        })
    }

    /// Ticks since the engine started, over every session the slot held: the `order` of its
    /// newest force.
    pub(crate) fn order(&self) -> u64 {
        self.order
    }

    /// Takes in the newest pose if one came since the last call; returns whether one did.
    pub(crate) fn poll_pose(&mut self) -> bool {
        let newer = self.poses.update();
        self.fresh |= newer;
        newer
    }

    /// When the server received the pose waiting to be ticked (`None`: none waits, or it was not
    /// stamped).
    pub(crate) fn pending_received(&self) -> Option<Instant> {
        if self.fresh {
            self.poses.peek_output_buffer().received
        } else {
            None
        }
    }

    /// Whether a pose newer than the last one ticked is waiting (as of the last
    /// [`poll_pose`](Self::poll_pose)).
    pub(crate) fn pose_pending(&self) -> bool {
        self.fresh
    }

    /// Starts a fresh session at `now`: undrilled bone, new state, no guidance, its first record
    /// on the engine's record grid (`None`: stepped offline, off any clock; it records at ticks
    /// 100, 200, …).
    pub(crate) fn activate(
        &mut self,
        generation: u32,
        path: PlannedPath,
        mode: GuidanceMode,
        gain: f64,
        now: Option<Instant>,
    ) {
        self.session.set_path(path);
        // Valid: it is the radius the session was built with.
        let _ = self.session.set_burr_radius(self.default_burr_m);
        self.session.reset_device(); // a new client: its device starts at rest
        self.set_guidance(mode, gain);
        self.generation = generation;
        self.active = true;
        (self.pose_seq, self.pose_time_ns, self.record_seq) = (0, 0, 0);
        self.attempt = self.attempt.wrapping_add(1);
        self.first_record_on_grid(now);
    }

    /// A new attempt at `now` (see [`activate`](Self::activate)).
    pub(crate) fn reset(&mut self, now: Option<Instant>) {
        self.session.reset();
        self.record_seq = 0;
        self.attempt = self.attempt.wrapping_add(1);
        self.first_record_on_grid(now);
    }

    fn first_record_on_grid(&mut self, now: Option<Instant>) {
        if let Some(now) = now {
            // In range by construction (1 to 100), so this cannot fail.
            let _ = self.session.set_next_record_in(super::ticks_to_grid(self.record_grid, now));
        }
    }

    /// After a record made at `now`: if it came off the grid (a stall skipped ticks), the next
    /// comes up to [`GRID_SLEW_TICKS`] sooner or later, towards the grid.
    fn keep_records_on_grid(&mut self, now: Instant) {
        let off = super::off_grid_ticks(self.record_grid, now);
        if off.abs() > GRID_TOLERANCE_TICKS {
            let next = RECORD_PERIOD_TICKS as f64 - off.round().clamp(-GRID_SLEW_TICKS, GRID_SLEW_TICKS);
            // 90 to 110 ticks, within the allowed range.
            let _ = self.session.set_next_record_in(next as u64);
        }
    }

    pub(crate) fn set_guidance(&mut self, mode: GuidanceMode, gain: f64) {
        // The gain was checked by the sender; a bad one would leave the guidance as it was.
        let _ = self.session.set_guidance(mode, gain);
    }

    /// Applies a model reply: guidance = predicted expert force − the current force feedback.
    pub(crate) fn prediction(
        &mut self,
        idx: u16,
        window_seq: u32,
        predicted_n: [f64; 3],
        latency_s: f64,
        pose_time_ns: u64,
    ) -> Output {
        let predicted = Vector3::from(predicted_n);
        let guidance_n = self.session.set_prediction(predicted);
        let gain = self.session.guide().gain();
        Output::Guidance {
            slot: idx,
            generation: self.generation,
            msg: GuidanceMsg {
                // The reply is fresh (the model is available); the guidance is felt when the gain
                // and the mixed guidance are not zero.
                flags: flags::MODEL_AVAILABLE
                    | if gain > 0.0 && guidance_n != Vector3::zeros() { flags::GUIDANCE_ACTIVE } else { 0 },
                window_seq,
                pose_client_time_ns: pose_time_ns,
                tick: self.session.state().ticks,
                predicted_force_n: predicted,
                guidance_n,
                model_latency_s: latency_s,
                gain,
            },
        }
    }

    /// One 1 ms tick at `now` (`None`: stepped offline): newest pose in, force (and every 100th
    /// tick the state) out. Returns when the server received the fresh pose it used, if it had one.
    pub(crate) fn tick(&mut self, idx: u16, now: Option<Instant>, emit: impl FnMut(Output)) -> Option<Instant> {
        self.tick_with(idx, now, true, emit)
    }

    /// A tick without a pose, as of its scheduled time `at`: the session holds its last pose, and
    /// a pose waiting (one that came after `at`) stays for the tick that follows.
    pub(crate) fn hold_tick(&mut self, idx: u16, at: Instant, emit: impl FnMut(Output)) {
        self.tick_with(idx, Some(at), false, emit);
    }

    fn tick_with(
        &mut self,
        idx: u16,
        now: Option<Instant>,
        take_pose: bool,
        mut emit: impl FnMut(Output),
    ) -> Option<Instant> {
        let mut fresh = None;
        let mut received = None;
        if take_pose {
            self.poll_pose();
        }
        if take_pose && std::mem::take(&mut self.fresh) {
            let s = *self.poses.peek_output_buffer();
            if s.generation == self.generation {
                if let Some(p) = s.pose {
                    fresh = Some(p);
                    (self.pose_seq, self.pose_time_ns) = (s.seq, s.client_time_ns);
                    received = s.received;
                }
            }
        }
        let out = self.session.tick(fresh.as_ref());
        self.order += 1;
        let rendered = out.force_n;
        let s = self.session.state();
        let share = s.guidance_n;
        let mut fl = flags_of(s);
        if s.model_available {
            fl |= flags::MODEL_AVAILABLE;
        }
        if share.norm() > 0.0 {
            fl |= flags::GUIDANCE_ACTIVE;
        }
        emit(Output::Force {
            slot: idx,
            generation: self.generation,
            received,
            order: self.order,
            published: false,
            pose: self.session.pose().copied(),
            msg: ForceMsg {
                flags: fl,
                pose_seq: self.pose_seq,
                pose_client_time_ns: self.pose_time_ns,
                tick: s.ticks,
                force_n: rendered,
                guidance_n: share,
                tip_m: v3(&s.tip_m),
                depth_m: s.depth_m,
                deviation_m: s.deviation_m,
                temperature_c: s.temperature_c,
                plunge_depth_m: s.plunge_depth_m,
                layer: s.layer.id(),
                breakthroughs: s.breakthroughs.min(u32::from(u16::MAX)) as u16,
            },
        });
        if let Some(record) = out.record {
            self.record_seq += 1;
            emit(Output::State {
                slot: idx,
                generation: self.generation,
                attempt: self.attempt,
                record,
                msg: StateMsg {
                    flags: fl,
                    record_seq: self.record_seq,
                    time_s: record.time_s,
                    features: record.features,
                    removed_mass_kg: s.removed_mass_kg,
                    removed_volume_m3: self.session.bone().removed_voxels() as f64 * self.voxel_m3,
                    peak_temperature_c: s.peak_temperature_c,
                    time_above_47_s: s.time_above_47_s,
                    thrust_n: s.thrust_n,
                    spindle_rpm: s.spindle_rpm,
                    plunge_depth_m: s.plunge_depth_m,
                    breakthroughs: s.breakthroughs.min(u32::from(u16::MAX)) as u16,
                    rejected_poses: s.rejected_poses.min(u64::from(u32::MAX)) as u32,
                    deviation_m: s.deviation_m,
                    guidance_gain: self.session.guide().gain(),
                },
            });
            if let Some(now) = now {
                self.keep_records_on_grid(now);
            }
        }
        received
    }
}
