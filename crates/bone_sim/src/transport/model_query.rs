//! The engine's side of the model: the sessions' windows of each 100 ms burst leave in one query,
//! to one worker of the pool (or, with none, to every queryable on the shared key), and each
//! reply's predictions go back to their sessions as commands. Windows are asked on the comm
//! thread; replies come on Zenoh's threads. Why one query a burst:
//! `docs/decisions/0032-one-query-a-burst.md`.

use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

use zenoh::query::{ConsolidationMode, QueryTarget};
use zenoh::sample::SampleKind;
use zenoh::Wait;

use super::pool::Outcome;
use super::{encoding, lock, Shared};
use crate::engine::handoff::Command;
use crate::engine::{GRACE_PERIODS, HOLD_LOOK_PERIODS, TICK_PERIOD};
use crate::error::{SimError, SimResult};
use crate::protocol::keys;
use crate::protocol::{self, MAX_PAYLOAD_BYTES, MAX_QUERY_WINDOWS, PREDICT, WINDOW_RECORDS};
use crate::record::FEATURE_COUNT;

/// Model round trips kept for the latency quantiles.
const LATENCIES_KEPT: usize = 2000;
/// Longest a session's new window waits for the rest of its burst before its model query leaves.
/// Every session records on one 100 ms grid (decision 0028), so each period's windows reach this
/// thread within a few ticks of one another; they leave in one query as soon as every open
/// session's is in, or after this wait (one at a time, a query and its reply cost about as much
/// as the forward pass: decision 0032). The spread it covers: the clients' pose phases (a period)
/// and, for a session whose record falls on a tick without a pose, that tick's grace and the
/// tick thread's late look for it (decision 0034): 6 ms. With 2 ms, 16 clients on 2 cores sent
/// 1.4–1.5 queries a grid mark, and the model as many forward passes (decision 0035).
const BURST_WAIT: Duration =
    Duration::from_micros(((1.0 + GRACE_PERIODS + HOLD_LOOK_PERIODS) * TICK_PERIOD.as_micros() as f64) as u64);
const _: () = assert!(MAX_QUERY_WINDOWS <= 64, "a query's answered windows are bits of a u64");

/// A window in the burst waiting for its query: whose it is.
#[derive(Debug, Clone, Copy)]
struct Asked {
    slot: u16,
    generation: u32,
    window_seq: u32,
    /// The client time of the pose its session's last force used (the guidance echoes it).
    pose_time_ns: u64,
    /// When the window reached this thread: its model latency counts from here, its wait for the
    /// rest of the burst included.
    at: Instant,
}

/// The windows of the burst now arriving, and their query's payload so far.
struct Burst {
    asked: Vec<Asked>,
    payload: Vec<u8>,
    /// When its first window arrived.
    since: Instant,
}

impl Burst {
    fn new() -> Self {
        Burst {
            asked: Vec::with_capacity(MAX_QUERY_WINDOWS),
            payload: Vec::with_capacity(MAX_QUERY_WINDOWS * PREDICT.size),
            since: Instant::now(),
        }
    }

    /// Whether its query leaves now: every open session's window is in, or the first has waited
    /// [`BURST_WAIT`].
    fn due(&self, sessions: u64, now: Instant) -> bool {
        !self.asked.is_empty() && (self.asked.len() as u64 >= sessions || now >= self.since + BURST_WAIT)
    }
}

/// The comm thread's model queries: the burst of windows now arriving, and where it goes.
pub(super) struct ModelQueries {
    session: zenoh::Session,
    shared: Arc<Shared>,
    querier: zenoh::query::Querier<'static>,
    burst: Burst,
}

