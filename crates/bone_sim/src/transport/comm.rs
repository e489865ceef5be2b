//! The comm thread: drains the outputs of every tick, publishes them (but the forces a pose's own
//! thread already put), keeps each session's window of records and the batches of its ticks, and
//! sends the model queries, one for each burst of sessions' windows. It sleeps until a tick
//! unparks it (at most [`IDLE_WAKE`], or until the burst waiting is due), or spins
//! ([`WaitMode::Spin`]).

use std::collections::VecDeque;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::Arc;
use std::thread::{self, JoinHandle};
use std::time::{Duration, Instant};

use zenoh::bytes::Encoding;
use zenoh::qos::{CongestionControl, Priority};
use zenoh::query::{ConsolidationMode, QueryTarget};
use zenoh::sample::Locality;
use zenoh::sample::SampleKind;
use zenoh::Wait;
use zenoh_ext::{AdvancedPublisher, AdvancedPublisherBuilderExt, CacheConfig, MissDetectionConfig};

use super::pool::Outcome;
use super::registry::ForcePublisher;
use super::{lock, Shared, ZENOH_IO_THREADS};
use crate::engine::handoff::{Command, Output};
use crate::engine::realtime;
use crate::engine::stats::HistogramSnapshot;
use crate::engine::WaitMode;
use crate::engine::{OutputQueue, GRACE_PERIODS, HOLD_LOOK_PERIODS, TICK_PERIOD};
use crate::error::{SimError, SimResult};
use crate::protocol::{self, TickBatch, MAX_PAYLOAD_BYTES, MAX_QUERY_WINDOWS, PREDICT, WINDOW_RECORDS};
use crate::record::{FEATURE_COUNT, RECORD_PERIOD_TICKS};
use crate::session::Pose;

/// Seconds of per-second tick-statistics history kept for the health report.
const HISTORY_S: usize = 600;
/// Model round trips kept for the latency quantiles.
const LATENCIES_KEPT: usize = 2000;
/// Longest the comm thread sleeps: forces a pose's thread already put are queued without waking
/// it, only to be added to the recorders' batches, so it takes them in this often.
pub(crate) const IDLE_WAKE: Duration = Duration::from_millis(20);
/// Longest a session's new window waits for the rest of its burst before its model query leaves.
/// Every session records on one 100 ms grid (decision 0028), so each period's windows reach this
/// thread within a few ticks of one another; they leave in one query as soon as every open
/// session's is in, or after this wait (one at a time, a query and its reply cost about as much
/// as the forward pass: decision 0032). The spread it covers: the clients' pose phases (a period)
/// and, for a session whose record falls on a tick without a pose, that tick's grace and the
/// tick thread's late look for it (decision 0034): 6 ms. With 2 ms, 16 clients on 2 cores sent
/// 1.4–1.5 queries a grid mark, and the model as many forward passes (decision 0035).
pub(crate) const BURST_WAIT: Duration =
    Duration::from_micros(((1.0 + GRACE_PERIODS + HOLD_LOOK_PERIODS) * TICK_PERIOD.as_micros() as f64) as u64);
const _: () = assert!(MAX_QUERY_WINDOWS <= 64, "a query's answered windows are bits of a u64");

