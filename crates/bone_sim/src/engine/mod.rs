//! The real-time engine: every session slot stepped once per 1 ms.
//!
//! A session ticks on one of two threads. A pose that finds its slot due ticks it on the thread
//! that received it ([`PoseTicker`]; with Zenoh, the thread of the pose's subscriber callback,
//! which then puts the force itself): no hand-off, no wake-up between a pose and its force. The
//! tick thread ([`TickCore`], run by [`TickThread`]) ticks what no pose starts (a slot whose pose
//! is late or came early, a silent client) and applies commands. Each slot is behind a claim
//! (`Mutex::try_lock`, which never waits): whoever holds it ticks; the other side goes on, the
//! tick thread retrying within [`CLAIM_RETRY`], the pose's thread leaving the pose to the tick
//! thread. Around that, everything is lock-free and made at start-up ([`handoff`]): an SPSC ring
//! of commands in, a bounded multi-producer queue of outputs out, a triple buffer per slot
//! carrying the newest pose, and one triple buffer for bone snapshots. Sessions, their reserved
//! bricks and the queues are all allocated before the first tick, so a tick never allocates,
//! waits for a lock or does I/O.
//!
//! Why: `docs/decisions/0023-tick-on-the-pose-thread.md`.
//!
//! When a slot ticks, locked to its client's poses, and how ticks without a pose run:
//! `engine/schedule.rs` (its items are re-exported here).
//!
//! A pose that cannot tick on its own thread (early, or its slot claimed) wakes the tick thread,
//! and so does every command ([`CommandSender`]): the tick thread sleeps until the earliest time
//! a slot needs it (a waiting pose's tick, or a look), not a period at most. Why:
//! `docs/decisions/0024-the-tick-thread-sleeps-to-its-deadlines.md`.

pub mod handoff;
pub mod realtime;
mod schedule;
mod slot;
pub mod stats;
mod tick_thread;

use std::sync::atomic::Ordering;
use std::sync::{Arc, Mutex, MutexGuard, OnceLock, TryLockError};
use std::thread::Thread;
use std::time::{Duration, Instant};

use crate::error::{SimError, SimResult};
use crate::guidance::{check_gain, GuidanceMode, GuidanceParams};
use crate::path::PlannedPath;
use crate::session::{DrillingSession, SessionConfig};
use crate::volume::drilled::DrilledVolume;
use crate::volume::Volume;
use handoff::{Command, Output, PoseSample};
pub use schedule::{
    off_grid_ticks, ticks_to_grid, EARLY_PERIODS, FAST_CLIENT_POSES_PER_TICK, GRACE_PERIODS, HOLD_BURST_PERIODS,
    HOLD_LOOK_PERIODS, LOCK_MIN_GAP_PERIODS, LOCK_RATE, MAX_POSE_WAIT_PERIODS, WAKE_SLACK_PERIODS,
};
use schedule::{Schedule, SlotState};
use slot::Slot;
use stats::TickStats;
pub use tick_thread::TickThread;

/// Most session slots an engine may have.
pub const MAX_SESSIONS: usize = 1024;
/// Outputs the ring holds per slot (ticks of slack before the comm side must drain it).
const OUTPUT_SLACK_PER_SLOT: usize = 128;
/// Commands applied per tick at most (the rest wait for the next tick).
const COMMANDS_PER_TICK: usize = 256;
/// How soon the tick thread looks again at a slot it found claimed by a pose's thread (which
/// holds it for one tick, a few µs), or at a command for it.
pub const CLAIM_RETRY: Duration = Duration::from_micros(50);
/// Longest the tick thread sleeps when no slot is due: what a command handed over without waking
/// it (none in the server: [`CommandSender`] wakes it) would wait at most.
pub const IDLE_WAKE: Duration = Duration::from_millis(20);
/// The tick period (1 kHz).
///
/// Why this value: `docs/decisions/0005-pose-locked-schedule.md`.
pub const TICK_PERIOD: Duration = Duration::from_millis(1);
// The schedule's period and the simulation's step are one fact: a change to one must be made to both.
const _: () = assert!(TICK_PERIOD.as_nanos() as f64 == crate::record::TICK_S * 1e9);

