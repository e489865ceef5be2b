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
//! Each slot ticks once per 1 ms on average, **locked to its client's poses**. Every slot has a
//! tick budget that fills by one period per 1 ms and is spent by one per tick; its deadline is
//! when the budget holds a period. A fresh pose starts the slot's tick as soon as it arrives,
//! once the budget holds a period less the [`EARLY_PERIODS`] it may borrow; a pose that comes
//! earlier waits, and while it waits the budget fills at [`LOCK_RATE`], so the slot's phase
//! drifts onto its client's. Only a pose that had to wait gets that speed-up; other ticks count
//! plain time, so the budget does not fill up with it. A steady 1 kHz client thus gets each force
//! computed from the pose that just arrived, whatever its phase, while a client sending faster
//! still gets 1 kHz (its slot sees more than [`FAST_CLIENT_POSES_PER_TICK`] poses per tick and
//! does not speed up). Without a fresh pose the slot ticks at its deadline, or once its client has
//! sent a pose, [`GRACE_PERIODS`] past it: it banks what it waited, so the late pose, once in,
//! ticks at once, however long the client was silent. A silent client still gets 1 kHz. After a
//! stall, a client's delayed poses arrive in a burst, out of phase: a pose that would wait more
//! than [`MAX_POSE_WAIT_PERIODS`] for the budget (judged when the thread first sees it) waits for
//! the schedule instead, and the client's next pose, back in phase, ticks at once. So a jittery
//! client gets 1 kHz on average.
//!
//! A tick without a pose runs **as of its time, but late**: nobody looks for it until
//! [`HOLD_LOOK_PERIODS`] after it is due. A pose that comes before then (its client was later than
//! the grace) first runs the ticks without a pose that fell due before it came, each holding the
//! last pose and dated at its own time, then its own tick; otherwise the tick thread runs them when
//! it looks. A session thus computes the same ticks from the same poses whenever it is looked at:
//! only when a tick without a pose leaves changes (a silent client's forces come in bursts of
//! about five). When the engine looks later still (a stall of the host) it runs the last
//! [`HOLD_BURST_PERIODS`] of them and skips the older ones, counted as missed: a stall buys a
//! burst of at most that many. A deferred pose's tick past its deadline skips and counts the
//! missed periods the same way, its budget banking at most [`WAKE_SLACK_PERIODS`] past that point.
//! Why: `docs/decisions/0034-ticks-without-a-pose-run-late-as-of-their-time.md`.
//!
//! A pose that cannot tick on its own thread (early, or its slot claimed) wakes the tick thread,
//! and so does every command ([`CommandSender`]): the tick thread sleeps until the earliest time
//! a slot needs it (a waiting pose's tick, or a look), not a period at most. Why:
//! `docs/decisions/0024-the-tick-thread-sleeps-to-its-deadlines.md`.

