//! A session's outlet on the comm thread: its publishers (force, the recorded state, guidance and
//! tick batches, the screens' view streams) and its window of records for the model.

use std::collections::VecDeque;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

use zenoh::bytes::Encoding;
use zenoh::qos::{CongestionControl, Priority};
use zenoh::sample::Locality;
use zenoh::Wait;
use zenoh_ext::{AdvancedPublisher, AdvancedPublisherBuilderExt, CacheConfig, MissDetectionConfig};

use super::encoding;
use super::registry::ForcePublisher;
use crate::protocol::{self, TickBatch, WINDOW_RECORDS};
use crate::record::{FEATURE_COUNT, RECORD_PERIOD_TICKS};
use crate::session::Pose;

/// Most messages a second on a session's view streams (`view/force`, `view/pose`): what a screen
/// draws the drill from, instead of taking in the two 1 kHz streams and dropping most of them (a
/// viewer's CPU fell fourfold without them, `docs/benchmarks.md`, the live view). The comm thread
/// wakes at least every [`IDLE_WAKE`](super::comm::IDLE_WAKE) (20 ms), so they leave 50–60 times a second.
const VIEW_HZ: f64 = 60.0;

/// Samples of each recorded stream (state, guidance) a session's publisher keeps for recorders
/// to recover: 60 s of the 10 Hz streams.
const RECORDED_HISTORY: usize = 600;
/// Batches of the recorders' 1 kHz stream (`ticks`, 10 a second) a session's publisher keeps:
/// 10 s, about 0.9 MB a session.
const TICKS_HISTORY: usize = 100;
/// Ticks in one batch: one record period, so a batch leaves at 10 Hz.
const TICKS_PER_BATCH: usize = RECORD_PERIOD_TICKS as usize;
/// A partial batch whose first tick is older than this (a silent or ended session's) leaves at the
/// comm thread's next wake-up (at most [`IDLE_WAKE`](super::comm::IDLE_WAKE) later): a full one
/// takes 100 ms at 1 kHz.
const BATCH_MAX_AGE: Duration = Duration::from_millis(200);
/// How often a recorded stream's publisher announces its last sequence number, so that a
/// recorder notices a lost last sample too.
const RECORDED_HEARTBEAT: Duration = Duration::from_millis(500);

/// A session's publishers and model window.
pub(super) struct Outlet {
    generation: u32,
    force: Arc<ForcePublisher>,
    guidance: AdvancedPublisher<'static>,
    state: AdvancedPublisher<'static>,
    ticks: AdvancedPublisher<'static>,
    /// The ticks since the last batch was published, and when its first arrived.
    batch: TickBatch,
    batch_since: Instant,
    /// The model's window of the session's records, and the client time of the pose its last
    /// force used.
    window: ModelWindow,
    pose_time_ns: u64,
    /// The screens' streams (`view/force`, `view/pose`): the newest force and pose at most
    /// [`VIEW_HZ`] times a second.
    view_force: ViewStream,
    view_pose: ViewStream,
    /// The newest force and the pose it used, not yet on the view streams.
    view: Option<(protocol::ForceMsg, Option<Pose>)>,
    view_sent: Instant,
}

impl Outlet {
    /// Declares a session's force publisher (`key`: its `force` key): express, at real-time
    /// priority, dropped rather than queued. The comm thread declares it before the outlet
    /// and hands it to the registry at once: from then on the session's poses put their own
    /// forces, while the outlet's other publishers are declared.
    pub(super) fn declare_force(session: &zenoh::Session, key: String, generation: u32) -> Option<Arc<ForcePublisher>> {
        let publisher = session
            .declare_publisher(key)
            .encoding(encoding("force"))
            .congestion_control(CongestionControl::Drop)
            .priority(Priority::RealTime)
            .express(true)
            .wait()
            .ok()?;
        Some(Arc::new(ForcePublisher { generation, publisher }))
    }