/// Claims a slot if no other thread holds it (never waits). A tick that panicked left its slot
/// consistent at each step, so a poisoned claim is taken over.
fn claim(cell: &Mutex<SlotState>) -> Option<MutexGuard<'_, SlotState>> {
    match cell.try_lock() {
        Ok(g) => Some(g),
        Err(TryLockError::Poisoned(p)) => Some(p.into_inner()),
        Err(TryLockError::WouldBlock) => None,
    }
}

/// Waits for a slot's claim (tests and diagnostics only: the real-time paths use [`claim`]).
fn claim_waiting(cell: &Mutex<SlotState>) -> MutexGuard<'_, SlotState> {
    cell.lock().unwrap_or_else(std::sync::PoisonError::into_inner)
}

/// The outputs' queue: every ticking thread pushes, the comm side pops.
pub type OutputQueue = crossbeam_queue::ArrayQueue<Output>;

/// Where a session's pose ticks it.
///
/// Why: `docs/decisions/0023-tick-on-the-pose-thread.md`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum TickOn {
    /// A pose that finds its slot due ticks it on the thread that received it, and its force
    /// leaves from there (the default); the tick thread ticks the rest.
    #[default]
    Pose,
    /// Every pose is handed to the tick thread, which ticks, and the comm thread puts the force:
    /// two thread hand-offs per pose (the design before issue 24, kept for comparison).
    Thread,
}

impl TickOn {
    /// The setting's name: `"pose"` or `"thread"`.
    #[must_use]
    pub fn name(self) -> &'static str {
        match self {
            Self::Pose => "pose",
            Self::Thread => "thread",
        }
    }
}

/// What [`PoseTicker::tick`] did with a pose.
#[derive(Debug, Clone, Copy)]
#[allow(clippy::large_enum_variant)] // returned by value on the pose's thread: boxing would allocate per tick
pub enum PoseTick {
    /// The slot ticked on this thread, and its outputs are queued (in the slot's order).
    Ticked {
        /// A copy of the force queued (an [`Output::Force`]): for the caller to put when it is
        /// marked `published`. When ticks without a pose ran before it (its client was later
        /// than the grace), or the slot's previous force still waited for the comm side, it is
        /// not: the waiting forces and this one leave from the comm side, in order.
        force: Output,
        /// Whether this tick also queued the 10 Hz state (the comm side publishes it).
        state: bool,
    },
    /// The slot was not due (the pose came early) or not ready (its session's commands are not
    /// applied yet): the tick thread ticks it at its time.
    NotDue,
    /// As [`NotDue`](Self::NotDue), but ticks without a pose that fell due before this pose ran
    /// here first, their outputs queued: the comm side must be woken to send them.
    Held,
    /// Another thread held the slot (the tick thread, ticking it or applying a command).
    Claimed,
}

/// A handle that ticks a slot on the calling thread when a pose makes it due (see the module
/// docs). Cheap to clone; every clone shares the slots.
#[derive(Debug, Clone)]
pub struct PoseTicker {
    cells: Arc<[Mutex<SlotState>]>,
    outputs: Arc<OutputQueue>,
    stats: Arc<TickStats>,
    waker: Arc<TickWaker>,
}

