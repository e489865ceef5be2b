//! The engine on Zenoh: its own Zenoh session, subscribers and queryables whose callbacks hand
//! data to the tick thread through the lock-free [`crate::engine::handoff`]
//! structures, and a comm thread (`comm`) that owns each session's publishers (`outlet`), sends the
//! model queries (`model_query`) and keeps the health report's per-second history (`history`).
//!
//! Key expressions (under a configurable prefix, `dhg` by default; payloads in
//! `docs/protocol.md`):
//! - `<prefix>/session/<id>/pose`: stylus poses in (a session is created by its first pose);
//! - `<prefix>/session/<id>/force`, `/guidance`, `/state`: out, at 1 kHz, 10 Hz, 10 Hz;
//! - `<prefix>/session/<id>/control`, `/metrics`: JSON queryables;
//! - `<prefix>/server/health`: JSON queryable;
//! - `<prefix>/model/workers/<id>` (liveliness) and `<prefix>/model/workers/<id>/predict`: the
//!   model workers' pool, one worker queried per window ([`pool`]); `<prefix>/model/predict`: the
//!   shared key, queried when the pool is empty.

mod comm;
mod control;
mod history;
pub mod metrics;
mod model_query;
mod outlet;
mod pool;
pub mod registry;
pub mod replies;
pub mod routes;

use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex, MutexGuard, OnceLock};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use serde::{Deserialize, Serialize};
use serde_json::Value;
use zenoh::Wait;

use crate::engine::handoff::Command;
use crate::engine::stats::TickStats;
use crate::engine::{self, EngineConfig, PoseTicker, Snapshot, TickOn, TickThread, WaitMode};
use crate::error::{SimError, SimResult};
use crate::guidance::{GuidanceMode, GuidanceParams};
use crate::path::PlannedPath;
use crate::session::SessionConfig;
use crate::volume::drilled::DrilledVolume;
use crate::volume::Volume;
use registry::Registry;

/// Each control operation with the fields it takes, in the order of `docs/protocol.md`.
#[must_use]
pub fn control_fields() -> Vec<(String, Vec<String>)> {
    control::ControlRequest::fields()
}

/// Seconds without poses or control requests after which a session is freed, by default.
pub const DEFAULT_IDLE_TIMEOUT_S: f64 = 5.0;
/// Timeout of one model query (s), by default: 2.5 windows of the 10 Hz stream.
pub const DEFAULT_MODEL_TIMEOUT_S: f64 = 0.25;
/// The longest model-query timeout a server takes (s): an answer that old guides nothing (the
/// guidance is 10 Hz), and Zenoh's timeout is a `Duration` (1e20 s does not fit one).
pub const MAX_MODEL_TIMEOUT_S: f64 = 10.0;

/// What `dhg-serve` sets, with the defaults: the one definition (`dhg.core.server.ServerSettings` reads
/// its fields and defaults from here, through `dhg._bone_sim.defaults()`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct ServerSettings {
    /// Session slots, allocated at start.
    pub max_sessions: usize,
    /// A session without poses or control requests for this long is freed (s).
    pub idle_timeout_s: f64,
    /// Timeout of one model query (s).
    pub model_timeout_s: f64,
    /// Guidance mode of a new session.
    pub guidance_mode: GuidanceMode,
    /// Guidance gain of a new session (0: computed and published, not rendered).
    pub guidance_gain: f64,
    /// Largest paper-cue and corridor share of the rendered force (N).
    pub guidance_max_n: f64,
    /// Fastest change of the guidance share (N/s).
    pub guidance_max_rate_n_per_s: f64,
    /// A model answer older than this is dropped and guidance fades out (s).
    pub guidance_timeout_s: f64,
    /// The corridor's stiffness along A→B: (bin width (m), stiffness per bin (N/m)); none: fixed.
    pub corridor_profile: Option<(f64, Vec<f64>)>,
    /// Stations whose sessions (`S` or `S-<anything>`) are capped at `max_sessions_per_owner`.
    pub session_owners: Vec<String>,
    /// Most sessions one station may hold at once (0: no cap).
    pub max_sessions_per_owner: usize,
    /// How the tick and comm threads wait.
    pub wait: WaitMode,
    /// Where a pose ticks its session: on the thread that received it (`pose`), or handed to the
    /// tick thread (`thread`, the design before, for comparison).
    pub tick_on: TickOn,
}