    /// Declares a session's publishers but the force's (`key` gives a leaf's key): the recorded
    /// streams and the screens' copies. `None` if Zenoh refuses one.
    pub(super) fn declare(
        session: &zenoh::Session,
        key: impl Fn(&str) -> String,
        generation: u32,
        force: Arc<ForcePublisher>,
    ) -> Option<Self> {
        // State and guidance are recorded for datasets, but a slow or frozen subscriber must
        // never hold up the comm thread (and with it every session's forces): they drop
        // rather than block, and keep the last RECORDED_HISTORY samples for recorders to
        // recover what they missed (zenoh-ext advanced publisher: cache, sample-miss
        // detection with a heartbeat, publisher detection).
        let recorded = |leaf: &str, history: usize| {
            session
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
        let view = |leaf: &str| ViewStream::declare(session, key(leaf), encoding(leaf.trim_start_matches("view/")));
        Some(Outlet {
            generation,
            force,
            guidance: recorded("guidance", RECORDED_HISTORY)?,
            state: recorded("state", RECORDED_HISTORY)?,
            ticks: recorded("ticks", TICKS_HISTORY)?,
            batch: TickBatch::with_capacity(TICKS_PER_BATCH),
            batch_since: Instant::now(),
            window: ModelWindow::default(),
            pose_time_ns: 0,
            view_force: view("view/force")?,
            view_pose: view("view/pose")?,
            view: None,
            view_sent: Instant::now(),
        })
    }

    /// The session generation whose outlet this is.
    pub(super) fn generation(&self) -> u32 {
        self.generation
    }

    /// The session's force publisher (a pose's thread puts with it too).
    pub(super) fn force(&self) -> &ForcePublisher {
        &self.force
    }

    /// Takes a tick's force (and the pose it used): into the recorders' batch, and the newest for
    /// the view streams.
    pub(super) fn add_force(&mut self, msg: protocol::ForceMsg, pose: Option<Pose>) {
        self.pose_time_ns = msg.pose_client_time_ns;
        self.add_tick(&msg, pose.as_ref());
        self.view = Some((msg, pose));
    }

    /// Publishes a 10 Hz state and adds its record to the model window (see [`ModelWindow`]).
    /// Returns what the model is asked and the client time of the pose the session's last force
    /// used.
    pub(super) fn add_state(
        &mut self,
        msg: &protocol::StateMsg,
        attempt: u32,
        features: [f32; FEATURE_COUNT],
    ) -> (Windowed, u64) {
        let _ = self.state.put(protocol::encode_state(msg).to_vec()).wait();
        (self.window.push(attempt, features), self.pose_time_ns)
    }

    /// Publishes a 10 Hz guidance message.
    pub(super) fn publish_guidance(&mut self, msg: &protocol::GuidanceMsg) {
        let _ = self.guidance.put(protocol::encode_guidance(msg).to_vec()).wait();
    }

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
    pub(super) fn publish_view(&mut self, now: Instant) {
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
    pub(super) fn publish_ticks(&mut self) {
        if !self.batch.is_empty() {
            let _ = self.ticks.put(self.batch.take()).wait();
        }
    }

    /// Publishes the batch of ticks if its first is older than [`BATCH_MAX_AGE`] at `now` (a
    /// silent or ended session's).
    pub(super) fn publish_stale_ticks(&mut self, now: Instant) {
        if !self.batch.is_empty() && now.saturating_duration_since(self.batch_since) >= BATCH_MAX_AGE {
            self.publish_ticks();
        }
    }
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
    /// unknown keys, would otherwise always match it). `None` if Zenoh refuses the publisher.
    fn declare(session: &zenoh::Session, key: String, encoding: Encoding) -> Option<Self> {
        let publisher = session
            .declare_publisher(key)
            .encoding(encoding)
            .congestion_control(CongestionControl::Drop)
            .priority(Priority::DataLow)
            .allowed_destination(Locality::Remote)
            .wait()
            .ok()?;
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
        Some(Self { publisher, watched })
    }

    fn watched(&self) -> bool {
        self.watched.load(Ordering::Relaxed)
    }
}

/// The records of a session's current attempt that the model is asked about: the newest
/// [`WINDOW_RECORDS`], numbered across attempts. A window never reaches back into the attempt
/// before a reset, as no training window straddles two episodes and the offline studies pad each
/// attempt's first windows with its own first record (`dhg.operators.episodes.drill_episode`).
#[derive(Debug, Default)]
pub(super) struct ModelWindow {
    records: VecDeque<[f32; FEATURE_COUNT]>,
    /// The newest window's number (per session, wrapping; never restarts, so replies can be told
    /// apart across attempts).
    seq: u32,
    /// The attempt of the newest record (`None`: none yet).
    attempt: Option<u32>,
}

/// A window for the model (see [`ModelWindow::push`]).
#[derive(Debug, Clone, Copy)]
pub(super) struct Windowed {
    /// The records, oldest first (see [`model_window`]).
    pub window: [[f32; FEATURE_COUNT]; WINDOW_RECORDS],
    /// Its number.
    pub seq: u32,
}

impl ModelWindow {
    /// Adds a record of `attempt` (the engine's count of the session's attempts); a new
    /// attempt's first record starts the window afresh. Returns the window to ask about.
    pub(super) fn push(&mut self, attempt: u32, features: [f32; FEATURE_COUNT]) -> Windowed {
        if self.attempt != Some(attempt) {
            self.records.clear();
            self.attempt = Some(attempt);
        }
        if self.records.len() == WINDOW_RECORDS {
            self.records.pop_front();
        }
        self.records.push_back(features);
        self.seq = self.seq.wrapping_add(1);
        Windowed { window: model_window(&self.records), seq: self.seq }
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

#[cfg(test)]
mod tests {
    use std::thread;

    use super::*;

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

    /// Opens Zenoh peers on one free loopback port: `open("listen")`, then `open("connect")`.
    fn peers() -> impl Fn(&str) -> zenoh::Session {
        let port = std::net::TcpListener::bind("127.0.0.1:0").unwrap().local_addr().unwrap().port();
        move |side: &str| {
            let conf = format!(
                r#"{{"mode": "peer", "{side}": {{"endpoints": ["tcp/127.0.0.1:{port}"]}}, "scouting": {{"multicast": {{"enabled": false}}, "gossip": {{"enabled": false}}}}}}"#
            );
            zenoh::open(zenoh::Config::from_json5(&conf).unwrap()).wait().unwrap()
        }
    }

    #[test]
    fn a_view_stream_is_watched_only_while_another_session_subscribes_to_it() {
        let open = peers();
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
    fn a_partial_batch_of_ticks_leaves_once_its_first_tick_is_older_than_its_maximum_age() {
        let open = peers();
        let server = open("listen");
        let recorder = open("connect");
        let batches = Arc::new(std::sync::Mutex::new(Vec::<Vec<u64>>::new()));
        let got = batches.clone();
        let _sub = recorder
            .declare_subscriber("t/session/a/ticks")
            .callback(move |s| {
                let rows = protocol::decode_ticks(&s.payload().to_bytes()).unwrap();
                got.lock().unwrap().push(rows.iter().map(|r| r.tick).collect());
            })
            .wait()
            .unwrap();
        let key = |leaf: &str| format!("t/session/a/{leaf}");
        let force = Outlet::declare_force(&server, key("force"), 1).unwrap();
        let mut outlet = Outlet::declare(&server, key, 1, force).unwrap();
        wait_for("the recorder to be connected", || outlet.ticks.matching_status().wait().is_ok_and(|m| m.matching()));
        // A session that ticked 30 times and went silent: its batch is not full.
        for tick in 1..=30 {
            outlet.add_force(protocol::ForceMsg { tick, ..Default::default() }, None);
        }
        let first = outlet.batch_since;
        outlet.publish_stale_ticks(first + BATCH_MAX_AGE / 2);
        assert_eq!(outlet.batch.len(), 30, "a batch younger than its maximum age waits for more ticks");
        outlet.publish_stale_ticks(first + BATCH_MAX_AGE);
        assert!(outlet.batch.is_empty(), "a batch as old as its maximum age leaves");
        wait_for("the partial batch to arrive", || !batches.lock().unwrap().is_empty());
        // Nothing left: no empty batch leaves after it.
        outlet.publish_stale_ticks(first + 10 * BATCH_MAX_AGE);
        for tick in 31..=(30 + TICKS_PER_BATCH as u64) {
            outlet.add_force(protocol::ForceMsg { tick, ..Default::default() }, None);
        }
        wait_for("the next, full batch", || batches.lock().unwrap().len() == 2);
        let got = batches.lock().unwrap().clone();
        assert_eq!(got[0], (1..=30).collect::<Vec<u64>>());
        assert_eq!(got[1], (31..=(30 + TICKS_PER_BATCH as u64)).collect::<Vec<u64>>(), "a full batch leaves at once");
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

    #[test]
    fn a_reset_starts_the_model_window_afresh_and_its_numbers_go_on() {
        let mut w = ModelWindow::default();
        let first = w.push(1, record(1));
        assert_eq!((first.seq, first.window), (1, [record(1); WINDOW_RECORDS]));
        for k in 2..=30 {
            let got = w.push(1, record(k));
            assert_eq!((got.seq, got.window[WINDOW_RECORDS - 1]), (k as u32, record(k)));
        }
        // A reset: the next attempt's first record, alone in the window.
        let after = w.push(2, record(100));
        assert_eq!(after.seq, 31, "window numbers never restart");
        assert_eq!(after.window, [record(100); WINDOW_RECORDS], "no record of the attempt before");
        let next = w.push(2, record(101));
        let col: Vec<f32> = next.window.iter().map(|r| r[0]).collect();
        let mut expected = vec![100.0; WINDOW_RECORDS - 1];
        expected.push(101.0);
        assert_eq!(col, expected);
        // Another reset whose first record was lost on the way: its second starts afresh.
        let lost_first = w.push(3, record(300));
        assert_eq!(lost_first.window, [record(300); WINDOW_RECORDS]);
    }
}
