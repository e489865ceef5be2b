//! Tick statistics, written by the tick thread with relaxed atomics and read by anyone.

use std::sync::atomic::{AtomicU64, Ordering::Relaxed};

/// Buckets of a [`Histogram`]: [`LINEAR_BUCKETS`] of its width, then [`SUB_BUCKETS`] per
/// doubling for 8 doublings (to 32,768 widths: 0.33 s at 10 µs). The last one also collects
/// everything above the range.
///
/// Why this value: `docs/decisions/0012-histogram-buckets.md`.
pub const BUCKETS: usize = 256;
/// Buckets of one width each at the start of a [`Histogram`] (exact to a width: 1.28 ms at 10 µs).
pub const LINEAR_BUCKETS: u64 = 128;
/// Buckets per doubling past the linear ones: within 1/16 (6.25 %) of the value, so that a tail of
/// several ms is still resolved (fixed 10 µs buckets stopped at 2.56 ms, where tails often lie).
pub const SUB_BUCKETS: u64 = 16;

/// The bucket of a duration of `units` bucket widths.
fn bucket_of(units: u64) -> usize {
    if units < LINEAR_BUCKETS {
        return units as usize;
    }
    let k = u64::from((units / LINEAR_BUCKETS).ilog2()); // units in [128·2^k, 128·2^(k+1))
    let b = LINEAR_BUCKETS + SUB_BUCKETS * k + (units - (LINEAR_BUCKETS << k)) / ((LINEAR_BUCKETS / SUB_BUCKETS) << k);
    (b as usize).min(BUCKETS - 1)
}

/// The upper edge of bucket `b`, in bucket widths.
fn upper_edge_units(b: usize) -> u64 {
    let b = b as u64;
    if b < LINEAR_BUCKETS {
        return b + 1;
    }
    let (k, j) = ((b - LINEAR_BUCKETS) / SUB_BUCKETS, (b - LINEAR_BUCKETS) % SUB_BUCKETS);
    (LINEAR_BUCKETS << k) + (j + 1) * ((LINEAR_BUCKETS / SUB_BUCKETS) << k)
}

/// A histogram of durations, linear then log-linear (see [`BUCKETS`]; lock-free, allocation-free
/// to record).
#[derive(Debug)]
pub struct Histogram {
    width_ns: u64,
    counts: [AtomicU64; BUCKETS],
}

impl Histogram {
    /// A histogram whose first buckets are `width_ns` wide (see [`BUCKETS`]).
    #[must_use]
    pub fn new(width_ns: u64) -> Self {
        Self { width_ns: width_ns.max(1), counts: std::array::from_fn(|_| AtomicU64::new(0)) }
    }

    /// Counts one duration (ns).
    pub fn record(&self, ns: u64) {
        self.counts[bucket_of(ns / self.width_ns)].fetch_add(1, Relaxed);
    }

    /// The counts now.
    #[must_use]
    pub fn snapshot(&self) -> HistogramSnapshot {
        HistogramSnapshot { width_ns: self.width_ns, counts: std::array::from_fn(|i| self.counts[i].load(Relaxed)) }
    }
}

/// Counts of a [`Histogram`] at one moment; subtract two for an interval.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct HistogramSnapshot {
    width_ns: u64,
    counts: [u64; BUCKETS],
}

impl HistogramSnapshot {
    /// Counts since `earlier`.
    #[must_use]
    pub fn since(&self, earlier: &Self) -> Self {
        Self {
            width_ns: self.width_ns,
            counts: std::array::from_fn(|i| self.counts[i].saturating_sub(earlier.counts[i])),
        }
    }

    /// Number of samples.
    #[must_use]
    pub fn total(&self) -> u64 {
        self.counts.iter().sum()
    }

    /// The `q` quantile (0..=1) as the upper edge of its bucket (s); 0 without samples. Values
    /// above the range report the range's end.
    #[must_use]
    pub fn quantile_s(&self, q: f64) -> f64 {
        let total = self.total();
        if total == 0 {
            return 0.0;
        }
        let rank = ((q.clamp(0.0, 1.0) * total as f64).ceil() as u64).max(1);
        let mut seen = 0;
        for (i, c) in self.counts.iter().enumerate() {
            seen += c;
            if seen >= rank {
                return (upper_edge_units(i) * self.width_ns) as f64 * 1e-9;
            }
        }
        (upper_edge_units(BUCKETS - 1) * self.width_ns) as f64 * 1e-9
    }
}