impl Default for ServerSettings {
    fn default() -> Self {
        let g = GuidanceParams::default();
        Self {
            max_sessions: engine::DEFAULT_MAX_SESSIONS,
            idle_timeout_s: DEFAULT_IDLE_TIMEOUT_S,
            model_timeout_s: DEFAULT_MODEL_TIMEOUT_S,
            guidance_mode: GuidanceMode::default(),
            guidance_gain: 1.0,
            guidance_max_n: g.max_n,
            guidance_max_rate_n_per_s: g.max_rate_n_per_s,
            guidance_timeout_s: g.timeout_s,
            corridor_profile: None,
            session_owners: Vec::new(),
            max_sessions_per_owner: 0,
            wait: WaitMode::default(),
            tick_on: TickOn::default(),
        }
    }
}

impl ServerSettings {
    /// The engine's and the transport's configurations: sessions of `session` on the default
    /// path `path`, keys under `prefix`, Zenoh configured by `zenoh_json5`.
    ///
    /// # Errors
    /// An invalid guidance setting (the rest is checked as the server starts).
    pub fn configs(
        &self,
        path: PlannedPath,
        session: SessionConfig,
        prefix: &str,
        zenoh_json5: String,
    ) -> SimResult<(EngineConfig, ServerConfig)> {
        let mut engine = EngineConfig::new(path);
        engine.max_sessions = self.max_sessions;
        engine.session = session;
        engine.default_mode = self.guidance_mode;
        engine.default_gain = self.guidance_gain;
        engine.wait = self.wait;
        engine.guidance.max_n = self.guidance_max_n;
        engine.guidance.max_rate_n_per_s = self.guidance_max_rate_n_per_s;
        engine.guidance.timeout_s = self.guidance_timeout_s;
        if let Some((bin_m, stiffness)) = &self.corridor_profile {
            engine.guidance.corridor_profile_bin_m = *bin_m;
            engine.guidance.corridor_profile_n_per_m.clone_from(stiffness);
        }
        engine.guidance.validate()?;
        let server = ServerConfig {
            prefix: prefix.to_owned(),
            idle_timeout_s: self.idle_timeout_s,
            model_timeout_s: self.model_timeout_s,
            zenoh_json5,
            owners: registry::Owners { names: self.session_owners.clone(), max_sessions: self.max_sessions_per_owner },
            tick_on: self.tick_on,
        };
        Ok((engine, server))
    }
}

/// Server settings beyond the engine's.
#[derive(Debug, Clone)]
pub struct ServerConfig {
    /// Key prefix (one or more key segments, no wildcards).
    pub prefix: String,
    /// Seconds without poses or control requests after which a session is freed.
    pub idle_timeout_s: f64,
    /// Timeout of one model query (s).
    pub model_timeout_s: f64,
    /// Zenoh configuration (JSON5).
    pub zenoh_json5: String,
    /// Session owners (stations) and how many sessions each may hold.
    pub owners: registry::Owners,
    /// Where a pose ticks its session.
    pub tick_on: TickOn,
}

impl ServerConfig {
    /// Checks every field.
    ///
    /// # Errors
    /// A bad prefix or a non-positive timeout.
    pub fn validate(&self) -> SimResult<()> {
        let ok = !self.prefix.is_empty()
            && self.prefix.split('/').all(|seg| !seg.is_empty() && registry::check_id(seg).is_ok());
        if !ok {
            return Err(SimError::InvalidOption {
                name: "prefix",
                value: self.prefix.clone(),
                allowed: "key segments of A-Z a-z 0-9 _ - . joined by '/'",
            });
        }
        crate::error::positive("idle_timeout_s", self.idle_timeout_s)?;
        crate::error::positive("model_timeout_s", self.model_timeout_s)?;
        if self.model_timeout_s > MAX_MODEL_TIMEOUT_S {
            return Err(SimError::InvalidParameter {
                name: "model_timeout_s",
                value: self.model_timeout_s,
                reason: "must be at most MAX_MODEL_TIMEOUT_S (10 s): a later answer guides nothing",
            });
        }
        Ok(())
    }
}