pub mod handoff;
pub mod realtime;
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
use crate::record::RECORD_PERIOD_TICKS;
use crate::session::{DrillingSession, SessionConfig};
use crate::volume::drilled::DrilledVolume;
use crate::volume::Volume;
use handoff::{Command, Output, PoseSample};
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
/// How early (in periods) a fresh pose may start a slot's tick: the slot borrows it from its
/// next period, so the rate still averages at most 1 kHz.
///
/// Why this value: `docs/decisions/0005-pose-locked-schedule.md`.
pub const EARLY_PERIODS: f64 = 0.3;
/// How long (in periods) a slot whose client has sent a pose waits past its deadline (its budget
/// holding a period) for the next pose before ticking without one. A whole period: with 16
/// clients on 2 cores, 3–5 % of poses came more than 0.55 ms after their predecessor's period
/// (recorded traces; one is replayed in `tests/schedule.rs`). With 0.3 periods the slot ticked
/// without them, and the pose that followed found no budget and waited for a later deadline.
///
/// Why this value: `docs/decisions/0001-grace-period.md`.
pub const GRACE_PERIODS: f64 = 1.0;
/// How fast a slot's budget fills for a fresh pose that came before the budget could tick it
/// (periods per period, over the whole time since the last tick): the 2 % that lets the slot's
/// phase drift onto its client's within tens of periods. Other ticks count plain time: when
/// every tick banked the 2 %, the bank stayed full, each late wake-up of the thread dropped some
/// of it, and the sessions ran slow. A client sending faster than 1 kHz does not get it (see
/// [`FAST_CLIENT_POSES_PER_TICK`]).
///
/// Why this value: `docs/decisions/0002-lock-rate.md`.
pub const LOCK_RATE: f64 = 1.02;
/// Least time (in periods) between a slot's last tick and a waiting pose's arrival for that pose
/// to get [`LOCK_RATE`]. A pose that comes sooner is most likely in a burst after a stall, not
/// evidence of a phase ahead of the slot's: at 16 clients on 2 cores, counting such poses too
/// made the sessions run 0.10–0.13 % fast, and without them 0.03–0.07 %.
///
/// Why this value: `docs/decisions/0002-lock-rate.md`.
pub const LOCK_MIN_GAP_PERIODS: f64 = 0.5;
/// Poses per tick (averaged) above which a client counts as sending faster than 1 kHz: its slot
/// then ticks on the plain 1 kHz budget, since the 2 % catch-up would only make it run fast.
///
/// Why this value: `docs/decisions/0002-lock-rate.md`.
pub const FAST_CLIENT_POSES_PER_TICK: f64 = 1.2;
/// Weight of the newest tick in a slot's average of poses per tick (about the last 50 ticks).
///
/// Why this value: `docs/decisions/0002-lock-rate.md`.
const POSE_RATE_WEIGHT: f64 = 0.02;
/// Longest (in periods) a fresh pose waits for its slot's budget. Past it the slot is out of
/// phase with its client, and it re-locks by waiting for the client's next pose (see
/// [`TickCore::tick_due`]) instead of ticking every pose late while the 2 % catch up.
///
/// Why this value: `docs/decisions/0001-grace-period.md` and `docs/decisions/0006-relock-after-a-stall.md`.
pub const MAX_POSE_WAIT_PERIODS: f64 = 0.5;
/// A slot due within this many periods (1 ns) is due now: float rounding must not cost a wake-up.
const DUE_SLACK_PERIODS: f64 = 1e-6;
/// How late (in periods) a pose's tick may run past the slot's point of ticking without a pose
/// and still lose no time: the budget banks this much past that point, and drops the rest. Without
/// it each late wake-up cost its lateness: a replay of two recorded clients waking 100 µs late ran
/// 0.2 % slow (`tests/schedule.rs`, `wake_up_latency_costs_no_ticks`). Since 0034 it matters only
/// for a deferred pose's tick: ticks without a pose run as of their own time however late the
/// thread looks (up to [`HOLD_BURST_PERIODS`] of them).
///
/// Why this value: `docs/decisions/0002-lock-rate.md`.
pub const WAKE_SLACK_PERIODS: f64 = 0.3;

/// How long (in periods) past a slot's tick without a pose the tick thread waits before it looks.
/// Until then a pose that comes runs that tick first, as of its time, then its own; a client that
/// stays silent gets its ticks in bursts of about this many. Each tick is the same (a tick's one
/// use of the clock, the record grid, takes its scheduled time); only when its force leaves
/// changes. Looking at each such tick's own time, the thread woke at a deadline that a pose had
/// usually moved on already: 500–1,000 wake-ups a second, 9–13 % of the engine's CPU at 4 clients.
///
/// Why this value: `docs/decisions/0034-ticks-without-a-pose-run-late-as-of-their-time.md`.
pub const HOLD_LOOK_PERIODS: f64 = 4.0;
/// Most ticks without a pose run in one go, as of their times, when the engine looks late: older
/// ones (a stall of the host) are skipped and counted as missed, so a stall buys a burst of at
/// most this many ticks, and a thread that wakes up to 3 ms past its look loses none.
///
/// Why this value: `docs/decisions/0034-ticks-without-a-pose-run-late-as-of-their-time.md`.
pub const HOLD_BURST_PERIODS: f64 = 8.0;

/// Periods of budget at which a slot ticks without a fresh pose: its deadline, or once its
/// client has sent a pose, [`GRACE_PERIODS`] past it, waiting for the client's late pose.
fn due_periods(streaming: bool) -> f64 {
    if streaming {
        1.0 + GRACE_PERIODS
    } else {
        1.0
    }
}

/// Periods from now until a slot ticks without a fresh pose (see [`due_periods`]).
fn timer_until(streaming: bool, tokens: f64, elapsed: f64) -> f64 {
    due_periods(streaming) - (tokens + elapsed)
}

/// The record grid's period (ns): one record period of ticks.
const RECORD_GRID_NS: u128 = TICK_PERIOD.as_nanos() * RECORD_PERIOD_TICKS as u128;