impl PoseTicker {
    /// Ticks `slot` now if the pose just handed over (written for `generation`) makes it due:
    /// the same schedule as the tick thread's, judged at `now`. `out_up_to` is the `order` of the
    /// slot's newest force that has left (or been let go); if the slot has made a newer one, that
    /// force still waits for the comm side, and a force put here would overtake it: the tick
    /// runs here all the same, but its force is queued for the comm side, behind the waiting one
    /// (not `published`, as after ticks without a pose), and counted in `pose_ticks_behind`.
    /// (Until 2026-12-08 such a pose was left to the tick thread, which woke to tick it and then
    /// woke the comm side: two hand-offs where one is needed.)
    ///
    /// The tick's outputs are queued before the slot is let go, so a slot's outputs queue in the
    /// order its ticks ran, wherever they ran (the recorders' batches read a tick that goes back as
    /// a reset). With `publish_here` the force is queued marked `published`: the caller puts it
    /// (the copy returned), and the comm side only records it. Never waits, allocates or does I/O.
    #[must_use]
    pub fn tick(&self, slot: u16, generation: u32, now: Instant, out_up_to: u64, publish_here: bool) -> PoseTick {
        let left = |why: PoseTick| {
            let i = usize::from(matches!(why, PoseTick::Claimed));
            self.stats.poses_left[i].fetch_add(1, Ordering::Relaxed);
            why
        };
        let Some(cell) = self.cells.get(usize::from(slot)) else { return left(PoseTick::NotDue) };
        let Some(mut st) = claim(cell) else { return left(PoseTick::Claimed) };
        if !st.slot.active || st.slot.generation != generation {
            return left(PoseTick::NotDue);
        }
        // The slot's newest force still waits for the comm side: this one must follow it out.
        let behind = st.slot.order() > out_up_to;
        let (mut force, mut state) = (None, false);
        let (outputs, stats) = (&*self.outputs, &*self.stats);
        // Ticks without a pose that fell due before this pose came run first, their forces left
        // to the comm side; then this pose's force must follow them from there too.
        let held = st.catch_up(slot, now, stats, |out| {
            state |= matches!(out, Output::State { .. });
            TickCore::emit(outputs, stats, out);
        });
        let publish_here = publish_here && held == 0 && !behind;
        let (ticked, _) = st.pose_tick(slot, now, stats, |out| {
            let out = match out {
                Output::Force { slot, generation, msg, pose, received, order, .. } => {
                    let f = Output::Force { slot, generation, msg, pose, received, order, published: publish_here };
                    force = Some(f);
                    f
                }
                other => {
                    state = true;
                    other
                }
            };
            TickCore::emit(outputs, stats, out);
        });
        drop(st);
        let ticks = held + u32::from(ticked);
        if ticks > 0 {
            self.stats.ticks.fetch_add(u64::from(ticks), Ordering::Relaxed);
        }
        match force {
            Some(force) if ticked => {
                self.stats.pose_thread_ticks.fetch_add(1, Ordering::Relaxed);
                if behind {
                    self.stats.pose_ticks_behind.fetch_add(1, Ordering::Relaxed);
                }
                PoseTick::Ticked { force, state }
            }
            _ if held > 0 => left(PoseTick::Held),
            _ => left(PoseTick::NotDue),
        }
    }

    /// After any [`PoseTick`] but `Ticked`: wakes the tick thread, so that it ticks the pose at
    /// its time (an early pose's, which is sooner than the slot's deadline) or at once.
    pub fn wake_tick_thread(&self) {
        self.waker.wake();
    }

    /// The drilling session of `slot` (tests and diagnostics: waits for a tick on another thread
    /// to end, and holds the slot, so that no tick runs, until dropped).
    #[must_use]
    pub fn session(&self, slot: usize) -> Option<SessionRef<'_>> {
        self.cells.get(slot).map(|c| SessionRef(claim_waiting(c)))
    }
}

/// Wakes the tick thread once it runs (before, there is nothing to wake: it starts by looking).
#[derive(Debug, Default)]
pub struct TickWaker(OnceLock<Thread>);

impl TickWaker {
    /// Unparks the tick thread: a wake-up before it parks is kept (its next park returns at once).
    pub fn wake(&self) {
        if let Some(t) = self.0.get() {
            t.unpark();
        }
    }

    /// Names the calling thread as the one to wake (the tick thread, as it starts).
    pub(crate) fn register(&self) {
        let _ = self.0.set(std::thread::current());
    }
}