/// Name prefixes of Zenoh's I/O threads (zenoh-runtime names its workers `<runtime>-<n>`):
/// receive (the pose subscriber runs on them) and transmit (they write the forces to the sockets).
///
/// Why this value: `docs/decisions/0004-short-time-slices.md`.
pub const ZENOH_IO_THREADS: [&str; 2] = ["rx-", "tx-"];

/// Counts of refused input, by reason.
#[derive(Debug, Default)]
pub struct Counters {
    /// Poses accepted.
    pub poses: AtomicU64,
    /// Payloads of the wrong size.
    pub wrong_size: AtomicU64,
    /// Payloads of another kind or version.
    pub wrong_version: AtomicU64,
    /// Payloads with NaN/infinite values.
    pub non_finite: AtomicU64,
    /// Payloads over the size limit.
    pub oversized: AtomicU64,
    /// Puts on keys the server does not serve.
    pub unknown_key: AtomicU64,
    /// Sessions refused because every slot was taken (or the id was bad).
    pub sessions_refused: AtomicU64,
    /// Poses dropped because another pose of their session was being handed on at that instant.
    pub poses_concurrent: AtomicU64,
    /// Poses of a session that closed while they were handed on.
    pub poses_ended: AtomicU64,
    /// Windows sent to the model.
    pub model_queries: AtomicU64,
    /// Model queries sent (each holds one or more windows).
    pub model_bursts: AtomicU64,
    /// Predictions applied.
    pub model_replies: AtomicU64,
    /// Error replies, replies too long to read, and predictions refused or matching no window.
    pub model_errors: AtomicU64,
    /// Valid predictions ignored: a second (or later) one for a window, or one for a window older
    /// than its session's newest applied (a late or rogue worker).
    pub model_ignored: AtomicU64,
    /// Windows whose query ended without a valid prediction for them.
    pub model_unanswered: AtomicU64,
    /// Valid predictions the engine's full command queue could not take.
    pub model_dropped: AtomicU64,
    /// Whether the comm thread got the short EEVDF slice (`engine::realtime`); 0 = no, 1 = yes.
    pub comm_short_slice: AtomicU64,
    /// Zenoh I/O threads on the short slice.
    pub io_short_slices: AtomicU64,
}

/// Model-service statistics (comm side).
#[derive(Debug, Default)]
pub struct ModelStats {
    /// When the last good reply arrived.
    pub last_reply: Option<Instant>,
    /// Recent round trips (s), newest last.
    pub latencies_s: std::collections::VecDeque<f64>,
    /// Id the model service reported.
    pub model_id: String,
}