/// Ticks from `now` to a session's first record, so that it falls on the engine's 100 ms record
/// grid (which starts at `grid`): 1 to [`RECORD_PERIOD_TICKS`]. A session activated or reset at
/// `now` ticks its first tick about then and one a period after, so every session's records, and
/// with them its model queries, come within a tick or two of the others', and the model service
/// answers them in one batched forward pass instead of one pass each. Why:
/// `docs/decisions/0028-records-on-one-grid.md`.
#[must_use]
pub fn ticks_to_grid(grid: Instant, now: Instant) -> u64 {
    let into = now.saturating_duration_since(grid).as_nanos() % RECORD_GRID_NS;
    // The first tick is about now, tick k k - 1 periods later: the one nearest the next mark.
    let tick_ns = TICK_PERIOD.as_nanos();
    let periods_left = ((RECORD_GRID_NS - into + tick_ns / 2) / tick_ns) as u64 % RECORD_PERIOD_TICKS;
    periods_left + 1
}

/// How far `now` is past the nearest mark of the record grid that starts at `grid` (ms, −50 to 50;
/// negative: before it).
#[must_use]
pub fn off_grid_ms(grid: Instant, now: Instant) -> f64 {
    let into = (now.saturating_duration_since(grid).as_nanos() % RECORD_GRID_NS) as f64;
    let period = RECORD_GRID_NS as f64;
    let past = if into * 2.0 < period { into } else { into - period };
    past * 1e-6
}

/// `seconds` rounded up to whole microseconds (waking a hair early would find nothing due).
fn ceil_us(seconds: f64) -> Duration {
    Duration::from_micros((seconds * 1e6).ceil() as u64)
}

/// A slot's tick budget: one period's worth accrues per 1 ms, a tick spends one.
#[derive(Debug, Clone, Copy)]
struct SlotClock {
    /// When the slot last ticked.
    last: Instant,
    /// Periods banked at `last`, after that tick (may be negative by up to [`EARLY_PERIODS`]).
    tokens: f64,
}

/// A slot's schedule state (see the module docs), reset when a session takes the slot.
#[derive(Debug, Clone, Copy)]
struct Schedule {
    /// Its tick budget (`None`: just activated, due at once).
    clock: Option<SlotClock>,
    /// Whether its client has sent a pose: from then on, the slot waits [`GRACE_PERIODS`] past
    /// each deadline for the late pose before ticking without it, so that a pose late by up to
    /// the grace ticks as it arrives, however long the client was silent.
    streaming: bool,
    /// When the waiting pose was first seen (its arrival, as near as the thread knows).
    seen: Instant,
    /// When the first of the poses waiting since the last tick arrived (the receiving thread's
    /// stamp, or when it was first seen): ticks without a pose run only up to there.
    pending_from: Instant,
    /// Poses seen since the last tick.
    arrivals: u32,
    /// Running average of poses seen per tick (see [`FAST_CLIENT_POSES_PER_TICK`]).
    poses_per_tick: f64,
}

impl Schedule {
    fn new(now: Instant) -> Self {
        Self { clock: None, streaming: false, seen: now, pending_from: now, arrivals: 0, poses_per_tick: 1.0 }
    }
}

/// A slot and its schedule: what a claim covers.
#[derive(Debug)]
struct SlotState {
    slot: Slot,
    schedule: Schedule,
}