impl ModelQueries {
    /// Follows the pool's workers and declares the querier of the shared key.
    pub(super) fn declare(session: &zenoh::Session, shared: &Arc<Shared>) -> SimResult<Self> {
        follow_workers(session, shared)?;
        let querier = session
            .declare_querier(keys::shared_predict(&shared.prefix))
            // With no worker in the pool: every queryable on the shared key gets every query (the
            // first valid prediction for each window is applied, the rest are counted as ignored);
            // with BestMatching, Zenoh would pick one per query, and a stalled one would get a share
            // to itself.
            .target(QueryTarget::All)
            .consolidation(ConsolidationMode::None)
            .timeout(Duration::from_secs_f64(shared.config.model_timeout_s))
            .wait()
            .map_err(|e| SimError::Transport(format!("cannot declare the model querier: {e}")))?;
        Ok(Self { session: session.clone(), shared: shared.clone(), querier, burst: Burst::new() })
    }

    /// Adds a session's newest window (of its record `window_seq`) to the burst; the burst's query
    /// leaves once it is full or due (see [`Burst::due`]).
    pub(super) fn ask(
        &mut self,
        slot: u16,
        generation: u32,
        window_seq: u32,
        pose_time_ns: u64,
        window: &[[f32; FEATURE_COUNT]; WINDOW_RECORDS],
    ) {
        let (b, at) = (&mut self.burst, Instant::now());
        if b.asked.is_empty() {
            b.since = at;
        }
        protocol::push_predict(&mut b.payload, b.asked.len() as u32, window_seq, window);
        b.asked.push(Asked { slot, generation, window_seq, pose_time_ns, at });
        if b.asked.len() == MAX_QUERY_WINDOWS {
            self.send_burst();
        } else {
            self.send_if_due(at);
        }
    }

    /// Sends the burst's query if it is due at `now`: every open session's window is in, or the
    /// first has waited [`BURST_WAIT`].
    pub(super) fn send_if_due(&mut self, now: Instant) {
        if self.burst.due(self.shared.stats.sessions.load(Ordering::Relaxed), now) {
            self.send_burst();
        }
    }

    /// When the burst waiting leaves at the latest (`None`: no window waits).
    pub(super) fn deadline(&self) -> Option<Instant> {
        (!self.burst.asked.is_empty()).then(|| self.burst.since + BURST_WAIT)
    }

    /// Lets the burst waiting go unasked (a stopping server's).
    pub(super) fn drop_burst(&mut self) {
        self.burst = Burst::new();
    }

    /// Sends the burst's windows in one model query (if it has any).
    fn send_burst(&mut self) {
        if self.burst.asked.is_empty() {
            return;
        }
        let Burst { asked, payload, .. } = std::mem::replace(&mut self.burst, Burst::new());
        self.query(asked, payload);
    }

