//! The per-second history of the tick statistics, from which the health report takes its
//! windows (`health?window=S`).

use std::collections::VecDeque;
use std::sync::atomic::Ordering;
use std::time::Instant;

use super::Shared;
use crate::engine::stats::HistogramSnapshot;

/// Seconds of per-second tick-statistics history kept for the health report.
const HISTORY_S: usize = 600;

/// One second's cumulative tick statistics.
#[derive(Debug, Clone)]
pub(crate) struct StatsSample {
    pub(crate) at: Instant,
    pub(crate) ticks: u64,
    pub(crate) pose_thread_ticks: u64,
    pub(crate) poses_left: [u64; 2],
    pub(crate) pose_ticks_behind: u64,
    pub(crate) wakes: u64,
    pub(crate) missed: u64,
    pub(crate) lateness: HistogramSnapshot,
    pub(crate) busy: HistogramSnapshot,
    pub(crate) pose_to_tick: HistogramSnapshot,
    pub(crate) pose_to_put: HistogramSnapshot,
}

impl StatsSample {
    /// The counts since `base` (everything since start without one).
    pub(crate) fn since(&self, base: Option<&Self>) -> Self {
        let Some(b) = base else { return self.clone() };
        Self {
            at: self.at,
            // Saturating: a base pushed just after `self` was sampled may be a little ahead.
            ticks: self.ticks.saturating_sub(b.ticks),
            pose_thread_ticks: self.pose_thread_ticks.saturating_sub(b.pose_thread_ticks),
            poses_left: std::array::from_fn(|i| self.poses_left[i].saturating_sub(b.poses_left[i])),
            pose_ticks_behind: self.pose_ticks_behind.saturating_sub(b.pose_ticks_behind),
            wakes: self.wakes.saturating_sub(b.wakes),
            missed: self.missed.saturating_sub(b.missed),
            lateness: self.lateness.since(&b.lateness),
            busy: self.busy.since(&b.busy),
            pose_to_tick: self.pose_to_tick.since(&b.pose_to_tick),
            pose_to_put: self.pose_to_put.since(&b.pose_to_put),
        }
    }
}

/// Per-second samples, oldest first.
#[derive(Debug, Default)]
pub(crate) struct History {
    pub(crate) samples: VecDeque<StatsSample>,
}

impl History {
    /// Adds a second's sample, dropping the oldest past [`HISTORY_S`].
    pub(crate) fn push(&mut self, sample: StatsSample) {
        if self.samples.len() == HISTORY_S {
            self.samples.pop_front();
        }
        self.samples.push_back(sample);
    }
}

/// The tick statistics now.
pub(crate) fn sample(shared: &Shared) -> StatsSample {
    let s = &shared.stats;
    StatsSample {
        at: Instant::now(),
        ticks: s.ticks.load(Ordering::Relaxed),
        pose_thread_ticks: s.pose_thread_ticks.load(Ordering::Relaxed),
        poses_left: std::array::from_fn(|i| s.poses_left[i].load(Ordering::Relaxed)),
        pose_ticks_behind: s.pose_ticks_behind.load(Ordering::Relaxed),
        wakes: s.wakes.load(Ordering::Relaxed),
        missed: s.missed.load(Ordering::Relaxed),
        lateness: s.lateness.snapshot(),
        busy: s.busy.snapshot(),
        pose_to_tick: s.pose_to_tick.snapshot(),
        pose_to_put: s.pose_to_put.snapshot(),
    }
}