/// The comm side's end of the command ring: every command pushed wakes the tick thread, so that
/// it is applied now, not at the next deadline (single producer: keep it behind one owner).
#[derive(Debug)]
pub struct CommandSender {
    ring: rtrb::Producer<Command>,
    waker: Arc<TickWaker>,
}

impl CommandSender {
    /// Queues `cmd` for the tick thread and wakes it.
    ///
    /// # Errors
    /// The ring is full (the tick thread is stalled).
    pub fn push(&mut self, cmd: Command) -> SimResult<()> {
        self.ring.push(cmd).map_err(|_| SimError::Engine("the engine's command ring is full".into()))?;
        self.waker.wake();
        Ok(())
    }

    /// Commands the ring can take now (its one producer is this sender, so no other push can
    /// take them before this sender's next).
    #[must_use]
    pub fn free(&self) -> usize {
        self.ring.slots()
    }
}

/// How the tick and comm threads wait for their next event.
///
/// Why: `docs/decisions/0003-spin-or-sleep.md`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum WaitMode {
    /// Sleep until the next deadline or wake-up: idle cores stay idle (the default).
    #[default]
    Sleep,
    /// Busy-wait while a session is open: the tick and comm threads each keep a core at 100 %, so
    /// that no wake-up latency (0.05 to several ms on a virtual machine without real-time
    /// scheduling) is added to a force. With no session they sleep. For hosts with cores to
    /// spare; on a 2-core machine it starves everything else. The tick thread then keeps normal
    /// scheduling (see [`TickThread::spawn`]).
    Spin,
}

impl WaitMode {
    /// The mode's name in settings and health reports: `"sleep"` or `"spin"`.
    #[must_use]
    pub fn name(self) -> &'static str {
        match self {
            Self::Sleep => "sleep",
            Self::Spin => "spin",
        }
    }

    /// The mode named `name` (`"sleep"` or `"spin"`).
    ///
    /// # Errors
    /// Any other name.
    pub fn from_name(name: &str) -> SimResult<Self> {
        match name {
            "sleep" => Ok(Self::Sleep),
            "spin" => Ok(Self::Spin),
            _ => Err(SimError::InvalidOption { name: "wait", value: name.to_owned(), allowed: "'sleep', 'spin'" }),
        }
    }
}

/// Session slots of an engine, by default.
pub const DEFAULT_MAX_SESSIONS: usize = 16;

/// Engine settings.
#[derive(Debug, Clone)]
pub struct EngineConfig {
    /// Session slots, allocated up front (each holds `reserve_bricks` bricks of 1 KiB plus a brick table).
    pub max_sessions: usize,
    /// Settings of every drilling session.
    pub session: SessionConfig,
    /// The planned path of a session that does not set its own.
    pub default_path: PlannedPath,
    /// Guidance limits.
    pub guidance: GuidanceParams,
    /// Guidance mode of a new session.
    pub default_mode: GuidanceMode,
    /// Guidance gain of a new session.
    pub default_gain: f64,
    /// Drilled bricks each session may hold before a tick would allocate.
    pub reserve_bricks: usize,
    /// How the tick and comm threads wait.
    pub wait: WaitMode,
}

/// How a new session is guided: its mode and gain, and the guidance laws every session runs
/// (what a server's `about` reply says, for a recording's dataset card).
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct NewSessionGuidance {
    /// Guidance mode of a new session (`set_guidance` may change a session's).
    pub mode: GuidanceMode,
    /// Guidance gain of a new session (a fading schedule or `set_guidance` may change it).
    pub gain: f64,
    /// The guidance laws and limits (every session's; the server's settings applied).
    pub params: GuidanceParams,
}

impl EngineConfig {
    /// How a new session is guided.
    #[must_use]
    pub fn new_session_guidance(&self) -> NewSessionGuidance {
        NewSessionGuidance { mode: self.default_mode, gain: self.default_gain, params: self.guidance.clone() }
    }

