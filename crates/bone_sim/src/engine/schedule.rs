//! When a slot ticks: its tick budget, locked to its client's poses, and the ticks it runs
//! without one; and when it records, on the engine's 100 ms grid.
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

use std::sync::atomic::Ordering;
use std::time::{Duration, Instant};

use super::handoff::Output;
use super::slot::Slot;
use super::stats::TickStats;
use super::TICK_PERIOD;
use crate::record::RECORD_PERIOD_TICKS;

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
/// [`SlotState::pose_tick`]) instead of ticking every pose late while the 2 % catch up.
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
pub(super) struct Schedule {
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
    pub(super) fn new(now: Instant) -> Self {
        Self { clock: None, streaming: false, seen: now, pending_from: now, arrivals: 0, poses_per_tick: 1.0 }
    }

    /// Whether the slot has ticked since its session took it.
    pub(super) fn started(&self) -> bool {
        self.clock.is_some()
    }
}

/// A slot and its schedule: what a claim covers.
#[derive(Debug)]
pub(super) struct SlotState {
    pub(super) slot: Slot,
    pub(super) schedule: Schedule,
}

impl SlotState {
    /// Runs the ticks without a pose that fell due before `now`, or, with a fresh pose waiting,
    /// before the thread first saw it: each as of its own time, holding the last pose (the waiting
    /// one stays for the tick that follows), as if the thread had woken at each. Ticks due more
    /// than [`HOLD_BURST_PERIODS`] before `now` are skipped and counted as missed. Returns how
    /// many ran.
    pub(super) fn catch_up(&mut self, idx: u16, now: Instant, stats: &TickStats, mut emit: impl FnMut(Output)) -> u32 {
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
    pub(super) fn step(
        &mut self,
        idx: u16,
        now: Instant,
        stats: &TickStats,
        mut emit: impl FnMut(Output),
    ) -> (u32, Instant) {
        let held = self.catch_up(idx, now, stats, &mut emit);
        let (ticked, next) = self.pose_tick(idx, now, stats, emit);
        (held + u32::from(ticked), next)
    }

    /// After [`catch_up`](Self::catch_up) at `now`: ticks the fresh pose if it is due. Returns
    /// whether it ticked and when the slot should next be looked at (see [`step`](Self::step)).
    pub(super) fn pose_tick(
        &mut self,
        idx: u16,
        now: Instant,
        stats: &TickStats,
        emit: impl FnMut(Output),
    ) -> (bool, Instant) {
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

/// How far `now` is past the nearest mark of the record grid that starts at `grid`, in tick
/// periods (−50 to 50 at 1 kHz; negative: before it).
#[must_use]
pub fn off_grid_ticks(grid: Instant, now: Instant) -> f64 {
    let into = (now.saturating_duration_since(grid).as_nanos() % RECORD_GRID_NS) as f64;
    let period = RECORD_GRID_NS as f64;
    let past = if into * 2.0 < period { into } else { into - period };
    past / TICK_PERIOD.as_nanos() as f64
}