/// One second's cumulative tick statistics.
#[derive(Debug, Clone)]
pub(crate) struct StatsSample {
    pub(crate) at: Instant,
    pub(crate) ticks: u64,
    pub(crate) pose_thread_ticks: u64,
    pub(crate) poses_left: [u64; 3],
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
            ticks: self.ticks - b.ticks,
            pose_thread_ticks: self.pose_thread_ticks - b.pose_thread_ticks,
            poses_left: std::array::from_fn(|i| self.poses_left[i] - b.poses_left[i]),
            wakes: self.wakes - b.wakes,
            missed: self.missed - b.missed,
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

/// The tick statistics now.
pub(crate) fn sample(shared: &Shared) -> StatsSample {
    let s = &shared.stats;
    StatsSample {
        at: Instant::now(),
        ticks: s.ticks.load(Ordering::Relaxed),
        pose_thread_ticks: s.pose_thread_ticks.load(Ordering::Relaxed),
        poses_left: std::array::from_fn(|i| s.poses_left[i].load(Ordering::Relaxed)),
        wakes: s.wakes.load(Ordering::Relaxed),
        missed: s.missed.load(Ordering::Relaxed),
        lateness: s.lateness.snapshot(),
        busy: s.busy.snapshot(),
        pose_to_tick: s.pose_to_tick.snapshot(),
        pose_to_put: s.pose_to_put.snapshot(),
    }
}

/// A session's publishers and model window.
struct Outlet {
    generation: u32,
    force: Arc<ForcePublisher>,
    guidance: AdvancedPublisher<'static>,
    state: AdvancedPublisher<'static>,
    ticks: AdvancedPublisher<'static>,
    /// The ticks since the last batch was published, and when its first arrived.
    batch: TickBatch,
    batch_since: Instant,
    window: VecDeque<[f32; FEATURE_COUNT]>,
    window_seq: u32,
    pose_time_ns: u64,
    /// The screens' streams (`view/force`, `view/pose`): the newest force and pose at most
    /// [`VIEW_HZ`] times a second.
    view_force: ViewStream,
    view_pose: ViewStream,
    /// The newest force and the pose it used, not yet on the view streams.
    view: Option<(protocol::ForceMsg, Option<Pose>)>,
    view_sent: Instant,
}

/// One of a session's view streams: its publisher, and whether a subscriber in another Zenoh session
/// (a screen) matches it, kept by Zenoh's matching listener. A stream nobody watches is not put
/// (`docs/decisions/0025-view-streams.md`).
struct ViewStream {
    publisher: zenoh::pubsub::Publisher<'static>,
    watched: Arc<AtomicBool>,
}

impl ViewStream {
    /// Declares the stream on `key`: the newest, a frame's worth, dropped rather than queued, and
    /// only for other sessions (the engine's own catch-all subscriber, which counts puts on
    /// unknown keys, would otherwise always match it).
    fn declare(session: &zenoh::Session, key: String, encoding: Encoding) -> Option<Self> {
        let publisher = session
            .declare_publisher(key)
            .encoding(encoding)
            .congestion_control(CongestionControl::Drop)
            .priority(Priority::DataLow)
            .allowed_destination(Locality::Remote)
            .wait()
            .ok()?;
        Some(Self::new(publisher))
    }

    fn new(publisher: zenoh::pubsub::Publisher<'static>) -> Self {
        let watched = Arc::new(AtomicBool::new(false));
        let flag = watched.clone();
        let listening = publisher
            .matching_listener()
            .callback(move |status| flag.store(status.matching(), Ordering::Relaxed))
            .background()
            .wait()
            .is_ok();
        // Without a listener (it could not be declared), put always, as before; with one, also
        // the status as it is now, in case the listener reports only changes.
        let now = publisher.matching_status().wait().map_or(true, |m| m.matching());
        watched.fetch_or(now || !listening, Ordering::Relaxed);
        Self { publisher, watched }
    }

