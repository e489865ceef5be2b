//! The JSON replies of the `control`, `metrics` and `health` queryables and the error reply of
//! all three, as types: serde writes them, and their JSON schemas (schemars) are what
//! `docs/protocol.md` is checked against and what a client in another language may validate
//! with ([`schemas`]).

use schemars::JsonSchema;
use serde::Serialize;
use serde_json::Value;

pub use super::pool::Worker;
pub use crate::guidance::FadingSchedule;

/// `get <p>/session/<id>/control`: the session info, the reply to every op but `close`.
#[derive(Debug, Clone, PartialEq, Serialize, JsonSchema)]
pub struct SessionInfo {
    /// The session's id.
    pub session: String,
    /// The engine slot it holds.
    pub slot: u16,
    /// Its guidance mode.
    pub guidance_mode: &'static str,
    /// Its guidance gain (0..4).
    pub guidance_gain: f64,
    /// Its fading schedule; null without one.
    pub fading: Option<FadingSchedule>,
    /// The drill's burr radius (m).
    pub burr_radius_m: f64,
    /// Entry point A (m, world frame).
    pub entry_m: [f64; 3],
    /// Target B (m, world frame).
    pub target_m: [f64; 3],
    /// Poses the session has received.
    pub poses_received: u64,
    /// The tip depth at which the planning CT shows the burr leaving the first cortex (m); null
    /// when the path crosses none.
    pub planned_breakthrough_depth_m: Option<f64>,
    /// The step at which `path_layers` samples the pristine bone along A→B (m).
    pub path_layer_step_m: f64,
    /// The planning CT along A→B, merged into runs of one layer.
    pub path_layers: Vec<PathLayer>,
    /// For `create`: whether this request created the session (false: it existed); null for
    /// every other op.
    pub created: Option<bool>,
}

/// A run of one layer along A→B, as the planning CT shows it.
#[derive(Debug, Clone, PartialEq, Serialize, JsonSchema)]
pub struct PathLayer {
    /// `outside`, `cortical`, `cancellous`, `marrow` or `necrosis` (layer ids 0–4).
    pub layer: &'static str,
    /// Depth from A of the run's first sample (m).
    pub start_m: f64,
    /// Depth from A of the run's last sample (m).
    pub end_m: f64,
}

/// `get <p>/session/<id>/control` with `{"op": "close"}`.
#[derive(Debug, Clone, PartialEq, Serialize, JsonSchema)]
pub struct Closed {
    /// The session's id.
    pub session: String,
    /// Always true: the session is gone.
    pub closed: bool,
}

/// The error reply of every queryable: what was wrong, and its kind.
#[derive(Debug, Clone, PartialEq, Serialize, JsonSchema)]
pub struct ErrorReply {
    /// What was wrong, for a person.
    pub error: String,
    /// `invalid_input`, `shape`, `engine` or `transport`: the Python client raises the class of
    /// `dhg.core.errors.ERROR_KINDS` it names.
    pub kind: &'static str,
}

/// `get <p>/session/<id>/metrics`: one session's running metrics (SI units).
#[derive(Debug, Clone, PartialEq, Serialize, JsonSchema)]
pub struct MetricsReply {
    /// 10 Hz records since the session started or was reset.
    pub records: u64,
    /// Session time of the last record (s).
    pub time_s: f64,
    /// Deepest tip along A→B (m).
    pub max_depth_m: f64,
    /// Mean distance of the tip from the segment A→B while in bone (m).
    pub mean_deviation_m: f64,
    /// Largest distance of the tip from the segment A→B while in bone (m).
    pub max_deviation_m: f64,
    /// Largest offset of the tip across the path while in bone (m).
    pub max_lateral_deviation_m: f64,
    /// Distance of the last tip from B (m); null before the first record.
    pub target_distance_m: Option<f64>,
    /// RMS rate of change of the device force over the 10 Hz states (N/s).
    pub force_jerk_n_per_s: f64,
    /// Peak drill-tip temperature (°C).
    pub peak_temperature_c: f64,
    /// Time the tip spent above 47 °C (s).
    pub time_above_47_s: f64,
    /// The attempt's largest plunge (m): a later, smaller plunge must not hide the first.
    pub plunge_depth_m: f64,
    /// Cortical breakthroughs so far.
    pub breakthroughs: u16,
    /// Bone removed (kg).
    pub removed_mass_kg: f64,
    /// Bone volume removed (m³).
    pub removed_volume_m3: f64,
    /// Poses the session refused.
    pub rejected_poses: u32,
    /// Guidance messages published.
    pub guidance_messages: u64,
    /// Mean magnitude of the paper's guidance (N).
    pub mean_guidance_n: f64,
    /// Mean model query → reply time (s).
    pub mean_model_latency_s: f64,
    /// Longest model query → reply time (s).
    pub max_model_latency_s: f64,
    /// The session's id.
    pub session: String,
    /// The session's guidance mode.
    pub guidance_mode: &'static str,
    /// The session's guidance gain.
    pub guidance_gain: f64,
    /// The session's burr radius (m).
    pub burr_radius_m: f64,
}