/// What the tick thread reports.
#[derive(Debug)]
pub struct TickStats {
    /// Ticks run.
    pub ticks: AtomicU64,
    /// Of them, those run on the thread that received their pose (`engine::PoseTicker`).
    pub pose_thread_ticks: AtomicU64,
    /// Poses their own thread left to the tick thread, by why: [not due (early, or the session's
    /// commands not applied yet), claimed (the tick thread held the slot)] (`engine::PoseTick`).
    pub poses_left: [AtomicU64; 2],
    /// Of `pose_thread_ticks`, those that ran while the slot's previous force still waited for
    /// the comm side: their force was queued behind it, to leave from there.
    pub pose_ticks_behind: AtomicU64,
    /// Times the sleeping tick thread woke (a slot's deadline, a pose or command that woke it, a
    /// retry; not counted when it spins).
    pub wakes: AtomicU64,
    /// Ticks skipped because the thread woke a whole period or more late.
    pub missed: AtomicU64,
    /// Wake-up lateness after each deadline (10 µs buckets, see [`BUCKETS`]).
    pub lateness: Histogram,
    /// Work time of each tick (2 µs buckets, see [`BUCKETS`]).
    pub busy: Histogram,
    /// Largest lateness seen (ns).
    pub max_lateness_ns: AtomicU64,
    /// Active sessions.
    pub sessions: AtomicU64,
    /// Outputs dropped because the outgoing ring was full (the comm side fell behind).
    pub dropped_outputs: AtomicU64,
    /// Whether the tick thread got real-time scheduling (`SCHED_FIFO`); 0 = no, 1 = yes.
    pub realtime: AtomicU64,
    /// 1 once a panic (a bug) ended the tick thread: commands are no longer applied, and sessions
    /// tick only on their poses' threads.
    pub tick_thread_failed: AtomicU64,
    /// Whether the tick thread, without `SCHED_FIFO`, got the short EEVDF slice
    /// (`realtime::LATENCY_SLICE_NS`); 0 = no, 1 = yes.
    pub short_slice: AtomicU64,
    /// From a pose's arrival in the subscriber to the tick that used it (10 µs buckets, see
    /// [`BUCKETS`]): the handoff, the tick thread's wake-up, and any wait for the slot's budget.
    pub pose_to_tick: Histogram,
    /// The server's part of pose → force: from a pose's arrival in the subscriber to the put of
    /// the force computed from it (10 µs buckets, see [`BUCKETS`]; recorded by whichever thread
    /// put it).
    pub pose_to_put: Histogram,
}

impl Default for TickStats {
    fn default() -> Self {
        Self {
            ticks: AtomicU64::new(0),
            pose_thread_ticks: AtomicU64::new(0),
            poses_left: [AtomicU64::new(0), AtomicU64::new(0)],
            pose_ticks_behind: AtomicU64::new(0),
            wakes: AtomicU64::new(0),
            missed: AtomicU64::new(0),
            lateness: Histogram::new(10_000),
            busy: Histogram::new(2_000),
            max_lateness_ns: AtomicU64::new(0),
            sessions: AtomicU64::new(0),
            dropped_outputs: AtomicU64::new(0),
            realtime: AtomicU64::new(0),
            tick_thread_failed: AtomicU64::new(0),
            short_slice: AtomicU64::new(0),
            pose_to_tick: Histogram::new(10_000),
            pose_to_put: Histogram::new(10_000),
        }
    }
}

#[cfg(test)]
#[allow(clippy::float_cmp)]
mod tests {
    use super::*;

    #[test]
    fn quantiles_come_from_bucket_edges() {
        let h = Histogram::new(10_000);
        for _ in 0..99 {
            h.record(5_000);
        }
        h.record(1_000_000_000);
        let s = h.snapshot();
        assert_eq!(s.total(), 100);
        assert_eq!(s.quantile_s(0.5), 10e-6);
        assert_eq!(s.quantile_s(0.99), 10e-6);
        assert_eq!(s.quantile_s(1.0), 0.327_68, "overflow reports the range end");
        let later = h.snapshot();
        assert_eq!(later.since(&s).total(), 0);
    }

    #[test]
    fn buckets_are_exact_to_a_width_then_within_a_sixteenth_up_to_the_end() {
        let mut last = 0;
        for units in 0..(LINEAR_BUCKETS << 8) {
            let b = bucket_of(units);
            assert!(b >= last && b < BUCKETS, "{units} widths: bucket {b} after {last}");
            last = b;
            let edge = upper_edge_units(b);
            assert!(edge > units, "{units} widths: edge {edge}");
            assert!(edge - units <= (units / SUB_BUCKETS).max(1), "{units} widths: edge {edge} too far");
        }
        assert_eq!(last, BUCKETS - 1, "the range uses every bucket");
        assert_eq!(bucket_of(u64::MAX), BUCKETS - 1);
        // A 5 ms tail at 10 µs buckets reads 5.12 ms (it read 2.56 ms, the old range end).
        let h = Histogram::new(10_000);
        h.record(5_000_000);
        assert!((h.snapshot().quantile_s(0.5) - 5.12e-3).abs() < 1e-12);
    }
}