    fn watched(&self) -> bool {
        self.watched.load(Ordering::Relaxed)
    }
}

/// Most messages a second on a session's view streams (`view/force`, `view/pose`): what a screen
/// draws the drill from, instead of taking in the two 1 kHz streams and dropping most of them (a
/// viewer's CPU fell fourfold without them, `docs/benchmarks.md`, the live view). The comm thread
/// wakes at least every [`IDLE_WAKE`] (20 ms), so they leave 50–60 times a second.
pub(crate) const VIEW_HZ: f64 = 60.0;

/// Samples of each recorded stream (state, guidance) a session's publisher keeps for recorders
/// to recover: 60 s of the 10 Hz streams.
const RECORDED_HISTORY: usize = 600;
/// Batches of the recorders' 1 kHz stream (`ticks`, 10 a second) a session's publisher keeps:
/// 10 s, about 0.9 MB a session.
const TICKS_HISTORY: usize = 100;
/// Ticks in one batch: one record period, so a batch leaves at 10 Hz.
const TICKS_PER_BATCH: usize = RECORD_PERIOD_TICKS as usize;
/// A partial batch older than this (a silent or ended session) leaves at the next housekeeping.
const BATCH_MAX_AGE: Duration = Duration::from_millis(200);
/// How often a recorded stream's publisher announces its last sequence number, so that a
/// recorder notices a lost last sample too.
const RECORDED_HEARTBEAT: Duration = Duration::from_millis(500);

fn encoding(name: &str) -> Encoding {
    Encoding::APPLICATION_OCTET_STREAM.with_schema(format!("dhg.{name}.v{}", protocol::VERSION))
}

impl Outlet {
    /// Adds a tick to the batch for the recorders; a full batch leaves.
    fn add_tick(&mut self, msg: &protocol::ForceMsg, pose: Option<&Pose>) {
        if self.batch.is_empty() {
            self.batch_since = Instant::now();
        }
        let mut row = protocol::TickRow {
            tick: msg.tick,
            pose_seq: if pose.is_some() { msg.pose_seq } else { 0 }, // after a reset: none yet
            flags: msg.flags,
            force_n: msg.force_n,
            guidance_n: msg.guidance_n,
            ..Default::default()
        };
        if let Some(p) = pose {
            let q = p.orientation.quaternion();
            row.position_m = p.position_m.coords.into();
            row.orientation_wxyz = [q.w, q.i, q.j, q.k];
            row.spindle_rpm = p.spindle_rpm;
        }
        self.batch.push(&row);
        if self.batch.len() >= TICKS_PER_BATCH {
            self.publish_ticks();
        }
    }

    /// Puts the newest force and pose on the view streams, if they are new and the last went
    /// out at least 1 / [`VIEW_HZ`] ago.
    fn publish_view(&mut self, now: Instant) {
        if now.saturating_duration_since(self.view_sent).as_secs_f64() * VIEW_HZ < 1.0 {
            return;
        }
        let (force, pose_too) = (self.view_force.watched(), self.view_pose.watched());
        if !force && !pose_too {
            return; // no screen: the newest waits for one
        }
        let Some((msg, pose)) = self.view.take() else { return };
        self.view_sent = now;
        if force {
            let _ = self.view_force.publisher.put(protocol::encode_force(&msg).to_vec()).wait();
        }
        if let (Some(pose), true) = (pose, pose_too) {
            let m = protocol::PoseMsg { seq: msg.pose_seq, client_time_ns: msg.pose_client_time_ns, pose };
            let _ = self.view_pose.publisher.put(protocol::encode_pose(&m).to_vec()).wait();
        }
    }