/// State shared by the callbacks, the comm thread and the server handle.
#[derive(Debug)]
pub struct Shared {
    pub(crate) prefix: String,
    pub(crate) registry: Mutex<Registry>,
    /// What a pose reads of its session, without the registry's lock (decision 0039).
    pub(crate) routes: Arc<routes::Routes>,
    pub(crate) counters: Counters,
    pub(crate) model: Mutex<ModelStats>,
    /// The model workers whose liveliness tokens are alive.
    pub(crate) pool: Mutex<pool::Pool>,
    pub(crate) stats: Arc<TickStats>,
    pub(crate) history: Mutex<history::History>,
    pub(crate) snapshot: Mutex<triple_buffer::Output<Snapshot>>,
    pub(crate) snapshot_seq: AtomicU64,
    pub(crate) stopping: AtomicBool,
    /// The comm thread, unparked by a pose's thread that queued output for it.
    pub(crate) comm_thread: std::sync::OnceLock<std::thread::Thread>,
    /// Ticks a session on the thread its pose arrived on ([`TickOn::Pose`]).
    pub(crate) ticker: PoseTicker,
    /// Per slot: the order (`Output::Force::order`) of the newest force whose put has begun, so
    /// that an older force, still queued for the comm thread, never follows a newer one out.
    pub(crate) put_begun: Box<[AtomicU64]>,
    /// Per slot: the order of the newest force whose put has ended (or that was let go). A pose's
    /// thread puts its own force only when every force the slot made before is out, so that its
    /// put cannot overtake one still waiting for, or under way on, the comm thread; otherwise its
    /// force queues behind them for the comm thread to put.
    pub(crate) put_done: Box<[AtomicU64]>,
    pub(crate) config: ServerConfig,
    /// How the tick and comm threads wait (for the health report).
    pub(crate) wait: WaitMode,
    pub(crate) started: Instant,
    /// The pristine bone, for the planned layers a session's info reports.
    pub(crate) volume: Arc<Volume>,
}

/// A payload's encoding: bytes, with the layout's name and protocol version as its schema.
pub(crate) fn encoding(name: &str) -> zenoh::bytes::Encoding {
    zenoh::bytes::Encoding::APPLICATION_OCTET_STREAM.with_schema(format!("dhg.{name}.v{}", crate::protocol::VERSION))
}

/// Locks a mutex, recovering the data if a panicking thread poisoned it (every update here keeps
/// the data consistent at each step).
pub(crate) fn lock<T>(m: &Mutex<T>) -> MutexGuard<'_, T> {
    m.lock().unwrap_or_else(std::sync::PoisonError::into_inner)
}

/// Checks Zenoh's runtime setting, the environment variable `ZENOH_RUNTIME` (its threads, for
/// example `(rx: (worker_threads: 1))`; decision 0031), before a session opens. Zenoh reads it once
/// per process, at its first use, and panics on a value it cannot parse, and tokio on a runtime of
/// zero threads; here either is an error naming the variable. The parse runs once (later calls
/// compare the variable with what was parsed). While it runs, the process's panic hook is a silent
/// one, so that Zenoh's message does not reach stderr: a panic elsewhere in that instant, before
/// any session is open, would go unprinted (still raised).
///
/// # Errors
/// [`SimError::InvalidConfig`] when the variable is set and Zenoh cannot read it, asks for zero
/// threads, or has changed since it was read.
pub fn check_zenoh_runtime() -> SimResult<()> {
    static PARSED: OnceLock<(Option<String>, Result<(), String>)> = OnceLock::new();
    let value = std::env::var(zenoh_runtime::ZENOH_RUNTIME_ENV).ok();
    let (parsed_value, outcome) = PARSED.get_or_init(|| (value.clone(), parse_zenoh_runtime()));
    let shown = |v: &Option<String>| v.as_deref().map_or("unset".into(), |v| format!("{v:?}"));
    let refuse = |reason: String| SimError::InvalidConfig {
        what: "ZENOH_RUNTIME (the environment variable of Zenoh's runtime threads)",
        reason: format!("{}: {reason}", shown(&value)),
    };
    if *parsed_value != value {
        let was = shown(parsed_value);
        return Err(refuse(format!("it was {was} when Zenoh read it, once for this process: restart the process")));
    }
    outcome
        .clone()
        .map_err(|reason| refuse(format!("{reason}; unset it, or write it as Zenoh does: (rx: (worker_threads: 1))")))
}

