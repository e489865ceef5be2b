//! The real-time engine: every session slot stepped once per 1 ms on a dedicated thread.
//!
//! The tick thread owns the sessions. It talks to the rest of the server only through lock-free
//! structures made at start-up ([`handoff`]): an SPSC ring of commands in, an SPSC ring of outputs
//! out, a triple buffer per slot carrying the newest pose, and one triple buffer for bone
//! snapshots. Sessions, their reserved bricks and the rings are all allocated before the first
//! tick, so a tick never allocates, locks or does I/O. Deadlines are absolute (start + k·1 ms): a
//! late wake-up does not shift later ticks, and a wake-up a whole period late skips the missed
//! ticks and counts them.

pub mod guidance;
pub mod handoff;
mod realtime;
mod slot;
pub mod stats;

use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::thread::{self, JoinHandle, Thread};
use std::time::{Duration, Instant};

use crate::error::{SimError, SimResult};
use crate::path::PlannedPath;
use crate::session::{DrillingSession, SessionConfig};
use crate::volume::drilled::DrilledVolume;
use crate::volume::Volume;
use guidance::{check_gain, GuidanceParams};
use handoff::{Command, Output, PoseSample};
use slot::Slot;
use stats::TickStats;

/// Most session slots an engine may have.
pub const MAX_SESSIONS: usize = 1024;
/// Outputs the ring holds per slot (ticks of slack before the comm side must drain it).
const OUTPUT_SLACK_PER_SLOT: usize = 128;
/// Commands applied per tick at most (the rest wait for the next tick).
const COMMANDS_PER_TICK: usize = 256;
/// The tick period (1 kHz).
pub const TICK_PERIOD: Duration = Duration::from_millis(1);

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
    /// Guidance gain of a new session.
    pub default_gain: f64,
    /// Drilled bricks each session may hold before a tick would allocate.
    pub reserve_bricks: usize,
}