    /// Publishes the batch of ticks, if it has any.
    fn publish_ticks(&mut self) {
        if !self.batch.is_empty() {
            let _ = self.ticks.put(self.batch.take()).wait();
        }
    }
}

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

struct Comm {
    session: zenoh::Session,
    shared: Arc<Shared>,
    outlets: Vec<Option<Outlet>>,
    querier: zenoh::query::Querier<'static>,
    burst: Burst,
}

impl Comm {
    fn outlet(&mut self, slot: u16, generation: u32) -> Option<&mut Outlet> {
        let i = slot as usize;
        let stale = self.outlets[i].as_ref().is_none_or(|o| o.generation != generation);
        if stale {
            if let Some(mut old) = self.outlets[i].take() {
                old.publish_ticks();
            }
            let id = {
                let reg = lock(&self.shared.registry);
                let info = &reg.slots[i];
                if info.generation != generation {
                    return None; // the slot moved on; drop what is left of the old session
                }
                info.id.clone()?
            };
            let key = |leaf: &str| format!("{}/session/{id}/{leaf}", self.shared.prefix);
            let publisher = self
                .session
                .declare_publisher(key("force"))
                .encoding(encoding("force"))
                .congestion_control(CongestionControl::Drop)
                .priority(Priority::RealTime)
                .express(true)
                .wait()
                .ok()?;
            let force = Arc::new(ForcePublisher { generation, publisher });
            // From now on the session's poses put their own forces (if they tick it).
            match lock(&self.shared.registry).slots.get_mut(i) {
                Some(info) if info.generation == generation => info.force = Some(force.clone()),
                _ => return None,
            }
            // State and guidance are recorded for datasets, but a slow or frozen subscriber must
            // never hold up the comm thread (and with it every session's forces): they drop
            // rather than block, and keep the last RECORDED_HISTORY samples for recorders to
            // recover what they missed (zenoh-ext advanced publisher: cache, sample-miss
            // detection with a heartbeat, publisher detection).
            let recorded = |leaf: &str, history: usize| {
                self.session
                    .declare_publisher(key(leaf))
                    .encoding(encoding(leaf))
                    .congestion_control(CongestionControl::Drop)
                    .priority(Priority::DataHigh)
                    .cache(CacheConfig::default().max_samples(history))
                    .sample_miss_detection(MissDetectionConfig::default().heartbeat(RECORDED_HEARTBEAT))
                    .publisher_detection()
                    .wait()
                    .ok()
            };
            // The screens' copies.
            let view =
                |leaf: &str| ViewStream::declare(&self.session, key(leaf), encoding(leaf.trim_start_matches("view/")));
            self.outlets[i] = Some(Outlet {
                generation,
                force,
                guidance: recorded("guidance", RECORDED_HISTORY)?,
                state: recorded("state", RECORDED_HISTORY)?,
                ticks: recorded("ticks", TICKS_HISTORY)?,
                batch: TickBatch::with_capacity(TICKS_PER_BATCH),
                batch_since: Instant::now(),
                window: VecDeque::with_capacity(WINDOW_RECORDS),
                window_seq: 0,
                pose_time_ns: 0,
                view_force: view("view/force")?,
                view_pose: view("view/pose")?,
                view: None,
                view_sent: Instant::now(),
            });
        }
        self.outlets[i].as_mut()
    }

    #[allow(clippy::large_types_passed_by_value)] // moved into the ring / consumed: by value is the point
    fn handle(&mut self, out: Output) {
        match out {
            Output::Force { slot, generation, msg, pose, received, order, published } => {
                let shared = self.shared.clone();
                if let Some(o) = self.outlet(slot, generation) {
                    o.pose_time_ns = msg.pose_client_time_ns;
                    if !published {
                        put_force(&shared, &o.force, slot, &msg, received, order);
                    }
                    o.add_tick(&msg, pose.as_ref());
                    o.view = Some((msg, pose));
                } else {
                    // Of a session that ended: let go, so that the slot's next forces may leave
                    // from their poses' threads.
                    for n in [&shared.put_begun, &shared.put_done].into_iter().filter_map(|a| a.get(usize::from(slot)))
                    {
                        n.fetch_max(order, Ordering::AcqRel);
                    }
                }
            }
            Output::State { slot, generation, record, msg } => {
                let Some(o) = self.outlet(slot, generation) else { return };
                let _ = o.state.put(protocol::encode_state(&msg).to_vec()).wait();
                if o.window.len() == WINDOW_RECORDS {
                    o.window.pop_front();
                }
                o.window.push_back(record.features.map(|x| x as f32));
                o.window_seq = o.window_seq.wrapping_add(1);
                let (window_seq, pose_time_ns) = (o.window_seq, o.pose_time_ns);
                let window = model_window(&o.window);
                if let Some(info) = lock(&self.shared.registry).slots.get_mut(slot as usize) {
                    if info.generation == generation {
                        info.metrics.add_state(&msg, &info.path);
                    }
                }
                let (b, at) = (&mut self.burst, Instant::now());
                if b.asked.is_empty() {
                    b.since = at;
                }
                protocol::push_predict(&mut b.payload, b.asked.len() as u32, window_seq, &window);
                b.asked.push(Asked { slot, generation, window_seq, pose_time_ns, at });
                let sessions = self.shared.stats.sessions.load(Ordering::Relaxed);
                if b.asked.len() == MAX_QUERY_WINDOWS || b.due(sessions, at) {
                    self.send_burst();
                }
            }
            Output::Guidance { slot, generation, msg } => {
                if let Some(o) = self.outlet(slot, generation) {
                    let _ = o.guidance.put(protocol::encode_guidance(&msg).to_vec()).wait();
                }
                if let Some(info) = lock(&self.shared.registry).slots.get_mut(slot as usize) {
                    if info.generation == generation {
                        info.metrics.add_guidance(&msg);
                    }
                }
            }
            Output::Snapshot { .. } => {
                self.shared.snapshot_seq.fetch_add(1, Ordering::AcqRel);
            }
        }
    }