/// Zenoh's own parse of `ZENOH_RUNTIME` (its lazy static), its panic caught; then every runtime's
/// thread counts, which tokio asserts are at least 1 when Zenoh builds the runtime.
fn parse_zenoh_runtime() -> Result<(), String> {
    use std::borrow::Borrow;
    use zenoh_runtime::{RuntimeParam, ZRuntime};
    // Other threads wait in OnceLock::get_or_init meanwhile: the hook is swapped and put back once.
    let hook = std::panic::take_hook();
    std::panic::set_hook(Box::new(|_| {}));
    let parsed = std::panic::catch_unwind(|| {
        let _ = &*zenoh_runtime::ZRUNTIME_PARAM;
    });
    std::panic::set_hook(hook);
    if let Err(panic) = parsed {
        let text = panic
            .downcast_ref::<String>()
            .map(String::as_str)
            .or_else(|| panic.downcast_ref::<&str>().copied())
            .unwrap_or("");
        return Err(ron_reason(text));
    }
    for zrt in ZRuntime::iter() {
        let p: &RuntimeParam = zrt.borrow();
        if p.worker_threads == 0 || p.max_blocking_threads == 0 {
            return Err(format!("the {zrt} runtime needs at least one thread of each kind"));
        }
    }
    Ok(())
}

/// What Zenoh's panic says of its RON parse (`SpannedError { code: ExpectedInteger, span: Span {
/// start: Position { line: 1, col: 22 }, ...`), as "`ExpectedInteger` at line 1, column 22".
fn ron_reason(panic: &str) -> String {
    let between = |after: &str, until: &str| -> Option<&str> {
        let rest = &panic[panic.find(after)? + after.len()..];
        Some(rest[..rest.find(until)?].trim())
    };
    match (between("code: ", ", span: "), between("line: ", ","), between("col: ", " ")) {
        (Some(code), Some(line), Some(col)) => format!("Zenoh cannot read it: {code} at line {line}, column {col}"),
        _ if panic.is_empty() => "Zenoh cannot read it".into(),
        _ => format!(
            "Zenoh cannot read it: {}",
            panic.trim_start_matches("called `Result::unwrap()` on an `Err` value: ")
        ),
    }
}

fn zerr(what: &str) -> impl FnOnce(zenoh::Error) -> SimError + '_ {
    move |e| SimError::Transport(format!("{what}: {e}"))
}

/// A running server: Zenoh session, tick thread and comm thread.
pub struct Server {
    shared: Arc<Shared>,
    session: zenoh::Session,
    tick: TickThread,
    comm: Option<JoinHandle<()>>,
}

impl std::fmt::Debug for Server {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Server").field("prefix", &self.shared.prefix).finish_non_exhaustive()
    }
}

impl Server {
    /// Opens the Zenoh session, declares the keys and starts the threads.
    ///
    /// # Errors
    /// Invalid settings, or Zenoh failing to open (e.g. the listen endpoint is in use).
    pub fn start(volume: &Arc<Volume>, engine_config: &EngineConfig, config: ServerConfig) -> SimResult<Self> {
        config.validate()?;
        let zconfig = zenoh::Config::from_json5(&config.zenoh_json5).map_err(zerr("bad zenoh configuration"))?;
        check_zenoh_runtime()?;
        let (core, link) = engine::build(volume, engine_config)?;
        let session = zenoh::open(zconfig).wait().map_err(zerr("cannot open the zenoh session"))?;
        let registry = Registry::new(
            link.commands,
            link.poses,
            engine_config.default_path.clone(),
            (engine_config.default_mode, engine_config.default_gain),
            engine_config.session.burr_radius_m,
            config.owners.clone(),
        );
        let shared = Arc::new(Shared {
            prefix: config.prefix.clone(),
            routes: registry.routes().clone(),
            registry: Mutex::new(registry),
            counters: Counters::default(),
            model: Mutex::new(ModelStats::default()),
            pool: Mutex::new(pool::Pool::default()),
            stats: link.stats,
            history: Mutex::new(history::History::default()),
            snapshot: Mutex::new(link.snapshot),
            snapshot_seq: AtomicU64::new(0),
            stopping: AtomicBool::new(false),
            comm_thread: std::sync::OnceLock::new(),
            ticker: link.ticker,
            put_begun: (0..engine_config.max_sessions).map(|_| AtomicU64::new(0)).collect(),
            put_done: (0..engine_config.max_sessions).map(|_| AtomicU64::new(0)).collect(),
            config,
            wait: engine_config.wait,
            started: Instant::now(),
            volume: volume.clone(),
        });
        control::declare(&session, &shared)?;
        let comm = comm::spawn(session.clone(), shared.clone(), link.outputs, engine_config.wait)?;
        let _ = shared.comm_thread.set(comm.thread().clone());
        let realtime = shared.config.tick_on == TickOn::Thread; // see TickThread::spawn
        let tick = TickThread::spawn(core, Some(comm.thread().clone()), engine_config.wait, realtime)?;
        Ok(Self { shared, session, tick, comm: Some(comm) })
    }