    /// Default settings for a path.
    #[must_use]
    pub fn new(default_path: PlannedPath) -> Self {
        Self {
            max_sessions: DEFAULT_MAX_SESSIONS,
            session: SessionConfig::default(),
            default_path,
            guidance: GuidanceParams::default(),
            default_mode: GuidanceMode::default(),
            default_gain: 1.0,
            reserve_bricks: 1024,
            wait: WaitMode::default(),
        }
    }

    /// Checks every field.
    ///
    /// # Errors
    /// Any invalid value.
    pub fn validate(&self) -> SimResult<()> {
        if self.max_sessions == 0 || self.max_sessions > MAX_SESSIONS {
            return Err(SimError::InvalidParameter {
                name: "max_sessions",
                value: self.max_sessions as f64,
                reason: "must be within 1..=1024",
            });
        }
        self.session.validate()?;
        self.guidance.validate()?;
        check_gain(self.default_gain)?;
        Ok(())
    }
}

/// A copy of one session's bone, taken on request for X-ray views.
#[derive(Debug, Clone)]
pub struct Snapshot {
    /// Slot it was taken from.
    pub slot: u16,
    /// Slot generation at the time.
    pub generation: u32,
    /// The bone as drilled.
    pub bone: DrilledVolume,
}

/// What the tick thread holds: the slots (shared, each behind its claim, with the
/// [`PoseTicker`]s), the command ring's consumer and the snapshot buffer.
#[derive(Debug)]
pub struct TickCore {
    cells: Arc<[Mutex<SlotState>]>,
    /// Per slot: whether it was active when last claimed (counted while another thread holds it).
    was_active: Vec<bool>,
    commands: rtrb::Consumer<Command>,
    outputs: Arc<OutputQueue>,
    snapshot: triple_buffer::Input<Snapshot>,
    default_path: PlannedPath,
    stats: Arc<TickStats>,
    /// Commands the last [`TickCore::tick_due`] applied.
    applied: usize,
    /// Ticks without a pose run before those commands.
    held: u32,
    waker: Arc<TickWaker>,
}

/// The comm side's ends of the handoff structures.
#[derive(Debug)]
pub struct EngineLink {
    /// Commands into the tick thread (single producer: keep it behind one owner).
    pub commands: CommandSender,
    /// Outputs of every tick, wherever it ran (pop from one consumer).
    pub outputs: Arc<OutputQueue>,
    /// Ticks a slot on the thread that received its pose.
    pub ticker: PoseTicker,
    /// One newest-pose writer per slot.
    pub poses: Vec<triple_buffer::Input<PoseSample>>,
    /// Bone snapshots.
    pub snapshot: triple_buffer::Output<Snapshot>,
    /// Tick statistics.
    pub stats: Arc<TickStats>,
}

/// Builds the tick core and its link, allocating every session up front.
///
/// # Errors
/// An invalid configuration.
pub fn build(volume: &Arc<Volume>, config: &EngineConfig) -> SimResult<(TickCore, EngineLink)> {
    config.validate()?;
    let n = config.max_sessions;
    let (commands_tx, commands_rx) = rtrb::RingBuffer::new(4 * COMMANDS_PER_TICK.max(n));
    let outputs = Arc::new(OutputQueue::new(OUTPUT_SLACK_PER_SLOT * n + 1024));
    let now = Instant::now();
    let mut slots = Vec::with_capacity(n);
    let mut poses = Vec::with_capacity(n);
    for _ in 0..n {
        let (tx, rx) = triple_buffer::triple_buffer(&PoseSample::default());
        let mut session = DrillingSession::new(volume.clone(), config.default_path.clone(), config.session.clone())?;
        session.reserve_bricks(config.reserve_bricks);
        let slot = Slot::new(session, config.guidance.clone(), rx, now)?;
        slots.push(Mutex::new(SlotState { slot, schedule: Schedule::new(now) }));
        poses.push(tx);
    }
    let blank =
        Snapshot { slot: 0, generation: 0, bone: DrilledVolume::with_reserve(volume.clone(), config.reserve_bricks) };
    let (snap_tx, snap_rx) = triple_buffer::triple_buffer(&blank);
    let stats = Arc::new(TickStats::default());
    let waker = Arc::new(TickWaker::default());
    let cells: Arc<[Mutex<SlotState>]> = slots.into();
    let ticker =
        PoseTicker { cells: cells.clone(), outputs: outputs.clone(), stats: stats.clone(), waker: waker.clone() };
    let core = TickCore {
        was_active: vec![false; cells.len()],
        cells,
        commands: commands_rx,
        outputs: outputs.clone(),
        snapshot: snap_tx,
        default_path: config.default_path.clone(),
        stats: stats.clone(),
        applied: 0,
        held: 0,
        waker: waker.clone(),
    };
    let commands = CommandSender { ring: commands_tx, waker };
    let link = EngineLink { commands, outputs, ticker, poses, snapshot: snap_rx, stats };
    Ok((core, link))
}