    /// Sends the burst's windows in one model query (if it has any).
    fn send_burst(&mut self) {
        if self.burst.asked.is_empty() {
            return;
        }
        let Burst { asked, payload, .. } = std::mem::replace(&mut self.burst, Burst::new());
        self.query(asked, payload);
    }

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
            let mut latencies = Vec::new();
            let mut reg = lock(&shared.registry);
            let tally = ending.answers.take(&bytes, |a, p| {
                let Some(info) = reg.slots.get_mut(usize::from(a.slot)).filter(|i| i.generation == a.generation) else {
                    return Verdict::Gone;
                };
                if info.applied_window_seq.is_some_and(|newest| !seq_after(a.window_seq, newest)) {
                    return Verdict::Older;
                }
                info.applied_window_seq = Some(a.window_seq);
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
                    return Verdict::Gone; // the engine's command ring is full
                }
                latencies.push(latency_s);
                Verdict::Applied
            });
            drop(reg);
            let c = &shared.counters;
            c.model_replies.fetch_add(latencies.len() as u64, Ordering::Relaxed);
            c.model_errors.fetch_add(tally.errors, Ordering::Relaxed);
            c.model_ignored.fetch_add(tally.ignored, Ordering::Relaxed);
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
                .get(format!("{}/model/workers/{id}/predict", self.shared.prefix))
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

    /// Once a second: the health history, idle sessions, and (when the number of sessions has
    /// changed) the short slice for Zenoh's I/O threads, which it starts as links come up.
    fn housekeeping(&mut self, io_sessions: &mut Option<u64>) {
        let sessions = self.shared.stats.sessions.load(Ordering::Relaxed);
        if *io_sessions != Some(sessions) {
            *io_sessions = Some(sessions);
            let n = realtime::short_slice_named(&ZENOH_IO_THREADS);
            self.shared.counters.io_short_slices.store(n as u64, Ordering::Relaxed);
        }
        let s = sample(&self.shared);
        let mut h = lock(&self.shared.history);
        if h.samples.len() == HISTORY_S {
            h.samples.pop_front();
        }
        h.samples.push_back(s);
        drop(h);
        let idle = self.shared.config.idle_timeout_s;
        lock(&self.shared.registry).sweep_idle(idle);
        for o in self.outlets.iter_mut().flatten() {
            if !o.batch.is_empty() && o.batch_since.elapsed() >= BATCH_MAX_AGE {
                o.publish_ticks();
            }
        }
    }