/// Why poses did not tick their session on the thread that received them (`health`): each such
/// pose wakes the tick thread, which ticks it.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, JsonSchema)]
pub struct PosesToTickThread {
    /// The session was not due: the pose came early (it waits for the session's budget), or the
    /// session's commands were not applied yet.
    pub early: u64,
    /// The tick thread held the session (ticking it, or applying a command).
    pub claimed: u64,
}

/// `get <p>/server/health?window=N`: the server's health, tick figures over the last N seconds.
#[derive(Debug, Clone, Serialize, JsonSchema)]
pub struct HealthReply {
    /// Time since the server started (s).
    pub uptime_s: f64,
    /// Open sessions.
    pub sessions: usize,
    /// Their ids, sorted.
    pub session_ids: Vec<String>,
    /// Session slots.
    pub max_sessions: usize,
    /// The window the figures below cover (s).
    pub window_s: f64,
    /// Session ticks in the window, summed over sessions.
    pub ticks: u64,
    /// Of them, those a pose ran on the thread that received it, whose force left from there
    /// (but see the next).
    pub ticks_on_pose_thread: u64,
    /// Of those, the ones that ran while the session's previous force still waited for the comm
    /// thread: their force followed it out from there, so that forces leave in order.
    pub ticks_on_pose_thread_behind: u64,
    /// Poses in the window that their own thread left to the tick thread, and why.
    pub poses_to_tick_thread: PosesToTickThread,
    /// Times the sleeping tick thread woke in the window: at a session's deadline (often to find
    /// that its pose already ticked it), for a pose or command that woke it, or a retry. About
    /// 500–3,000 a second with clients streaming, 50 a second idle.
    pub tick_thread_wakes: u64,
    /// Periods a session's tick came a whole period or more past its deadline, in the window.
    pub missed_ticks: u64,
    /// The same since the server started.
    pub missed_ticks_total: u64,
    /// How late a session tick ran after it was due, median (s).
    pub tick_lateness_p50_s: f64,
    /// ... 99th percentile (s).
    pub tick_lateness_p99_s: f64,
    /// ... 99.9th percentile (s).
    pub tick_lateness_p999_s: f64,
    /// Work per wake-up of the tick thread, 99th percentile (s).
    pub tick_busy_p99_s: f64,
    /// A pose's arrival to the tick that used it, median (s).
    pub pose_to_tick_p50_s: f64,
    /// ... 99th percentile (s).
    pub pose_to_tick_p99_s: f64,
    /// ... 99.9th percentile (s).
    pub pose_to_tick_p999_s: f64,
    /// A pose's arrival to the put of the force computed from it, median (s).
    pub pose_to_put_p50_s: f64,
    /// ... 99th percentile (s).
    pub pose_to_put_p99_s: f64,
    /// ... 99.9th percentile (s).
    pub pose_to_put_p999_s: f64,
    /// Latest tick since the server started (s).
    pub tick_lateness_max_s: f64,
    /// Outputs the tick thread could not hand to the publisher.
    pub dropped_outputs: u64,
    /// Whether the tick thread got `SCHED_FIFO`.
    pub tick_realtime: bool,
    /// Whether a panic (a bug) ended the tick thread: restart the server.
    pub tick_thread_failed: bool,
    /// Which threads run on Linux 6.12's short time slice.
    pub short_slices: ShortSlices,
    /// `"sleep"` or `"spin"` (`dhg-serve --wait`).
    pub tick_wait: &'static str,
    /// `"pose"` or `"thread"` (`dhg-serve --tick-on`).
    pub tick_on: &'static str,
    /// Poses received.
    pub poses: u64,
    /// Puts refused, by reason.
    pub refused: Refused,
    /// The model's side.
    pub model: ModelHealth,
}