impl SlotState {
    /// Runs the ticks without a pose that fell due before `now`, or, with a fresh pose waiting,
    /// before the thread first saw it: each as of its own time, holding the last pose (the waiting
    /// one stays for the tick that follows), as if the thread had woken at each. Ticks due more
    /// than [`HOLD_BURST_PERIODS`] before `now` are skipped and counted as missed. Returns how
    /// many ran.
    fn catch_up(&mut self, idx: u16, now: Instant, stats: &TickStats, mut emit: impl FnMut(Output)) -> u32 {
        let period_s = TICK_PERIOD.as_secs_f64();
        let (s, sched) = (&mut self.slot, &mut self.schedule);
        let clock = sched.clock.get_or_insert(SlotClock { last: now, tokens: 1.0 });
        let waiting = s.pose_pending();
        if s.poll_pose() {
            sched.seen = now;
            sched.arrivals += 1;
            if !waiting {
                // As the receiving thread stamped it, when the thread that sees it first is
                // another, later one.
                sched.pending_from = s.pending_received().map_or(now, |r| r.min(now));
            }
        }
        let fresh = s.pose_pending();
        // With a pose waiting, up to the arrival of the first one not ticked yet: a tick due after
        // it would have taken that pose (or a newer one), had the thread looked on time.
        let horizon = if fresh { sched.pending_from } else { now };
        let due = due_periods(sched.streaming);
        let mut held = 0;
        loop {
            // Periods from the last tick to the next one without a pose (never negative: the bank
            // holds at most `due` + WAKE_SLACK_PERIODS − 1 after a tick).
            let gap = (due - clock.tokens).max(0.0);
            let since = |t: Instant| t.saturating_duration_since(clock.last).as_secs_f64() / period_s;
            let ahead = gap - since(horizon);
            // With a pose waiting, a tick due the moment it came is the pose's own.
            if ahead > DUE_SLACK_PERIODS || (fresh && ahead >= -DUE_SLACK_PERIODS) {
                return held;
            }
            let behind = since(now) - gap;
            // How late past the thread's look (the tick's time plus HOLD_LOOK_PERIODS) it runs: its
            // wake-up latency (a pose that runs it sooner makes it on time). After a stall, the
            // oldest skipped tick's too, so that the stall shows.
            let late_ns = ((behind - HOLD_LOOK_PERIODS).max(0.0) * period_s * 1e9) as u64;
            stats.lateness.record(late_ns);
            stats.max_lateness_ns.fetch_max(late_ns, Ordering::Relaxed);
            if behind > HOLD_BURST_PERIODS - 1.0 {
                // A stall: skip to the oldest tick that leaves at most HOLD_BURST_PERIODS to run
                // by now, counting the rest.
                let skip = (behind - (HOLD_BURST_PERIODS - 1.0)).ceil();
                stats.missed.fetch_add(skip as u64, Ordering::Relaxed);
                clock.last += Duration::from_nanos((skip * period_s * 1e9).round() as u64);
                continue;
            }
            let at = clock.last + Duration::from_nanos((gap * period_s * 1e9).round() as u64);
            s.hold_tick(idx, at, &mut emit);
            *clock = SlotClock { last: at, tokens: due - 1.0 };
            // No pose came before it: the waiting one (if any) counts for the tick that follows.
            sched.poses_per_tick -= POSE_RATE_WEIGHT * sched.poses_per_tick;
            held += 1;
        }
    }

    /// Ticks the slot if it is due at `now` (see the module docs), emitting its outputs: first
    /// the ticks without a pose that fell due before (see [`catch_up`](Self::catch_up)), then
    /// the fresh pose's, if due. Returns the ticks run and when the slot should next be looked at:
    /// when a waiting pose may tick, or [`HOLD_LOOK_PERIODS`] after its next tick without a pose.
    fn step(&mut self, idx: u16, now: Instant, stats: &TickStats, mut emit: impl FnMut(Output)) -> (u32, Instant) {
        let held = self.catch_up(idx, now, stats, &mut emit);
        let (ticked, next) = self.pose_tick(idx, now, stats, emit);
        (held + u32::from(ticked), next)
    }