    fn run(&mut self, outputs: &OutputQueue, wait: WaitMode) {
        // A force waits for this thread's wake-up: preempt longer-sliced threads (no privilege).
        let slice = realtime::short_slice(0);
        self.shared.counters.comm_short_slice.store(u64::from(slice), Ordering::Relaxed);
        let mut io_sessions = None;
        let mut next_housekeeping = Instant::now();
        // Outputs other than forces, handled once every waiting force is out.
        let mut later = VecDeque::with_capacity(4 * self.outlets.len());
        while !self.shared.stopping.load(Ordering::Acquire) {
            if wait == WaitMode::Spin && self.shared.stats.sessions.load(Ordering::Relaxed) > 0 {
                std::hint::spin_loop();
            } else {
                // A tick unparks this thread when it queued output to publish; a burst's query
                // leaves at most BURST_WAIT after its first window.
                let due = self.burst.since + BURST_WAIT;
                let nap =
                    if self.burst.asked.is_empty() { IDLE_WAKE } else { due.saturating_duration_since(Instant::now()) };
                thread::park_timeout(nap);
            }
            drain_forces_first(outputs, &mut later, |out| self.handle(out));
            let now = Instant::now();
            if self.burst.due(self.shared.stats.sessions.load(Ordering::Relaxed), now) {
                self.send_burst();
            }
            for o in self.outlets.iter_mut().flatten() {
                o.publish_view(now);
            }
            if now >= next_housekeeping {
                self.housekeeping(&mut io_sessions);
                next_housekeeping += Duration::from_secs(1);
            }
        }
        for o in self.outlets.iter_mut().flatten() {
            o.publish_ticks();
        }
        self.outlets.clear();
        self.burst = Burst::new(); // the windows of a stopping server go unasked
    }
}

/// Handles every output in `outputs`, forces first: a state's model query or a guidance message
/// takes tens of µs (up to ms), and a force queued behind it would wait for it. So every waiting
/// force, including those that arrive meanwhile, goes out before each of the other outputs, which
/// wait in `later` (kept across calls, so its capacity is reused). Why:
/// `docs/decisions/0008-forces-first.md`.
fn drain_forces_first(outputs: &OutputQueue, later: &mut VecDeque<Output>, mut handle: impl FnMut(Output)) {
    loop {
        while let Some(out) = outputs.pop() {
            if matches!(out, Output::Force { .. }) {
                handle(out);
            } else {
                later.push_back(out);
            }
        }
        let Some(out) = later.pop_front() else { return };
        handle(out);
    }
}

/// Puts a session's force (from the comm thread, or from the thread its pose arrived on), unless
/// a newer force of the slot is already out (`order`: the slot's tick count), and records the
/// pose → put time.
pub(crate) fn put_force(
    shared: &Shared,
    force: &ForcePublisher,
    slot: u16,
    msg: &protocol::ForceMsg,
    received: Option<Instant>,
    order: u64,
) {
    let i = usize::from(slot);
    let newest = shared.put_begun.get(i).map_or(0, |n| n.fetch_max(order, Ordering::AcqRel));
    if newest >= order {
        return; // superseded: a newer force left first; the recorders' batch still has it
    }
    let _ = force.publisher.put(protocol::encode_force(msg).to_vec()).wait();
    if let Some(n) = shared.put_done.get(i) {
        n.fetch_max(order, Ordering::AcqRel);
    }
    if let Some(t) = received {
        shared.stats.pose_to_put.record(t.elapsed().as_nanos() as u64);
    }
}

/// The model's input from a session's last records (oldest first, at least one): the last
/// `WINDOW_RECORDS`; until that many exist, padded at the front with copies of the first record
/// (`docs/protocol.md`, predict).
fn model_window(records: &VecDeque<[f32; FEATURE_COUNT]>) -> [[f32; FEATURE_COUNT]; WINDOW_RECORDS] {
    let mut window = [[0f32; FEATURE_COUNT]; WINDOW_RECORDS];
    let n = records.len().min(WINDOW_RECORDS);
    let skip = records.len() - n;
    let pad = WINDOW_RECORDS - n;
    for (r, row) in window.iter_mut().enumerate() {
        *row = records[skip + r.saturating_sub(pad)];
    }
    window
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
    /// Not applied: its session ended (or the engine could not take it).
    Gone,
}