/// Which threads run on the 0.1 ms slice of Linux 6.12's scheduler.
#[derive(Debug, Clone, Serialize, JsonSchema)]
pub struct ShortSlices {
    /// The tick thread.
    pub tick: bool,
    /// The force publisher (comm thread).
    pub comm: bool,
    /// How many of Zenoh's I/O threads.
    pub zenoh_io: u64,
}

/// Puts refused, by reason (each counted, never acted on).
#[derive(Debug, Clone, Serialize, JsonSchema)]
pub struct Refused {
    /// A payload of the wrong size for its key.
    pub wrong_size: u64,
    /// A protocol version other than ours.
    pub wrong_version: u64,
    /// A NaN or infinity in a pose.
    pub non_finite: u64,
    /// A payload over the size limit.
    pub oversized: u64,
    /// A put on a key the server does not take.
    pub unknown_key: u64,
    /// A session refused (bad id, every slot taken).
    pub sessions: u64,
    /// A pose dropped (not waited for) because another thread held its session's pose writer at
    /// that instant: two clients publishing under one session id, or the server opening or
    /// closing a session in that slot or declaring its force publisher.
    pub concurrent: u64,
    /// A pose of a session that closed between finding its session and being handed on (the next
    /// pose of that id opens a new session).
    pub ended: u64,
}

/// The model's side of the server.
#[derive(Debug, Clone, Serialize, JsonSchema)]
pub struct ModelHealth {
    /// Whether a model replied in the last second.
    pub available: bool,
    /// The id of the model that replied last.
    pub id: String,
    /// Windows sent to the model (one a session every 100 ms).
    pub queries: u64,
    /// The Zenoh queries that carried them: one for each burst of sessions' windows.
    pub bursts: u64,
    /// Predictions applied.
    pub replies: u64,
    /// Error replies, replies too long to read, and predictions refused or matching no window.
    pub errors: u64,
    /// Valid predictions not applied (a second worker's, a late or rogue one's).
    pub ignored: u64,
    /// Windows whose query ended without a valid prediction for them.
    pub unanswered: u64,
    /// Valid predictions the engine could not take: its command queue was full (never seen under
    /// load so far; a count above 0 says the tick thread fell far behind).
    pub dropped: u64,
    /// A window's record → its prediction applied (its wait for the burst included), median (s).
    pub latency_p50_s: f64,
    /// ... 99th percentile (s).
    pub latency_p99_s: f64,
    /// The workers' pool.
    pub workers: Vec<Worker>,
    /// Worker tokens refused (a bad name, or beyond the pool's size).
    pub workers_refused: u64,
}

/// The JSON schemas of the replies, by name (`info`, `closed`, `metrics`, `health`, `error`), as
/// serde writes them (a field with a serde default is still always written).
#[must_use]
pub fn schemas() -> Value {
    fn written<T: JsonSchema>() -> schemars::Schema {
        schemars::generate::SchemaSettings::default().for_serialize().into_generator().into_root_schema_for::<T>()
    }
    serde_json::json!({
        "info": written::<SessionInfo>(),
        "closed": written::<Closed>(),
        "metrics": written::<MetricsReply>(),
        "health": written::<HealthReply>(),
        "error": written::<ErrorReply>(),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_schemas_name_every_field_serde_writes() {
        let s = schemas();
        let path = crate::path::PlannedPath::new([0.0; 3].into(), [0.0, 0.0, 0.04].into()).unwrap();
        let reply = super::super::metrics::SessionMetrics::default().reply(&path, "s", "shaped", 1.0, 1e-3);
        let written = serde_json::to_value(&reply).unwrap();
        let keys = |v: &Value| v.as_object().unwrap().keys().cloned().collect::<Vec<_>>();
        assert_eq!(keys(&s["metrics"]["properties"]), keys(&written));
        assert_eq!(written["target_distance_m"], Value::Null, "no record yet: no distance");
        for (reply, nested) in [
            ("health", &["PosesToTickThread", "ShortSlices", "Refused", "ModelHealth", "Worker"][..]),
            ("metrics", &[]),
            ("info", &["FadingSchedule", "FadingParams", "PathLayer"]),
            ("closed", &[]),
            ("error", &[]),
        ] {
            let defs = &s[reply]["$defs"];
            assert_eq!(defs.as_object().map_or(0, serde_json::Map::len), nested.len(), "{reply}: {defs}");
            for name in nested {
                assert!(defs[name]["properties"].is_object(), "{reply}.{name}");
            }
        }
    }
}