impl EngineConfig {
    /// Default settings for a path.
    #[must_use]
    pub fn new(default_path: PlannedPath) -> Self {
        Self {
            max_sessions: 16,
            session: SessionConfig::default(),
            default_path,
            guidance: GuidanceParams::default(),
            default_gain: 1.0,
            reserve_bricks: 1024,
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

/// Everything the tick thread owns.
#[derive(Debug)]
pub struct TickCore {
    slots: Vec<Slot>,
    commands: rtrb::Consumer<Command>,
    outputs: rtrb::Producer<Output>,
    snapshot: triple_buffer::Input<Snapshot>,
    default_path: PlannedPath,
    stats: Arc<TickStats>,
}

/// The comm side's ends of the handoff structures.
#[derive(Debug)]
pub struct EngineLink {
    /// Commands into the tick thread (single producer: keep it behind one owner).
    pub commands: rtrb::Producer<Command>,
    /// Outputs of the tick thread (single consumer).
    pub outputs: rtrb::Consumer<Output>,
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
    let (outputs_tx, outputs_rx) = rtrb::RingBuffer::new(OUTPUT_SLACK_PER_SLOT * n + 1024);
    let mut slots = Vec::with_capacity(n);
    let mut poses = Vec::with_capacity(n);
    for _ in 0..n {
        let (tx, rx) = triple_buffer::triple_buffer(&PoseSample::default());
        let mut session = DrillingSession::new(volume.clone(), config.default_path.clone(), config.session.clone())?;
        session.reserve_bricks(config.reserve_bricks);
        slots.push(Slot::new(session, config.guidance.clone(), rx)?);
        poses.push(tx);
    }
    let blank =
        Snapshot { slot: 0, generation: 0, bone: DrilledVolume::with_reserve(volume.clone(), config.reserve_bricks) };
    let (snap_tx, snap_rx) = triple_buffer::triple_buffer(&blank);
    let stats = Arc::new(TickStats::default());
    let core = TickCore {
        slots,
        commands: commands_rx,
        outputs: outputs_tx,
        snapshot: snap_tx,
        default_path: config.default_path.clone(),
        stats: stats.clone(),
    };
    let link = EngineLink { commands: commands_tx, outputs: outputs_rx, poses, snapshot: snap_rx, stats };
    Ok((core, link))
}

impl TickCore {
    /// Number of slots.
    #[must_use]
    pub fn slots(&self) -> usize {
        self.slots.len()
    }

    /// The drilling session of `slot` (tests and diagnostics).
    #[must_use]
    pub fn session(&self, slot: usize) -> Option<&DrillingSession> {
        self.slots.get(slot).map(|s| &s.session)
    }

    #[allow(clippy::large_types_passed_by_value)] // moved into the ring / consumed: by value is the point
    fn emit(outputs: &mut rtrb::Producer<Output>, stats: &TickStats, out: Output) {
        if outputs.push(out).is_err() {
            stats.dropped_outputs.fetch_add(1, Ordering::Relaxed);
        }
    }

    fn apply(&mut self, cmd: Command) {
        let slot_of = |s: u16| s as usize;
        match cmd {
            Command::Activate { slot, generation, path, gain } => {
                let default = &self.default_path;
                if let Some(s) = self.slots.get_mut(slot_of(slot)) {
                    s.activate(generation, path.unwrap_or_else(|| default.clone()), gain);
                }
            }
            Command::Release { slot } => {
                if let Some(s) = self.slots.get_mut(slot_of(slot)) {
                    s.active = false;
                }
            }
            Command::Reset { slot } => {
                if let Some(s) = self.slots.get_mut(slot_of(slot)) {
                    s.reset();
                }
            }
            Command::SetPath { slot, path } => {
                if let Some(s) = self.slots.get_mut(slot_of(slot)) {
                    s.session.set_path(path);
                }
            }
            Command::SetGain { slot, gain } => {
                if let Some(s) = self.slots.get_mut(slot_of(slot)) {
                    s.set_gain(gain);
                }
            }
            Command::Prediction { slot, generation, window_seq, predicted_n, latency_s, pose_client_time_ns } => {
                if let Some(s) = self.slots.get_mut(slot_of(slot)) {
                    if s.active && s.generation == generation {
                        let out = s.prediction(slot, window_seq, predicted_n, latency_s, pose_client_time_ns);
                        Self::emit(&mut self.outputs, &self.stats, out);
                    }
                }
            }
            Command::Snapshot { slot } => {
                if let Some(s) = self.slots.get(slot_of(slot)) {
                    let buf = self.snapshot.input_buffer_mut();
                    buf.slot = slot;
                    buf.generation = s.generation;
                    // Same volume by construction, so this cannot fail.
                    let _ = buf.bone.copy_from(s.session.bone());
                    self.snapshot.publish();
                    Self::emit(&mut self.outputs, &self.stats, Output::Snapshot { slot, generation: s.generation });
                }
            }
        }
    }

    /// One tick of every active slot: commands first, then the sessions.
    pub fn tick(&mut self) {
        for _ in 0..COMMANDS_PER_TICK {
            match self.commands.pop() {
                Ok(cmd) => self.apply(cmd),
                Err(_) => break,
            }
        }
        let mut active = 0;
        let (outputs, stats) = (&mut self.outputs, &self.stats);
        for (i, s) in self.slots.iter_mut().enumerate() {
            if s.active {
                active += 1;
                s.tick(i as u16, |out| Self::emit(outputs, stats, out));
            }
        }
        self.stats.sessions.store(active, Ordering::Relaxed);
        self.stats.ticks.fetch_add(1, Ordering::Relaxed);
    }
}

/// The running tick thread.
#[derive(Debug)]
pub struct TickThread {
    stop: Arc<AtomicBool>,
    handle: Option<JoinHandle<()>>,
}

impl TickThread {
    /// Starts ticking `core` at 1 kHz on absolute deadlines; `notify` is unparked after every
    /// tick (the comm thread, so outputs leave without polling delay).
    ///
    /// # Errors
    /// The thread could not be spawned.
    pub fn spawn(mut core: TickCore, notify: Option<Thread>) -> SimResult<Self> {
        let stop = Arc::new(AtomicBool::new(false));
        let flag = stop.clone();
        let handle = thread::Builder::new()
            .name("dhg-tick".into())
            .spawn(move || {
                let period_ns = TICK_PERIOD.as_nanos() as u64;
                core.stats.realtime.store(u64::from(realtime::promote()), Ordering::Relaxed);
                let start = Instant::now();
                let mut k: u64 = 0;
                while !flag.load(Ordering::Relaxed) {
                    let deadline = start + Duration::from_nanos(k * period_ns);
                    let now = Instant::now();
                    if now < deadline {
                        thread::sleep(deadline - now);
                    }
                    let woke = Instant::now();
                    let late_ns = woke.saturating_duration_since(deadline).as_nanos() as u64;
                    let stats = &core.stats;
                    stats.lateness.record(late_ns);
                    stats.max_lateness_ns.fetch_max(late_ns, Ordering::Relaxed);
                    let behind = late_ns / period_ns;
                    if behind > 0 {
                        stats.missed.fetch_add(behind, Ordering::Relaxed);
                        k += behind;
                    }
                    core.tick();
                    core.stats.busy.record(woke.elapsed().as_nanos() as u64);
                    if let Some(t) = &notify {
                        t.unpark();
                    }
                    k += 1;
                }
            })
            .map_err(|e| SimError::Engine(format!("cannot start the tick thread: {e}")))?;
        Ok(Self { stop, handle: Some(handle) })
    }

    /// Stops the thread and waits for it (at most one tick).
    pub fn stop(&mut self) {
        self.stop.store(true, Ordering::Relaxed);
        if let Some(h) = self.handle.take() {
            let _ = h.join();
        }
    }
}

impl Drop for TickThread {
    fn drop(&mut self) {
        self.stop();
    }
}