    /// After [`catch_up`](Self::catch_up) at `now`: ticks the fresh pose if it is due. Returns
    /// whether it ticked and when the slot should next be looked at (see [`step`](Self::step)).
    fn pose_tick(&mut self, idx: u16, now: Instant, stats: &TickStats, emit: impl FnMut(Output)) -> (bool, Instant) {
        let period_s = TICK_PERIOD.as_secs_f64();
        let (s, sched) = (&mut self.slot, &mut self.schedule);
        let clock = sched.clock.get_or_insert(SlotClock { last: now, tokens: 1.0 });
        let elapsed = now.saturating_duration_since(clock.last).as_secs_f64() / period_s;
        let fresh = s.pose_pending();
        let timer = timer_until(sched.streaming, clock.tokens, elapsed);
        let look = |until: f64| now + ceil_us((until + HOLD_LOOK_PERIODS) * period_s);
        if !fresh {
            // Every tick without a pose due by now has run.
            return (false, look(timer));
        }
        // A fresh pose that came before the budget could tick it, and not right behind the
        // last tick (its phase is ahead of the slot's; it is not a burst), counts its whole
        // wait 2 % fast, so the slot's phase drifts onto its client's. Cut where the pose
        // could tick, the 2 % was lost whenever the thread woke late, and the slot never
        // locked. Other ticks count plain time: a surplus banked on every tick filled the
        // bank, and each late wake-up then dropped some (the slot ran slow). Not for a client
        // sending faster than 1 kHz, which would take all of the 2 %.
        let fast_client = sched.poses_per_tick > FAST_CLIENT_POSES_PER_TICK;
        let seen_after = sched.seen.saturating_duration_since(clock.last).as_secs_f64() / period_s;
        let ahead = clock.tokens + seen_after < 1.0 - EARLY_PERIODS && seen_after >= LOCK_MIN_GAP_PERIODS;
        let lock = if ahead && !fast_client { LOCK_RATE } else { 1.0 };
        let have = clock.tokens + elapsed * lock;
        let short = (1.0 - EARLY_PERIODS - have) / lock;
        // Waiting longer means the slot is out of phase with its client (its poses came in a
        // burst after a stall): this pose waits for the schedule, and the client's next pose,
        // in phase, ticks the moment it arrives. Judged as of the pose's arrival (`short` then
        // was `short + waited`), so how often the thread looks changes nothing: a spinning
        // thread would otherwise tick every deferred pose once `short` shrank.
        let waited = now.saturating_duration_since(sched.seen).as_secs_f64() / period_s;
        let until = if short + waited <= MAX_POSE_WAIT_PERIODS { short } else { timer };
        if until > DUE_SLACK_PERIODS {
            // The pose's tick is looked at on time.
            return (false, now + ceil_us(until * period_s));
        }
        // How far past its schedule the slot ticks: a deferred pose the thread looked at late (a
        // pose ticking as it arrives is on time).
        let late_periods = (-timer).max(0.0);
        let late_ns = (late_periods * period_s * 1e9) as u64;
        stats.lateness.record(late_ns);
        stats.max_lateness_ns.fetch_max(late_ns, Ordering::Relaxed);
        let behind = late_periods.floor();
        if behind >= 1.0 {
            stats.missed.fetch_add(behind as u64, Ordering::Relaxed);
        }
        if let Some(t) = s.tick(idx, Some(now), emit) {
            stats.pose_to_tick.record(now.saturating_duration_since(t).as_nanos() as u64);
        }
        let bank = due_periods(sched.streaming) + WAKE_SLACK_PERIODS;
        *clock = SlotClock { last: now, tokens: have.min(bank) - 1.0 };
        sched.poses_per_tick += POSE_RATE_WEIGHT * (f64::from(sched.arrivals) - sched.poses_per_tick);
        sched.arrivals = 0;
        sched.streaming = true;
        (true, look(timer_until(sched.streaming, clock.tokens, 0.0)))
    }
}

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
        /// than the grace) it is not: their forces and this one leave from the comm side, in
        /// order.
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
    /// The slot's newest force has not left yet (it waits for the comm side): the tick thread
    /// ticks this pose, so that forces leave in order.
    Behind,
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
    /// force still waits for the comm side, and a force made here would overtake it: the pose is
    /// left to the tick thread ([`PoseTick::Behind`]), whose force follows the waiting one.
    ///
    /// The tick's outputs are queued before the slot is let go, so a slot's outputs queue in the
    /// order its ticks ran, wherever they ran (the recorders' batches read a tick that goes back as
    /// a reset). With `publish_here` the force is queued marked `published`: the caller puts it
    /// (the copy returned), and the comm side only records it. Never waits, allocates or does I/O.
    #[must_use]
    pub fn tick(&self, slot: u16, generation: u32, now: Instant, out_up_to: u64, publish_here: bool) -> PoseTick {
        let left = |why: PoseTick| {
            let i = match why {
                PoseTick::Claimed => 1,
                PoseTick::Behind => 2,
                _ => 0,
            };
            self.stats.poses_left[i].fetch_add(1, Ordering::Relaxed);
            why
        };
        let Some(cell) = self.cells.get(usize::from(slot)) else { return left(PoseTick::NotDue) };
        let Some(mut st) = claim(cell) else { return left(PoseTick::Claimed) };
        if !st.slot.active || st.slot.generation != generation {
            return left(PoseTick::NotDue);
        }
        if st.slot.order() > out_up_to {
            return left(PoseTick::Behind);
        }
        let (mut force, mut state) = (None, false);
        let (outputs, stats) = (&*self.outputs, &*self.stats);
        // Ticks without a pose that fell due before this pose came run first, their forces left
        // to the comm side; then this pose's force must follow them from there too.
        let held = st.catch_up(slot, now, stats, |out| {
            state |= matches!(out, Output::State { .. });
            TickCore::emit(outputs, stats, out);
        });
        let publish_here = publish_here && held == 0;
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

impl EngineConfig {
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
                        if let (Some(now), true) = (now, st.slot.active && st.schedule.clock.is_some()) {
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

    /// Applies waiting commands, then ticks every active slot that is due at `now` (see the
    /// module docs). A slot another thread holds (a pose ticking it) is passed over and looked
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