    /// Server health (the `health` queryable's reply, `docs/protocol.md`), with tick quantiles
    /// over the last `window_s` seconds.
    #[must_use]
    pub fn health(&self, window_s: f64) -> replies::HealthReply {
        control::health(&self.shared, window_s)
    }

    /// Ids of the open sessions.
    #[must_use]
    pub fn sessions(&self) -> Vec<String> {
        let mut ids: Vec<String> = lock(&self.shared.registry).by_id.keys().cloned().collect();
        ids.sort();
        ids
    }

    /// A session's metrics (the `metrics` queryable's reply).
    ///
    /// # Errors
    /// Unknown session.
    pub fn metrics(&self, id: &str) -> SimResult<replies::MetricsReply> {
        control::metrics(&self.shared, id)
    }

    /// Applies a control request (the JSON the control queryable takes) to a session.
    ///
    /// # Errors
    /// A bad request or unknown session.
    pub fn control(&self, id: &str, request: &Value) -> SimResult<Value> {
        control::apply(&self.shared, id, request)
    }

    /// A copy of a session's bone as drilled now (taken by the tick thread between two ticks).
    ///
    /// # Errors
    /// Unknown session, or no snapshot within `timeout`.
    pub fn snapshot(&self, id: &str, timeout: Duration) -> SimResult<DrilledVolume> {
        let mut out = lock(&self.shared.snapshot);
        let before = self.shared.snapshot_seq.load(Ordering::Acquire);
        let (slot, generation) = {
            let mut reg = lock(&self.shared.registry);
            let slot = reg.slot_of(id).ok_or_else(|| SimError::Engine(format!("no session {id:?}")))?;
            reg.send(Command::Snapshot { slot })?;
            (slot, reg.slots[slot as usize].generation)
        };
        let t0 = Instant::now();
        while self.shared.snapshot_seq.load(Ordering::Acquire) == before {
            if t0.elapsed() > timeout {
                return Err(SimError::Engine(format!("no snapshot of session {id:?} within {timeout:?}")));
            }
            std::thread::sleep(Duration::from_micros(500));
        }
        let snap = out.read();
        if snap.slot != slot || snap.generation != generation {
            return Err(SimError::Engine(format!("session {id:?} ended while its snapshot was taken")));
        }
        Ok(snap.bone.clone())
    }

    /// Stops the threads and closes the Zenoh session (idempotent).
    pub fn stop(&mut self) {
        self.shared.stopping.store(true, Ordering::Release);
        self.tick.stop();
        if let Some(h) = self.comm.take() {
            h.thread().unpark();
            let _ = h.join();
        }
        let _ = self.session.close().wait();
    }
}

impl Drop for Server {
    fn drop(&mut self) {
        self.stop();
    }
}

#[cfg(test)]
mod tests {
    use std::sync::atomic::AtomicU32;
    use std::thread;

    use nalgebra::{Point3, UnitQuaternion};

    use super::*;
    use crate::protocol::{self, PoseMsg, FORCE};
    use crate::session::Pose;
    use crate::volume::{layer::Layer, test_support::uniform_block};