/// What one reply held, beyond the predictions applied.
#[derive(Debug, Default, PartialEq)]
struct Tally {
    /// Predictions refused by the decoder (the first ends the reply), for a window the query does
    /// not have, or with another window's `window_seq`.
    errors: u64,
    /// Valid predictions not applied: a second one for a window, or one for a window older than
    /// its session's newest applied.
    ignored: u64,
    /// The model id of the last prediction taken.
    model_id: Option<String>,
}

/// A query's windows and which of them have been answered (a bit per entry).
#[derive(Debug)]
struct Answers {
    asked: Vec<Asked>,
    /// Bit `entry` of each window a valid prediction came for.
    answered: AtomicU64,
    /// Bit `entry` of each window whose prediction was applied.
    applied: AtomicU64,
}

impl Answers {
    fn new(asked: Vec<Asked>) -> Self {
        Answers { asked, answered: AtomicU64::new(0), applied: AtomicU64::new(0) }
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
            match apply(&a, &p) {
                Verdict::Applied => {
                    self.applied.fetch_or(bit, Ordering::AcqRel);
                }
                Verdict::Older => tally.ignored += 1,
                Verdict::Gone => {}
            }
            tally.model_id = Some(p.model_id);
        }
        tally
    }

    /// How the query did, once it has ended: answered when most of its windows' predictions were
    /// applied (a worker that answers the first window of each query alone fails), and how many
    /// windows no valid prediction came for.
    fn outcome(&self) -> (Outcome, u64) {
        let n = self.asked.len() as u64;
        let applied = u64::from(self.applied.load(Ordering::Acquire).count_ones());
        let unanswered = n - u64::from(self.answered.load(Ordering::Acquire).count_ones());
        (if 2 * applied > n { Outcome::Answered } else { Outcome::Failed }, unanswered)
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
    let prefix = format!("{}/model/workers/", shared.prefix);
    session
        .liveliness()
        .declare_subscriber(format!("{prefix}*"))
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

/// Starts the comm thread.
pub(crate) fn spawn(
    session: zenoh::Session,
    shared: Arc<Shared>,
    outputs: Arc<OutputQueue>,
    wait: WaitMode,
) -> SimResult<JoinHandle<()>> {
    follow_workers(&session, &shared)?;
    let querier = session
        .declare_querier(format!("{}/model/predict", shared.prefix))
        // With no worker in the pool: every queryable on the shared key gets every query (the
        // first valid prediction for each window is applied, the rest are counted as ignored);
        // with BestMatching, Zenoh would pick one per query, and a stalled one would get a share
        // to itself.
        .target(QueryTarget::All)
        .consolidation(ConsolidationMode::None)
        .timeout(Duration::from_secs_f64(shared.config.model_timeout_s))
        .wait()
        .map_err(|e| SimError::Transport(format!("cannot declare the model querier: {e}")))?;
    let slots = lock(&shared.registry).slots.len();
    let mut comm = Comm { session, shared, outlets: (0..slots).map(|_| None).collect(), querier, burst: Burst::new() };
    thread::Builder::new()
        .name("dhg-comm".into())
        .spawn(move || comm.run(&outputs, wait))
        .map_err(|e| SimError::Engine(format!("cannot start the comm thread: {e}")))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::protocol::ForceMsg;

    fn force(slot: u16) -> Output {
        Output::Force {
            slot,
            generation: 1,
            msg: ForceMsg::default(),
            pose: None,
            received: None,
            order: 1,
            published: false,
        }
    }

    fn other(slot: u16) -> Output {
        Output::Snapshot { slot, generation: 1 }
    }

    fn name(out: &Output) -> String {
        match out {
            Output::Force { slot, .. } => format!("F{slot}"),
            Output::Snapshot { slot, .. } => format!("S{slot}"),
            _ => "?".into(),
        }
    }

    fn record(k: usize) -> [f32; FEATURE_COUNT] {
        [k as f32; FEATURE_COUNT]
    }

    /// Waits up to 10 s for `done`.
    fn wait_for(what: &str, done: impl Fn() -> bool) {
        let deadline = Instant::now() + Duration::from_secs(10);
        while !done() {
            assert!(Instant::now() < deadline, "waited 10 s for {what}");
            thread::sleep(Duration::from_millis(5));
        }
    }

    #[test]
    fn a_view_stream_is_watched_only_while_another_session_subscribes_to_it() {
        let port = std::net::TcpListener::bind("127.0.0.1:0").unwrap().local_addr().unwrap().port();
        let open = |side: &str| {
            let conf = format!(
                r#"{{"mode": "peer", "{side}": {{"endpoints": ["tcp/127.0.0.1:{port}"]}}, "scouting": {{"multicast": {{"enabled": false}}, "gossip": {{"enabled": false}}}}}}"#
            );
            zenoh::open(zenoh::Config::from_json5(&conf).unwrap()).wait().unwrap()
        };
        let server = open("listen");
        // The engine's own catch-all subscriber (`control::declare`) is no screen.
        server
            .declare_subscriber("t/**")
            .allowed_origin(Locality::Remote)
            .callback(|_| {})
            .background()
            .wait()
            .unwrap();
        let view = ViewStream::declare(&server, "t/session/a/view/force".into(), encoding("force")).unwrap();
        assert!(!view.watched(), "watched with no screen");
        let screen = open("connect");
        for _ in 0..2 {
            let sub = screen.declare_subscriber("t/session/*/view/**").callback(|_| {}).wait().unwrap();
            wait_for("the screen to be seen", || view.watched());
            sub.undeclare().wait().unwrap();
            wait_for("the screen's leaving to be seen", || !view.watched());
        }
    }

    #[test]
    fn the_model_window_is_the_last_records_padded_at_the_front_with_the_first() {
        let first: Vec<f32> = model_window(&VecDeque::from([record(7)])).iter().map(|r| r[0]).collect();
        assert_eq!(first, vec![7.0; WINDOW_RECORDS]);
        let three: VecDeque<_> = (1..=3).map(record).collect();
        let w = model_window(&three);
        let col: Vec<f32> = w.iter().map(|r| r[0]).collect();
        let mut expected = vec![1.0; WINDOW_RECORDS - 3];
        expected.extend([1.0, 2.0, 3.0]);
        assert_eq!(col, expected);
        let full: VecDeque<_> = (1..=WINDOW_RECORDS + 5).map(record).collect();
        let col: Vec<f32> = model_window(&full).iter().map(|r| r[8]).collect();
        let expected: Vec<f32> = (6..=WINDOW_RECORDS + 5).map(|k| k as f32).collect();
        assert_eq!(col, expected, "the newest WINDOW_RECORDS, oldest first");
    }

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
        // A second reply: entry 0 again (ignored), entry 1 with entry 2's window_seq and an entry
        // the query does not have (errors), then entry 1 itself.
        let second =
            [prediction(0, 10, 9.0), prediction(1, 30, 9.0), prediction(3, 20, 9.0), prediction(1, 20, 2.0)].concat();
        let t = answers.take(&second, &mut apply);
        assert_eq!((t.errors, t.ignored), (2, 1));
        assert_eq!(got, [(7, 3.0), (3, 1.0), (5, 2.0)], "each session got its own window's prediction, once");
        assert_eq!(answers.outcome(), (Outcome::Answered, 0));
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

    #[test]
    fn forces_go_out_before_other_outputs_even_those_that_arrive_meanwhile() {
        let queue = OutputQueue::new(16);
        for out in [other(0), force(1), other(2), force(3)] {
            queue.push(out).unwrap();
        }
        let mut later = VecDeque::new();
        let mut order = Vec::new();
        drain_forces_first(&queue, &mut later, |out| {
            // While the first slow output is handled, a tick emits another force.
            if matches!(out, Output::Snapshot { slot: 0, .. }) {
                queue.push(force(4)).unwrap();
            }
            order.push(name(&out));
        });
        assert_eq!(order, ["F1", "F3", "S0", "F4", "S2"]);
        assert!(later.is_empty() && queue.is_empty());
    }
}