    /// Sends one query with these windows (`payload`, their predict layouts) to a worker of the
    /// pool, or with none to the shared key; each reply's predictions are applied as it comes.
    fn query(&self, asked: Vec<Asked>, payload: Vec<u8>) {
        let shared = self.shared.clone();
        shared.counters.model_queries.fetch_add(asked.len() as u64, Ordering::Relaxed);
        shared.counters.model_bursts.fetch_add(1, Ordering::Relaxed);
        // One worker of the pool answers (`pool`), or, with no worker in the pool, every
        // queryable on the shared key. Either way at most one prediction per window is applied:
        // the first valid one; a second worker's (or a rogue's) extra replies must not override it.
        let worker = lock(&shared.pool).pick(Instant::now());
        let ending = Ending { shared: shared.clone(), worker: worker.clone(), answers: Answers::new(asked) };
        let on_reply = move |reply: zenoh::query::Reply| {
            let shared = &ending.shared;
            let bytes = match reply.result() {
                Ok(sample) if sample.payload().len() <= MAX_QUERY_WINDOWS * MAX_PAYLOAD_BYTES => {
                    sample.payload().to_bytes()
                }
                _ => {
                    shared.counters.model_errors.fetch_add(1, Ordering::Relaxed);
                    return;
                }
            };
            // Every window answered: a second worker's or a rogue's extra replies change nothing,
            // so they are counted without taking the registry the poses' threads take.
            if ending.answers.complete() {
                shared.counters.model_ignored.fetch_add(1, Ordering::Relaxed);
                return;
            }
            let mut latencies = Vec::new();
            let mut reg = lock(&shared.registry);
            let tally = ending.answers.take(&bytes, |a, p| {
                let Some(info) = reg.slots.get_mut(usize::from(a.slot)).filter(|i| i.generation == a.generation) else {
                    return Verdict::Gone;
                };
                if info.attempt_first_window.is_none_or(|first| seq_after(first, a.window_seq)) {
                    return Verdict::Retired;
                }
                if info.applied_window_seq.is_some_and(|newest| !seq_after(a.window_seq, newest)) {
                    return Verdict::Older;
                }
                let latency_s = a.at.elapsed().as_secs_f64();
                let cmd = Command::Prediction {
                    slot: a.slot,
                    generation: a.generation,
                    window_seq: a.window_seq,
                    predicted_n: [p.force_n.x, p.force_n.y, p.force_n.z],
                    latency_s,
                    pose_client_time_ns: a.pose_time_ns,
                };
                // The guidance message leaves as the prediction is applied: now, not at the
                // session's next tick (up to 1 ms away, more for a paused client): sending the
                // command woke the tick thread. Why:
                // docs/decisions/0009-model-reply-wakes-the-tick.md.
                if reg.send(cmd).is_err() {
                    return Verdict::Dropped; // the engine's command ring is full
                }
                // `info` again: the send borrowed the registry.
                if let Some(info) = reg.slots.get_mut(usize::from(a.slot)) {
                    info.applied_window_seq = Some(a.window_seq);
                }
                latencies.push(latency_s);
                Verdict::Applied
            });
            drop(reg);
            let c = &shared.counters;
            c.model_replies.fetch_add(latencies.len() as u64, Ordering::Relaxed);
            c.model_errors.fetch_add(tally.errors, Ordering::Relaxed);
            c.model_ignored.fetch_add(tally.ignored, Ordering::Relaxed);
            c.model_dropped.fetch_add(tally.dropped, Ordering::Relaxed);
            let Some(id) = tally.model_id.filter(|_| !latencies.is_empty()) else { return };
            let mut m = lock(&shared.model);
            m.last_reply = Some(Instant::now());
            for latency_s in latencies {
                if m.latencies_s.len() == LATENCIES_KEPT {
                    m.latencies_s.pop_front();
                }
                m.latencies_s.push_back(latency_s);
            }
            m.model_id = id;
        };
        let sent_ok = match &worker {
            Some(id) => self
                .session
                .get(keys::worker_predict(&self.shared.prefix, id))
                .target(QueryTarget::All)
                .consolidation(ConsolidationMode::None)
                .timeout(Duration::from_secs_f64(self.shared.config.model_timeout_s))
                .payload(payload)
                .encoding(encoding("predict"))
                .callback(on_reply)
                .wait(),
            None => self.querier.get().payload(payload).encoding(encoding("predict")).callback(on_reply).wait(),
        };
        if sent_ok.is_err() {
            self.shared.counters.model_errors.fetch_add(1, Ordering::Relaxed);
        }
    }
}

/// Whether window sequence number `a` comes after `b` (they wrap at 2³²).
fn seq_after(a: u32, b: u32) -> bool {
    (a.wrapping_sub(b) as i32) > 0
}

/// What the engine made of a window's prediction.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Verdict {
    /// Applied: its session's guidance follows it.
    Applied,
    /// Not applied: its session has applied a newer window's (a late reply).
    Older,
    /// Not applied: its session ended (or the engine could not take it). The query counts as
    /// answered for the worker.
    Gone,
    /// Not applied: its window is of an attempt its session has ended (a reset). The worker
    /// answered in time, so the query counts as answered for it.
    Retired,
    /// Not applied: the engine's command queue was full. Counted (`dropped`); the worker
    /// answered in time, so the query counts as answered for it.
    Dropped,
}