    /// No force of an open session waits on the registry's lock (decision 0039): while another
    /// thread holds it, as the control, metrics and health queries and the model's replies do,
    /// the server takes the session's poses (handed to the engine and counted) and its forces go
    /// on, also those of ticks without a pose, which leave from the comm thread while it waits
    /// for the registry at each 10 Hz state.
    #[test]
    fn an_open_sessions_poses_and_forces_go_on_while_the_registry_is_held() {
        const MS: Duration = Duration::from_millis(1);
        let port = std::net::TcpListener::bind("127.0.0.1:0").unwrap().local_addr().unwrap().port();
        let conf = |mode: &str, side: &str| {
            format!(
                r#"{{"mode": "{mode}", "{side}": {{"endpoints": ["tcp/127.0.0.1:{port}"]}}, "scouting": {{"multicast": {{"enabled": false}}, "gossip": {{"enabled": false}}}}}}"#
            )
        };
        let vol = Arc::new(uniform_block(24, 0.5e-3, Layer::Cortical, 1500.0, 4));
        let path = PlannedPath::new(Point3::new(6e-3, 6e-3, 1e-3), Point3::new(6e-3, 6e-3, 10e-3)).unwrap();
        let mut engine = EngineConfig::new(path);
        (engine.max_sessions, engine.reserve_bricks) = (2, 64);
        let config = ServerConfig {
            prefix: "t".into(),
            idle_timeout_s: 60.0,
            model_timeout_s: DEFAULT_MODEL_TIMEOUT_S,
            zenoh_json5: conf("router", "listen"),
            owners: registry::Owners::default(),
            tick_on: TickOn::Pose,
        };
        let mut server = Server::start(&vol, &engine, config).unwrap();
        let client = zenoh::open(zenoh::Config::from_json5(&conf("client", "connect")).unwrap()).wait().unwrap();
        // The newest pose whose force came back (the force's `pose_seq`).
        let answered = Arc::new(AtomicU32::new(0));
        let seen = answered.clone();
        let at = FORCE.fields.iter().find(|f| f.name == "pose_seq").unwrap().offset;
        let _forces = client
            .declare_subscriber("t/session/a/force")
            .callback(move |s| {
                let b = s.payload().to_bytes();
                seen.fetch_max(u32::from_le_bytes(b[at..at + 4].try_into().unwrap()), Ordering::AcqRel);
            })
            .wait()
            .unwrap();
        let poses = client.declare_publisher("t/session/a/pose").wait().unwrap();
        let pose = Pose {
            position_m: Point3::new(6e-3, 6e-3, 0.0), // in the air above the block
            orientation: UnitQuaternion::identity(),
            drill_on: false,
            spindle_rpm: 0.0,
        };
        let mut seq = 0u32;
        // Sends poses `gap` apart until `done`, for at most 10 s.
        let mut stream_until = |what: &str, gap: Duration, done: &dyn Fn() -> bool| {
            let deadline = Instant::now() + Duration::from_secs(10);
            while !done() {
                assert!(Instant::now() < deadline, "waited 10 s for {what}");
                seq += 1;
                let msg = PoseMsg { seq, client_time_ns: u64::from(seq) * 1_000_000, pose };
                poses.put(protocol::encode_pose(&msg).to_vec()).wait().unwrap();
                thread::sleep(gap);
            }
            seq
        };
        // The first pose opens the session (under the registry's lock); then its forces flow.
        stream_until("the session's first forces", MS, &|| answered.load(Ordering::Acquire) > 0);
        let taken = || server.shared.counters.poses.load(Ordering::Acquire);
        let before = taken();
        let held = lock(&server.shared.registry);
        stream_until("20 poses taken while the registry is held", MS, &|| taken() >= before + 20);
        // Now 5 ms between poses: the ticks between them run without a pose, and their forces
        // leave from the comm thread, which meets the held registry at each 10 Hz state. It puts
        // the forces that come while it waits, so the session's forces go on (60 poses: 0.3 s).
        let from = stream_until("", MS, &|| true);
        stream_until("forces of gappy poses while the registry is held", 5 * MS, &|| {
            answered.load(Ordering::Acquire) >= from + 60
        });
        drop(held);
        let last = stream_until("", MS, &|| true);
        stream_until("the forces after the hold", MS, &|| answered.load(Ordering::Acquire) >= last);
        server.stop();
    }
}
