//! The model-worker pool: which worker answers the next model query.
//!
//! Zenoh does not balance load between queryables: a query reaches every matching one (or,
//! with `BestMatching`, one of Zenoh's choosing). So each worker announces itself with a
//! liveliness token `<prefix>/model/workers/<id>` and serves `<prefix>/model/workers/<id>/predict`;
//! the engine follows the tokens and sends each query (a burst of sessions' windows) to one
//! worker, the one with the fewest queries in flight (ties in turn). A worker whose query ends
//! without most of its windows answered (timed out, an error reply, a bad payload) is left out
//! for a while — 0.25 s, doubling with each further failure up to 8 s — and tried again after;
//! one good answer clears it. A frozen worker therefore costs a few queries, not a share of them,
//! and a worker that is killed leaves the pool when its token goes (at once when its connection
//! closes). With no worker in the pool the engine queries the
//! shared `<prefix>/model/predict` key instead (every queryable there, each window's first valid
//! prediction applied), so a worker written from `docs/protocol.md` alone still works.

use std::time::{Duration, Instant};

use serde::Serialize;

/// Leave-out time after a worker's first failure; doubled per further failure.
const FIRST_BACKOFF: Duration = Duration::from_millis(250);
/// Longest leave-out time.
const MAX_BACKOFF: Duration = Duration::from_secs(8);
/// Most workers the pool follows (a flood of tokens cannot grow it without bound).
pub(crate) const MAX_WORKERS: usize = 64;

/// How a query sent to a worker ended.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum Outcome {
    /// Valid predictions for most of the query's windows arrived and were applied.
    Answered,
    /// The query ended without that (timeout, an error reply, a bad payload, too late).
    Failed,
}

/// One worker, as the engine sees it (reported in the health's `model.workers`).
#[derive(Debug, Clone, Serialize, schemars::JsonSchema)]
pub struct Worker {
    /// The worker's id (its liveliness token's last chunk).
    pub id: String,
    /// Queries sent and not yet ended.
    pub in_flight: u32,
    /// Queries it answered.
    pub answered: u64,
    /// Queries it failed (an error, a bad reply or no reply in time).
    pub failed: u64,
    /// Failures since its last good answer.
    #[serde(skip)]
    strikes: u32,
    #[serde(skip)]
    left_out_until: Option<Instant>,
    /// Whether it is being left out now (set when reported).
    pub left_out: bool,
}

/// The workers whose tokens are alive.
#[derive(Debug, Default)]
pub(crate) struct Pool {
    workers: Vec<Worker>,
    /// Where the search for a tie-breaking turn starts.
    turn: usize,
    /// Tokens refused because the pool was full, or with a bad id.
    pub(crate) refused: u64,
}

impl Pool {
    /// A worker's token appeared. Returns false when refused (bad id, pool full).
    pub(crate) fn join(&mut self, id: &str) -> bool {
        if self.workers.iter().any(|w| w.id == id) {
            return true;
        }
        if super::registry::check_id(id).is_err() || self.workers.len() >= MAX_WORKERS {
            self.refused += 1;
            return false;
        }
        self.workers.push(Worker {
            id: id.to_owned(),
            in_flight: 0,
            answered: 0,
            failed: 0,
            strikes: 0,
            left_out_until: None,
            left_out: false,
        });
        true
    }

    /// A worker's token went away.
    pub(crate) fn leave(&mut self, id: &str) {
        self.workers.retain(|w| w.id != id);
    }

    /// The worker for the next query, counted as in flight: among the workers not left out, the
    /// one with the fewest queries in flight (ties in turn); if every worker is left out, the one
    /// whose leave-out ends first (a query to it is the only chance of guidance). None when the
    /// pool is empty.
    pub(crate) fn pick(&mut self, now: Instant) -> Option<String> {
        let n = self.workers.len();
        if n == 0 {
            return None;
        }
        let usable = |w: &Worker| w.left_out_until.is_none_or(|t| now >= t);
        let order = (0..n).map(|k| (self.turn + k) % n);
        let best = order
            .clone()
            .filter(|&i| usable(&self.workers[i]))
            .min_by_key(|&i| self.workers[i].in_flight)
            .or_else(|| order.min_by_key(|&i| self.workers[i].left_out_until))?;
        self.turn = (best + 1) % n;
        let w = &mut self.workers[best];
        w.in_flight += 1;
        Some(w.id.clone())
    }