/// What one reply held, beyond the predictions applied.
#[derive(Debug, Default, PartialEq)]
struct Tally {
    /// Predictions refused by the decoder (the first ends the reply), for a window the query does
    /// not have, or with another window's `window_seq`.
    errors: u64,
    /// Valid predictions not applied: a second one for a window, one for a window older than its
    /// session's newest applied, or one for a window of an attempt its session has ended.
    ignored: u64,
    /// Valid predictions the engine's full command queue could not take.
    dropped: u64,
    /// The model id of the last prediction taken.
    model_id: Option<String>,
}

/// A query's windows and which of them have been answered (a bit per entry).
#[derive(Debug)]
struct Answers {
    asked: Vec<Asked>,
    /// Bit `entry` of each window a valid prediction came for.
    answered: AtomicU64,
    /// Bit `entry` of each window whose prediction served: applied, or in time for a window of an
    /// attempt or a session that has ended since ([`Verdict::Retired`], [`Verdict::Gone`]), or
    /// dropped by a full command queue ([`Verdict::Dropped`]).
    served: AtomicU64,
}

impl Answers {
    fn new(asked: Vec<Asked>) -> Self {
        Answers { asked, answered: AtomicU64::new(0), served: AtomicU64::new(0) }
    }

    /// Takes one reply: each prediction is matched to its window by `entry` and `window_seq`,
    /// and the first valid one for each window goes to `apply` (later ones are ignored).
    fn take(&self, bytes: &[u8], mut apply: impl FnMut(&Asked, &protocol::Prediction) -> Verdict) -> Tally {
        let mut tally = Tally::default();
        for p in protocol::decode_predictions(bytes) {
            let matched = p.ok().and_then(|p| Some((*self.asked.get(p.entry as usize)?, p)));
            let Some((a, p)) = matched.filter(|(a, p)| a.window_seq == p.window_seq) else {
                tally.errors += 1;
                continue; // a refused prediction ends the reply: the decoder yields nothing after it
            };
            let bit = 1u64 << p.entry; // entry < asked.len() <= MAX_QUERY_WINDOWS <= 64
            if self.answered.fetch_or(bit, Ordering::AcqRel) & bit != 0 {
                tally.ignored += 1;
                continue;
            }
            let verdict = apply(&a, &p);
            // Only a late answer counts against the worker: a session gone or an attempt ended
            // meanwhile is not its doing.
            if verdict != Verdict::Older {
                self.served.fetch_or(bit, Ordering::AcqRel);
            }
            if matches!(verdict, Verdict::Older | Verdict::Retired) {
                tally.ignored += 1;
            }
            if verdict == Verdict::Dropped {
                tally.dropped += 1;
            }
            tally.model_id = Some(p.model_id);
        }
        tally
    }

    /// Whether every window has had its valid prediction: later replies can change nothing.
    fn complete(&self) -> bool {
        let n = self.asked.len();
        let all = if n >= 64 { u64::MAX } else { (1u64 << n) - 1 };
        self.answered.load(Ordering::Acquire) & all == all
    }

    /// How the query did, once it has ended: answered when most of its windows' predictions
    /// served (a worker that answers the first window of each query alone fails), and how many
    /// windows no valid prediction came for.
    fn outcome(&self) -> (Outcome, u64) {
        let n = self.asked.len() as u64;
        let served = u64::from(self.served.load(Ordering::Acquire).count_ones());
        let unanswered = n - u64::from(self.answered.load(Ordering::Acquire).count_ones());
        (if 2 * served > n { Outcome::Answered } else { Outcome::Failed }, unanswered)
    }
}

/// What a model query holds until it ends (Zenoh drops the reply callback, and this with it, once
/// every reply is in or the query timed out): counts the windows left unanswered and tells the
/// pool how its worker did.
struct Ending {
    shared: Arc<Shared>,
    worker: Option<String>,
    answers: Answers,
}