/// A claimed slot's session (tests and diagnostics).
#[derive(Debug)]
pub struct SessionRef<'a>(MutexGuard<'a, SlotState>);

impl std::ops::Deref for SessionRef<'_> {
    type Target = DrillingSession;
    fn deref(&self) -> &DrillingSession {
        &self.0.slot.session
    }
}

impl TickCore {
    /// Number of slots.
    #[must_use]
    pub fn slots(&self) -> usize {
        self.cells.len()
    }

    /// The drilling session of `slot` (tests and diagnostics: waits for a tick on another thread
    /// to end, and holds the slot until dropped).
    #[must_use]
    pub fn session(&self, slot: usize) -> Option<SessionRef<'_>> {
        self.cells.get(slot).map(|c| SessionRef(claim_waiting(c)))
    }

    #[allow(clippy::large_types_passed_by_value)] // moved into the queue / consumed: by value is the point
    fn emit(outputs: &OutputQueue, stats: &TickStats, out: Output) {
        if outputs.push(out).is_err() {
            stats.dropped_outputs.fetch_add(1, Ordering::Relaxed);
        }
    }

    /// Applies `cmd` to its slot, which the caller has claimed (`st`), at `now` (`None`: stepped
    /// offline, off any clock).
    fn apply(&mut self, st: &mut SlotState, cmd: Command, now: Option<Instant>) {
        let s = &mut st.slot;
        match cmd {
            Command::Activate { generation, path, mode, gain, .. } => {
                s.activate(generation, path.unwrap_or_else(|| self.default_path.clone()), mode, gain, now);
                st.schedule = Schedule::new(Instant::now());
            }
            Command::Release { .. } => s.active = false,
            Command::Reset { .. } => s.reset(now),
            Command::SetPath { path, .. } => s.session.set_path(path),
            // Checked by the sender; a bad value would leave the session as it was.
            Command::SetBurr { radius_m, .. } => {
                let _ = s.session.set_burr_radius(radius_m);
            }
            Command::SetGuidance { mode, gain, .. } => s.set_guidance(mode, gain),
            Command::Prediction { slot, generation, window_seq, predicted_n, latency_s, pose_client_time_ns } => {
                if s.active && s.generation == generation {
                    let out = s.prediction(slot, window_seq, predicted_n, latency_s, pose_client_time_ns);
                    Self::emit(&self.outputs, &self.stats, out);
                }
            }
            Command::Snapshot { slot } => {
                let buf = self.snapshot.input_buffer_mut();
                buf.slot = slot;
                buf.generation = s.generation;
                // Same volume by construction, so this cannot fail.
                let _ = buf.bone.copy_from(s.session.bone());
                self.snapshot.publish();
                Self::emit(&self.outputs, &self.stats, Output::Snapshot { slot, generation: s.generation });
            }
        }
    }

    /// Applies waiting commands in order, each under its slot's claim. Returns false if it
    /// stopped at a command whose slot another thread held (it stays first in the ring).
    fn apply_commands(&mut self, wait: bool, now: Option<Instant>) -> bool {
        self.applied = 0;
        self.held = 0;
        let cells = self.cells.clone();
        for _ in 0..COMMANDS_PER_TICK {
            let Ok(slot) = self.commands.peek().map(Command::slot) else { break };
            match cells.get(usize::from(slot)) {
                Some(cell) => {
                    let Some(mut st) = (if wait { Some(claim_waiting(cell)) } else { claim(cell) }) else {
                        return false;
                    };
                    if let Ok(cmd) = self.commands.pop() {
                        // The ticks without a pose that fell due before the command came first, as
                        // they would have run had the thread looked at their time (none before a
                        // session's first tick: a new session's settings come before it).
                        if let (Some(now), true) = (now, st.slot.active && st.schedule.started()) {
                            let (outputs, stats) = (&*self.outputs, &*self.stats);
                            self.held += st.catch_up(slot, now, stats, |out| Self::emit(outputs, stats, out));
                        }
                        self.apply(&mut st, cmd, now);
                    }
                }
                None => {
                    let _ = self.commands.pop(); // no such slot: nothing to apply it to
                }
            }
            self.applied += 1;
        }
        true
    }

    /// What wakes the thread running this core.
    #[must_use]
    pub fn waker(&self) -> &Arc<TickWaker> {
        &self.waker
    }

    /// Commands the last [`tick_due`](Self::tick_due) (or [`tick`](Self::tick)) applied. A model
    /// prediction emits its guidance message as it is applied, not at the slot's next tick.
    #[must_use]
    pub fn commands_applied(&self) -> usize {
        self.applied
    }

    /// Applies waiting commands, then ticks every active slot that is due at `now` (see
    /// `engine/schedule.rs`). A slot another thread holds (a pose ticking it) is passed over and looked
    /// at again within [`CLAIM_RETRY`]. Returns the number of slot ticks and when to look again:
    /// when a waiting pose may tick, or [`HOLD_LOOK_PERIODS`] after a slot's next tick without a
    /// pose (at most [`IDLE_WAKE`] away: commands wake the thread).
    pub fn tick_due(&mut self, now: Instant) -> (u32, Instant) {
        let mut next = now + IDLE_WAKE;
        if !self.apply_commands(false, Some(now)) {
            next = next.min(now + CLAIM_RETRY);
        }
        let mut ticked = self.held;
        let mut active = 0;
        let (outputs, stats) = (&*self.outputs, &*self.stats);
        for (i, cell) in self.cells.iter().enumerate() {
            let Some(mut st) = claim(cell) else {
                active += u64::from(self.was_active[i]);
                next = next.min(now + CLAIM_RETRY);
                continue;
            };
            self.was_active[i] = st.slot.active;
            if !st.slot.active {
                continue;
            }
            active += 1;
            let (did, due) = st.step(i as u16, now, stats, |out| Self::emit(outputs, stats, out));
            ticked += did;
            next = next.min(due);
        }
        self.stats.sessions.store(active, Ordering::Relaxed);
        if ticked > 0 {
            // Skipped when idle: a spinning tick thread calls this every few hundred ns.
            self.stats.ticks.fetch_add(u64::from(ticked), Ordering::Relaxed);
        }
        (ticked, next)
    }

    /// One tick of every active slot, due or not: commands first, then the sessions (tests and
    /// offline stepping; waits for each slot's claim; the tick thread uses
    /// [`tick_due`](Self::tick_due)). Off any clock, so off the record grid: its sessions record
    /// at ticks 100, 200, ….
    pub fn tick(&mut self) {
        self.apply_commands(true, None);
        let mut active = 0;
        let (outputs, stats) = (&*self.outputs, &*self.stats);
        for (i, cell) in self.cells.iter().enumerate() {
            let mut st = claim_waiting(cell);
            if st.slot.active {
                active += 1;
                st.slot.tick(i as u16, None, |out| Self::emit(outputs, stats, out));
            }
        }
        self.stats.sessions.store(active, Ordering::Relaxed);
        self.stats.ticks.fetch_add(1, Ordering::Relaxed);
    }
}