    /// A query sent to `id` ended (it may have left the pool meanwhile).
    pub(crate) fn ended(&mut self, id: &str, outcome: Outcome, now: Instant) {
        let Some(w) = self.workers.iter_mut().find(|w| w.id == id) else { return };
        w.in_flight = w.in_flight.saturating_sub(1);
        match outcome {
            Outcome::Answered => {
                w.answered += 1;
                w.strikes = 0;
                w.left_out_until = None;
            }
            Outcome::Failed => {
                w.failed += 1;
                w.strikes = w.strikes.saturating_add(1);
                let backoff = FIRST_BACKOFF.saturating_mul(1 << (w.strikes - 1).min(5)).min(MAX_BACKOFF);
                w.left_out_until = Some(now + backoff);
            }
        }
    }

    /// The workers, with `left_out` as of `now`.
    pub(crate) fn report(&self, now: Instant) -> Vec<Worker> {
        self.workers
            .iter()
            .map(|w| Worker { left_out: w.left_out_until.is_some_and(|t| now < t), ..w.clone() })
            .collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn pool(ids: &[&str]) -> Pool {
        let mut p = Pool::default();
        for id in ids {
            assert!(p.join(id));
        }
        p
    }

    #[test]
    fn idle_workers_take_queries_in_turn() {
        let mut p = pool(&["a", "b", "c"]);
        let t = Instant::now();
        let mut got = Vec::new();
        for _ in 0..6 {
            let id = p.pick(t).unwrap();
            p.ended(&id, Outcome::Answered, t);
            got.push(id);
        }
        assert_eq!(got, ["a", "b", "c", "a", "b", "c"]);
    }

    #[test]
    fn a_worker_with_queries_in_flight_gets_fewer_new_ones() {
        let mut p = pool(&["slow", "fast"]);
        let t = Instant::now();
        // "slow" never answers (frozen); "fast" answers each query at once.
        let mut to_slow = 0;
        for _ in 0..100 {
            let id = p.pick(t).unwrap();
            if id == "slow" {
                to_slow += 1;
            } else {
                p.ended(&id, Outcome::Answered, t);
            }
        }
        assert_eq!(to_slow, 1, "a worker that holds a query gets no other while another is idle");
    }

    #[test]
    fn a_failed_worker_is_left_out_with_a_doubling_backoff_and_back_after_an_answer() {
        let mut p = pool(&["a", "b"]);
        let t0 = Instant::now();
        assert_eq!(p.pick(t0).unwrap(), "a");
        p.ended("a", Outcome::Failed, t0);
        for k in 0..5 {
            let id = p.pick(t0 + Duration::from_millis(k * 40)).unwrap();
            assert_eq!(id, "b");
            p.ended(&id, Outcome::Answered, t0);
        }
        assert!(p.report(t0)[0].left_out);
        // After 0.25 s "a" is tried again; a second failure leaves it out for 0.5 s.
        let t1 = t0 + FIRST_BACKOFF;
        assert_eq!(p.pick(t1).unwrap(), "a");
        p.ended("a", Outcome::Failed, t1);
        assert_eq!(p.pick(t1 + Duration::from_millis(400)).unwrap(), "b");
        p.ended("b", Outcome::Answered, t1);
        let t2 = t1 + 2 * FIRST_BACKOFF;
        assert_eq!(p.pick(t2).unwrap(), "a");
        p.ended("a", Outcome::Answered, t2);
        let r = p.report(t2);
        assert!(!r[0].left_out && r[0].answered == 1 && r[0].failed == 2 && r[0].in_flight == 0);
    }

    #[test]
    fn the_backoff_is_capped_and_a_lone_failing_worker_is_still_asked() {
        let mut p = pool(&["only"]);
        let t = Instant::now();
        for _ in 0..40 {
            let id = p.pick(t).expect("the only worker is asked even while left out");
            p.ended(&id, Outcome::Failed, t);
        }
        let w = &p.workers[0];
        assert_eq!(w.left_out_until, Some(t + MAX_BACKOFF));
        assert_eq!(w.in_flight, 0);
    }

    #[test]
    fn workers_leave_bad_ids_and_overflow_are_refused_and_unknown_endings_are_ignored() {
        let mut p = pool(&["a"]);
        assert!(!p.join("..") && !p.join("") && !p.join("a/b"));
        for k in 1..MAX_WORKERS {
            assert!(p.join(&format!("w{k}")));
        }
        assert!(!p.join("one-too-many"));
        assert_eq!(p.refused, 4);
        assert!(p.join("a"), "a known worker joining again is no change");
        p.leave("a");
        assert_eq!(p.workers.len(), MAX_WORKERS - 1);
        p.ended("a", Outcome::Answered, Instant::now()); // a reply after it left: nothing to count
        let mut empty = Pool::default();
        assert!(empty.pick(Instant::now()).is_none());
    }
}