impl Drop for Ending {
    fn drop(&mut self) {
        let (outcome, unanswered) = self.answers.outcome();
        self.shared.counters.model_unanswered.fetch_add(unanswered, Ordering::Relaxed);
        if let Some(id) = &self.worker {
            lock(&self.shared.pool).ended(id, outcome, Instant::now());
        }
    }
}

/// Follows the model workers' liveliness tokens (`<prefix>/model/workers/<id>`) into the pool,
/// those alive before the engine started included.
fn follow_workers(session: &zenoh::Session, shared: &Arc<Shared>) -> SimResult<()> {
    let s = shared.clone();
    let prefix = keys::worker(&shared.prefix, "");
    session
        .liveliness()
        .declare_subscriber(keys::worker(&shared.prefix, "*"))
        .history(true)
        .callback(move |sample| {
            let Some(id) = sample.key_expr().as_str().strip_prefix(&prefix) else { return };
            let mut pool = lock(&s.pool);
            match sample.kind() {
                SampleKind::Put => {
                    pool.join(id);
                }
                SampleKind::Delete => pool.leave(id),
            }
        })
        .background()
        .wait()
        .map_err(|e| SimError::Transport(format!("cannot follow the model workers: {e}")))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn asked(slot: u16, window_seq: u32) -> Asked {
        Asked { slot, generation: 1, window_seq, pose_time_ns: 0, at: Instant::now() }
    }

    /// A prediction of `entry` for window `window_seq` (force z = `z`), as a worker writes it.
    fn prediction(entry: u32, window_seq: u32, z: f32) -> Vec<u8> {
        let mut b = vec![0u8; protocol::PREDICTION.size];
        b[0] = protocol::PREDICTION.kind;
        b[1] = protocol::VERSION;
        b[4..8].copy_from_slice(&window_seq.to_le_bytes());
        b[16..20].copy_from_slice(&z.to_le_bytes());
        b[24..26].copy_from_slice(&1u16.to_le_bytes());
        b[28..32].copy_from_slice(&entry.to_le_bytes());
        b.push(b'm');
        b
    }

    #[test]
    fn each_window_takes_the_first_valid_prediction_for_it_in_any_order_and_over_several_replies() {
        let answers = Answers::new(vec![asked(3, 10), asked(5, 20), asked(7, 30)]);
        let mut got = Vec::new();
        let mut apply = |a: &Asked, p: &protocol::Prediction| {
            got.push((a.slot, p.force_n.z));
            Verdict::Applied
        };
        let first = [prediction(2, 30, 3.0), prediction(0, 10, 1.0)].concat();
        assert_eq!(answers.take(&first, &mut apply), Tally { model_id: Some("m".into()), ..Tally::default() });
        assert!(!answers.complete(), "entry 1 is still open");
        // A second reply: entry 0 again (ignored), entry 1 with entry 2's window_seq and an entry
        // the query does not have (errors), then entry 1 itself.
        let second =
            [prediction(0, 10, 9.0), prediction(1, 30, 9.0), prediction(3, 20, 9.0), prediction(1, 20, 2.0)].concat();
        let t = answers.take(&second, &mut apply);
        assert_eq!((t.errors, t.ignored), (2, 1));
        assert_eq!(got, [(7, 3.0), (3, 1.0), (5, 2.0)], "each session got its own window's prediction, once");
        assert_eq!(answers.outcome(), (Outcome::Answered, 0));
        assert!(answers.complete(), "every window answered: a later reply is not read");
        let n = protocol::MAX_QUERY_WINDOWS;
        let full = Answers::new((0..n as u16).map(|i| asked(i, 1)).collect());
        let all: Vec<u8> = (0..n as u32).flat_map(|e| prediction(e, 1, 1.0)).collect();
        assert!(!full.complete());
        full.take(&all, |_, _| Verdict::Applied);
        assert!(full.complete(), "a full query, every bit");
    }

    #[test]
    fn a_worker_that_answers_only_the_first_window_fails_and_the_rest_count_as_unanswered() {
        let answers = Answers::new(vec![asked(0, 1), asked(1, 1), asked(2, 1)]);
        answers.take(&prediction(0, 1, 1.0), |_, _| Verdict::Applied);
        assert_eq!(answers.outcome(), (Outcome::Failed, 2));
        // Most applied: answered, the one left out counted.
        let answers = Answers::new(vec![asked(0, 1), asked(1, 1), asked(2, 1)]);
        answers.take(&[prediction(0, 1, 1.0), prediction(2, 1, 1.0)].concat(), |_, _| Verdict::Applied);
        assert_eq!(answers.outcome(), (Outcome::Answered, 1));
        // A late worker: every prediction valid but older than its session's newest: failed.
        let answers = Answers::new(vec![asked(0, 1)]);
        let t = answers.take(&prediction(0, 1, 1.0), |_, _| Verdict::Older);
        assert_eq!((t.ignored, answers.outcome()), (1, (Outcome::Failed, 0)));
        // In time, but for an attempt its session has ended since (a reset): not applied,
        // ignored, and the worker answered.
        let answers = Answers::new(vec![asked(0, 1)]);
        let t = answers.take(&prediction(0, 1, 1.0), |_, _| Verdict::Retired);
        assert_eq!((t.ignored, answers.outcome()), (1, (Outcome::Answered, 0)));
        // For a session that has ended since: not counted, and the worker answered.
        let answers = Answers::new(vec![asked(0, 1), asked(1, 1)]);
        let t = answers.take(&[prediction(0, 1, 1.0), prediction(1, 1, 1.0)].concat(), |a, _| {
            if a.slot == 0 {
                Verdict::Gone
            } else {
                Verdict::Applied
            }
        });
        assert_eq!((t.ignored, t.errors, answers.outcome()), (0, 0, (Outcome::Answered, 0)));
        // The engine's command queue full: counted as dropped, not ignored; the worker answered.
        let answers = Answers::new(vec![asked(0, 1)]);
        let t = answers.take(&prediction(0, 1, 1.0), |_, _| Verdict::Dropped);
        assert_eq!((t.dropped, t.ignored, answers.outcome()), (1, 0, (Outcome::Answered, 0)));
        // A refused prediction ends the reply; nothing after it is read.
        let answers = Answers::new(vec![asked(0, 1), asked(1, 2)]);
        let mut bad = prediction(0, 1, f32::NAN);
        bad.extend(prediction(1, 2, 1.0));
        let t = answers.take(&bad, |_, _| Verdict::Applied);
        assert_eq!((t.errors, answers.outcome()), (1, (Outcome::Failed, 2)));
    }

    #[test]
    fn a_burst_leaves_when_every_session_has_asked_or_its_first_window_has_waited() {
        let mut b = Burst::new();
        let t0 = b.since;
        assert!(!b.due(0, t0 + BURST_WAIT), "an empty burst never leaves");
        b.asked.push(asked(0, 1));
        assert!(!b.due(3, t0), "one window of three sessions' waits");
        assert!(!b.due(3, t0 + BURST_WAIT / 2));
        assert!(b.due(3, t0 + BURST_WAIT), "...at most BURST_WAIT");
        b.asked.extend([b.asked[0]; 2]);
        assert!(b.due(3, t0), "every session's window is in: at once");
        assert!(b.due(2, t0), "a session ended meanwhile");
    }

    #[test]
    fn a_reply_is_newer_only_if_its_window_comes_after_across_the_wrap() {
        assert!(seq_after(2, 1) && !seq_after(1, 2) && !seq_after(5, 5));
        assert!(seq_after(0, u32::MAX) && seq_after(3, u32::MAX - 3), "sequence numbers wrap at 2^32");
        assert!(!seq_after(u32::MAX, 0));
    }
}
