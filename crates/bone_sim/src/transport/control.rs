//! The inputs: the pose subscriber, the catch-all that counts unknown keys, and the JSON
//! queryables (session control, session metrics, server health).

use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;
use std::time::Instant;

use serde::{Deserialize, Serialize};
use serde_json::{json, Value};
use zenoh::bytes::Encoding;
use zenoh::query::Query;
use zenoh::sample::{Locality, Sample};
use zenoh::Wait;

use super::comm::put_force;
use super::registry::ForcePublisher;
use super::replies::{
    Closed, ErrorReply, HealthReply, MetricsReply, ModelHealth, PathLayer, PosesToTickThread, Refused, SessionInfo,
    ShortSlices,
};
use super::routes::Missed;
use super::{lock, Shared};
use crate::engine::handoff::{Command, Output};
use crate::engine::{PoseTick, TickOn};
use crate::error::{SimError, SimResult};
use crate::guidance::{check_gain, Fading, FadingParams, GuidanceMode};
use crate::path::PlannedPath;
use crate::protocol::{self, Refusal};
use crate::session::{check_burr_radius, DrillingSession};

use crate::protocol::keys::{self, CLIENT_PUT_LEAF};

fn bump(counter: &AtomicU64) {
    counter.fetch_add(1, Ordering::Relaxed);
}

fn count_refusal(shared: &Shared, r: Refusal) {
    let c = &shared.counters;
    match r {
        Refusal::WrongSize => &c.wrong_size,
        Refusal::WrongVersion => &c.wrong_version,
        Refusal::NonFinite => &c.non_finite,
        Refusal::Oversized => &c.oversized,
    }
    .fetch_add(1, Ordering::Relaxed);
}

/// Every put from another Zenoh session under the prefix, in one subscriber so that a pose is
/// delivered once (a second, catch-all subscriber cost every pose a second delivery). The only
/// key a client may put on is a session's `pose`; a put anywhere else (an output key such as
/// `force`, a leaf below `pose`, the model's or the server's namespace, an unknown leaf) is
/// counted as `unknown_key`.
fn on_put(shared: &Shared, sample: &Sample) {
    let received = std::time::Instant::now();
    let pose_of = sample
        .key_expr()
        .as_str()
        .strip_prefix(shared.prefix.as_str())
        .and_then(|rest| rest.strip_prefix("/session/"))
        .and_then(|rest| rest.split_once('/'))
        .and_then(|(id, leaf)| (leaf == CLIENT_PUT_LEAF).then_some(id));
    match pose_of {
        Some(id) => on_pose(shared, id, sample, received),
        None => {
            shared.counters.unknown_key.fetch_add(1, Ordering::Relaxed);
        }
    }
}

fn on_pose(shared: &Shared, id: &str, sample: &Sample, received: std::time::Instant) {
    if sample.payload().len() > protocol::MAX_PAYLOAD_BYTES {
        count_refusal(shared, Refusal::Oversized);
        return;
    }
    let msg = match protocol::decode_pose(&sample.payload().to_bytes()) {
        Ok(m) => m,
        Err(r) => return count_refusal(shared, r),
    };
    // The routes, not the registry: nothing a pose does waits on the registry's lock (decision
    // 0039), but its session's first pose, which opens the session.
    let route = if let Some(route) = shared.routes.find(id) {
        route
    } else {
        let mut reg = lock(&shared.registry);
        let Ok((slot, _)) = reg.open(id, None) else {
            shared.counters.sessions_refused.fetch_add(1, Ordering::Relaxed);
            return;
        };
        reg.route(slot)
    };
    let (slot, generation) = (route.slot, route.generation);
    let force = match shared.routes.pose(route, &msg, received) {
        Ok(force) => force,
        Err(Missed::Busy) => return bump(&shared.counters.poses_concurrent),
        Err(Missed::Ended) => return bump(&shared.counters.poses_ended),
    };
    shared.counters.poses.fetch_add(1, Ordering::Relaxed);
    if shared.config.tick_on == TickOn::Pose {
        let out_up_to = shared.put_done.get(usize::from(slot)).map_or(0, |n| n.load(Ordering::Acquire));
        match shared.ticker.tick(slot, generation, Instant::now(), out_up_to, force.is_some()) {
            PoseTick::Ticked { force: out, state } => return tick_here(shared, force.as_deref(), &out, state),
            // Ticks without a pose ran here, queued for the comm thread; the pose waits.
            PoseTick::Held => wake_comm(shared),
            PoseTick::NotDue | PoseTick::Claimed => {}
        }
    }
    shared.ticker.wake_tick_thread(); // the slot may tick now rather than at its next deadline
}

/// A pose ticked its session on this thread (its outputs are queued): the force leaves from here
/// once the comm thread has declared the session's publisher, and the comm thread only records it;
/// the comm thread is woken only for what it must publish (the first forces, the 10 Hz state).
fn tick_here(shared: &Shared, publisher: Option<&ForcePublisher>, force: &Output, state: bool) {
    // Not `published` when ticks without a pose ran before it, or the session's previous force had
    // not left yet: those forces leave first, from the comm thread, and this one after them.
    let here = matches!(force, Output::Force { published: true, .. });
    if let (Output::Force { slot, msg, received, order, .. }, Some(p), true) = (force, publisher, here) {
        put_force(shared, p, *slot, msg, *received, *order);
    }
    if state || publisher.is_none() || !here {
        wake_comm(shared);
    }
}

fn wake_comm(shared: &Shared) {
    if let Some(t) = shared.comm_thread.get() {
        t.unpark();
    }
}

fn query_json(query: &Query) -> SimResult<Value> {
    let Some(payload) = query.payload() else { return Ok(json!({})) };
    if payload.len() > protocol::MAX_PAYLOAD_BYTES {
        return Err(SimError::Payload { message: "control", reason: format!("{} bytes, too long", payload.len()) });
    }
    serde_json::from_slice(&payload.to_bytes())
        .map_err(|e| SimError::Payload { message: "control", reason: format!("not JSON: {e}") })
}

fn reply(query: &Query, result: SimResult<Value>) {
    let key = query.key_expr().clone();
    let _ = match result {
        Ok(v) => query.reply(key, v.to_string()).encoding(Encoding::APPLICATION_JSON).wait(),
        Err(e) => query
            .reply_err(json!(ErrorReply { error: e.to_string(), kind: e.kind() }).to_string())
            .encoding(Encoding::APPLICATION_JSON)
            .wait(),
    };
}

/// A control request (`docs/protocol.md`, control): a JSON object whose `op` names the variant
/// (`info` when it has none). Unknown fields are refused, so a misspelt one is not silently
/// ignored.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(tag = "op", rename_all = "snake_case", deny_unknown_fields)]
pub enum ControlRequest {
    /// Opens the session (or returns the open one), on its own path if given.
    Create {
        /// Entry point A (m); with `target_m`.
        #[serde(default)]
        entry_m: Option<Vec<f64>>,
        /// Target point B (m); with `entry_m`.
        #[serde(default)]
        target_m: Option<Vec<f64>>,
        /// Guidance mode of the new session.
        #[serde(default)]
        guidance_mode: Option<GuidanceMode>,
        /// Guidance gain of the new session (0–4).
        #[serde(default)]
        guidance_gain: Option<f64>,
        /// Burr radius (m).
        #[serde(default)]
        burr_radius_m: Option<f64>,
    },
    /// A new attempt on fresh bone (the fading schedule counts the one that ended).
    Reset,
    /// A new planned path.
    SetPath {
        /// Entry point A (m).
        entry_m: Vec<f64>,
        /// Target point B (m).
        target_m: Vec<f64>,
    },
    /// The guidance mode, the gain, or both.
    SetGuidance {
        /// Guidance mode.
        #[serde(default)]
        mode: Option<GuidanceMode>,
        /// Guidance gain (0–4).
        #[serde(default)]
        gain: Option<f64>,
    },
    /// Starts (an object of schedule params, `{}` for the defaults) or stops (null) fading.
    SetFading {
        /// The schedule's params, or null; required.
        #[serde(deserialize_with = "Option::deserialize")]
        fading: Option<FadingParams>,
    },
    /// Another burr.
    SetDrill {
        /// Burr radius (m).
        burr_radius_m: f64,
    },
    /// Frees the session.
    Close,
    /// The session's info.
    Info,
}

impl ControlRequest {
    /// Reads a request body.
    ///
    /// # Errors
    /// Not an object, an `op` that is not a string or not an operation, a missing or unknown
    /// field, a value of the wrong type.
    pub fn from_json(body: &Value) -> SimResult<Self> {
        let bad = |reason: String| SimError::Payload { message: "control", reason };
        let Some(obj) = body.as_object() else {
            return Err(bad("the body must be a JSON object, {\"op\": ...}".into()));
        };
        match obj.get("op") {
            None => {
                let mut with_op = obj.clone();
                with_op.insert("op".into(), json!("info"));
                return Self::from_json(&Value::Object(with_op));
            }
            Some(Value::String(op)) if !OPS.contains(&op.as_str()) => {
                return Err(SimError::InvalidOption { name: "op", value: op.clone(), allowed: OPS_TEXT });
            }
            Some(Value::String(_)) => {}
            Some(_) => return Err(bad(format!("\"op\" must be a string: {OPS_TEXT}"))),
        }
        Self::deserialize(body).map_err(|e| bad(e.to_string()))
    }
}

impl ControlRequest {
    /// Each operation with the fields it takes, in the order `docs/protocol.md` lists them (read
    /// from the serde definition: every field of a fully given request).
    #[must_use]
    pub fn fields() -> Vec<(String, Vec<String>)> {
        let v = Some(vec![0.0; 3]);
        let every = [
            Self::Create {
                entry_m: v.clone(),
                target_m: v.clone(),
                guidance_mode: Some(GuidanceMode::default()),
                guidance_gain: Some(1.0),
                burr_radius_m: Some(1e-3),
            },
            Self::Reset,
            Self::SetPath { entry_m: vec![0.0; 3], target_m: vec![0.0; 3] },
            Self::SetGuidance { mode: Some(GuidanceMode::default()), gain: Some(1.0) },
            Self::SetFading { fading: Some(FadingParams::default()) },
            Self::SetDrill { burr_radius_m: 1e-3 },
            Self::Close,
            Self::Info,
        ];
        every
            .iter()
            .filter_map(|r| {
                let Value::Object(m) = serde_json::to_value(r).ok()? else { return None };
                let op = m.get("op")?.as_str()?.to_owned();
                Some((op, m.keys().filter(|k| *k != "op").cloned().collect()))
            })
            .collect()
    }
}

/// Every operation's name.
const OPS: [&str; 8] = ["create", "reset", "set_path", "set_guidance", "set_fading", "set_drill", "close", "info"];
const OPS_TEXT: &str = "create, reset, set_path, set_guidance, set_fading, set_drill, close, info";

fn point(xs: &[f64], name: &'static str) -> SimResult<nalgebra::Point3<f64>> {
    match xs {
        [x, y, z] => Ok(nalgebra::Point3::new(*x, *y, *z)),
        _ => Err(SimError::ShapeMismatch {
            what: name,
            expected: "a list of 3 numbers (m)".into(),
            got: format!("{xs:?}"),
        }),
    }
}

fn path_of(entry_m: &[f64], target_m: &[f64]) -> SimResult<PlannedPath> {
    PlannedPath::new(point(entry_m, "entry_m")?, point(target_m, "target_m")?)
}

/// The step (m) at which a session's info samples the pristine layers along its path.
const PATH_LAYER_STEP_M: f64 = DrillingSession::PLAN_STEP_M;

fn session_info(shared: &Shared, id: &str, created: Option<bool>) -> SimResult<Value> {
    let (mut info, path) = {
        let reg = lock(&shared.registry);
        let slot = reg.slot_of(id).ok_or_else(|| SimError::Engine(format!("no session {id:?}")))?;
        let info = &reg.slots[slot as usize];
        let (a, b) = (info.path.entry_m(), info.path.target_m());
        let v = SessionInfo {
            session: id.to_string(),
            slot,
            guidance_mode: info.mode.name(),
            guidance_gain: info.gain,
            fading: info.fading.as_ref().map(Fading::schedule),
            burr_radius_m: info.burr_radius_m,
            entry_m: [a.x, a.y, a.z],
            target_m: [b.x, b.y, b.z],
            poses_received: reg.poses_received(slot),
            planned_breakthrough_depth_m: None,
            path_layer_step_m: PATH_LAYER_STEP_M,
            path_layers: Vec::new(),
            created,
        };
        (v, info.path.clone())
    };
    // Sampled outside the registry lock: the pose subscriber needs it at 1 kHz per client.
    let runs = path.layer_runs(&shared.volume, PATH_LAYER_STEP_M)?;
    // Where the session's guidance and a planning trainee expect the first cortex to give.
    info.planned_breakthrough_depth_m =
        path.first_cortex_exit_m(&shared.volume, DrillingSession::PLAN_STEP_M).map(|e| e - info.burr_radius_m);
    info.path_layers =
        runs.iter().map(|r| PathLayer { layer: r.layer.name(), start_m: r.start_m, end_m: r.end_m }).collect();
    Ok(json!(info))
}

/// Sets the guidance of `slot`, keeping what is not given.
fn set_guidance(
    reg: &mut super::registry::Registry,
    slot: u16,
    mode: Option<GuidanceMode>,
    gain: Option<f64>,
) -> SimResult<()> {
    let info = &reg.slots[slot as usize];
    let (mode, gain) = (mode.unwrap_or(info.mode), gain.unwrap_or(info.gain));
    reg.send(Command::SetGuidance { slot, mode, gain })?;
    let info = &mut reg.slots[slot as usize];
    (info.mode, info.gain) = (mode, gain);
    Ok(())
}

/// Resets `slot` for a new attempt; with fading, an attempt that drilled (poses arrived and were
/// recorded) ends here and sets the next one's gain.
fn reset(reg: &mut super::registry::Registry, slot: u16) -> SimResult<()> {
    reg.room_for(2)?; // Reset and a fading schedule's SetGuidance: both or none
    reg.send(Command::Reset { slot })?;
    let poses_received = reg.poses_received(slot);
    let info = &mut reg.slots[slot as usize];
    let drilled = poses_received > info.attempt_first_pose && info.metrics.records() > 0;
    let next_gain = match info.fading.as_mut() {
        Some(f) if drilled => {
            let (plunge_m, deviation_m) = info.metrics.worst_m(&info.path);
            Some(f.finish_attempt(plunge_m, deviation_m))
        }
        _ => None,
    };
    info.new_attempt(poses_received);
    match next_gain {
        Some(gain) => set_guidance(reg, slot, None, Some(gain)),
        None => Ok(()),
    }
}

/// Opens (or finds) session `id` with its checked settings; returns (slot, created). Refused whole
/// when the command ring cannot take every command it sends.
fn create(
    reg: &mut super::registry::Registry,
    id: &str,
    path: Option<PlannedPath>,
    mode: Option<GuidanceMode>,
    gain: Option<f64>,
    burr_radius_m: Option<f64>,
) -> SimResult<(u16, bool)> {
    reg.room_for(3)?; // Activate, SetGuidance, SetBurr: all or none
    let (s, created) = reg.open(id, path)?;
    if mode.is_some() || gain.is_some() {
        set_guidance(reg, s, mode, gain)?;
    }
    if let Some(radius_m) = burr_radius_m {
        reg.send(Command::SetBurr { slot: s, radius_m })?;
        reg.slots[s as usize].burr_radius_m = radius_m;
    }
    Ok((s, created))
}

/// Starts (`Some` params) or stops (`None`) the fading schedule of `slot`.
fn set_fading(reg: &mut super::registry::Registry, slot: u16, params: Option<FadingParams>) -> SimResult<()> {
    let fading = params.map(Fading::new).transpose()?;
    if let Some(f) = &fading {
        set_guidance(reg, slot, None, Some(f.gain()))?;
    }
    reg.slots[slot as usize].fading = fading;
    Ok(())
}

/// Applies one control request (its JSON body) to session `id`.
pub(crate) fn apply(shared: &Shared, id: &str, body: &Value) -> SimResult<Value> {
    let req = ControlRequest::from_json(body)?;
    {
        let mut reg = lock(&shared.registry);
        let slot = |reg: &super::registry::Registry| {
            reg.slot_of(id).ok_or_else(|| SimError::Engine(format!("no session {id:?}; create it first")))
        };
        match req {
            ControlRequest::Create { entry_m, target_m, guidance_mode, guidance_gain, burr_radius_m } => {
                // Everything is checked before the session exists: a refused create creates nothing.
                let path = match (entry_m, target_m) {
                    (None, None) => None,
                    (a, b) => Some(path_of(a.as_deref().unwrap_or(&[]), b.as_deref().unwrap_or(&[]))?),
                };
                let gain = guidance_gain.map(check_gain).transpose()?;
                let burr = burr_radius_m.map(check_burr_radius).transpose()?;
                let (_, created) = create(&mut reg, id, path, guidance_mode, gain, burr)?;
                drop(reg);
                return session_info(shared, id, Some(created));
            }
            ControlRequest::Reset => {
                let s = slot(&reg)?;
                reset(&mut reg, s)?;
            }
            ControlRequest::SetFading { fading } => {
                let s = slot(&reg)?;
                set_fading(&mut reg, s, fading)?;
            }
            ControlRequest::SetPath { entry_m, target_m } => {
                let s = slot(&reg)?;
                let path = path_of(&entry_m, &target_m)?;
                reg.send(Command::SetPath { slot: s, path: path.clone() })?;
                reg.slots[s as usize].path = path;
            }
            ControlRequest::SetGuidance { mode, gain } => {
                let s = slot(&reg)?;
                let gain = gain.map(check_gain).transpose()?;
                if mode.is_none() && gain.is_none() {
                    return Err(SimError::Payload {
                        message: "control",
                        reason:
                            "set_guidance needs a \"mode\" (paper, corridor, brake, shaped), a \"gain\" (0–4), or both"
                                .into(),
                    });
                }
                set_guidance(&mut reg, s, mode, gain)?;
            }
            ControlRequest::SetDrill { burr_radius_m } => {
                let s = slot(&reg)?;
                let radius_m = check_burr_radius(burr_radius_m)?;
                reg.send(Command::SetBurr { slot: s, radius_m })?;
                reg.slots[s as usize].burr_radius_m = radius_m;
            }
            ControlRequest::Close => {
                reg.close(id)?;
                return Ok(json!(Closed { session: id.to_string(), closed: true }));
            }
            ControlRequest::Info => {}
        }
        if let Some(s) = reg.slot_of(id) {
            reg.seen(s);
        }
    }
    session_info(shared, id, None)
}

/// A session's metrics.
pub(crate) fn metrics(shared: &Shared, id: &str) -> SimResult<MetricsReply> {
    let reg = lock(&shared.registry);
    let slot = reg.slot_of(id).ok_or_else(|| SimError::Engine(format!("no session {id:?}")))?;
    let info = &reg.slots[slot as usize];
    Ok(info.metrics.reply(&info.path, id, info.mode.name(), info.gain, info.burr_radius_m))
}

fn quantile(sorted: &[f64], q: f64) -> f64 {
    if sorted.is_empty() {
        return 0.0;
    }
    sorted[((q * sorted.len() as f64).ceil() as usize).clamp(1, sorted.len()) - 1]
}

/// The health report; tick quantiles cover the last `window_s` seconds (whole seconds).
pub(crate) fn health(shared: &Shared, window_s: f64) -> HealthReply {
    let now = super::history::sample(shared);
    let (window, base) = {
        let h = lock(&shared.history);
        let seconds = window_s.max(1.0).round();
        let back = (seconds as usize).min(h.samples.len());
        // A window reaching back to the server's start covers it all (its first sample came a
        // second in), as the totals (`poses`) do.
        let whole = shared.started.elapsed().as_secs_f64() <= seconds;
        match h.samples.len().checked_sub(back).and_then(|i| h.samples.get(i)) {
            Some(s) if back > 0 && !whole => (now.at.duration_since(s.at).as_secs_f64(), Some(s.clone())),
            _ => (shared.started.elapsed().as_secs_f64(), None),
        }
    };
    let d = now.since(base.as_ref());
    // Each lock only for a copy of what the reply needs: the model's replies take the model's
    // stats and the registry for each guidance message, and a client asking for health as fast as
    // it can must not hold them while the reply is built (a sort of up to 2,000 latencies, the
    // quantiles, the ids).
    let (mut lat, available, model_id) = {
        let model = lock(&shared.model);
        let lat: Vec<f64> = model.latencies_s.iter().copied().collect();
        (lat, model.last_reply.is_some_and(|t| t.elapsed().as_secs_f64() < 1.0), model.model_id.clone())
    };
    lat.sort_by(f64::total_cmp);
    let c = &shared.counters;
    let n = |a: &std::sync::atomic::AtomicU64| a.load(Ordering::Relaxed);
    let (workers, workers_refused) = {
        let pool = lock(&shared.pool);
        (pool.report(Instant::now()), pool.refused)
    };
    let (sessions, mut session_ids, max_sessions) = {
        let reg = lock(&shared.registry);
        (reg.by_id.len(), reg.by_id.keys().cloned().collect::<Vec<String>>(), reg.slots.len())
    };
    session_ids.sort();
    HealthReply {
        uptime_s: shared.started.elapsed().as_secs_f64(),
        sessions,
        session_ids,
        max_sessions,
        window_s: window,
        ticks: d.ticks,
        ticks_on_pose_thread: d.pose_thread_ticks,
        ticks_on_pose_thread_behind: d.pose_ticks_behind,
        poses_to_tick_thread: PosesToTickThread { early: d.poses_left[0], claimed: d.poses_left[1] },
        tick_thread_wakes: d.wakes,
        missed_ticks: d.missed,
        missed_ticks_total: now.missed,
        tick_lateness_p50_s: d.lateness.quantile_s(0.5),
        tick_lateness_p99_s: d.lateness.quantile_s(0.99),
        tick_lateness_p999_s: d.lateness.quantile_s(0.999),
        tick_busy_p99_s: d.busy.quantile_s(0.99),
        pose_to_tick_p50_s: d.pose_to_tick.quantile_s(0.5),
        pose_to_tick_p99_s: d.pose_to_tick.quantile_s(0.99),
        pose_to_tick_p999_s: d.pose_to_tick.quantile_s(0.999),
        pose_to_put_p50_s: d.pose_to_put.quantile_s(0.5),
        pose_to_put_p99_s: d.pose_to_put.quantile_s(0.99),
        pose_to_put_p999_s: d.pose_to_put.quantile_s(0.999),
        tick_lateness_max_s: n(&shared.stats.max_lateness_ns) as f64 * 1e-9,
        dropped_outputs: n(&shared.stats.dropped_outputs),
        tick_realtime: n(&shared.stats.realtime) == 1,
        tick_thread_failed: n(&shared.stats.tick_thread_failed) == 1,
        short_slices: ShortSlices {
            tick: n(&shared.stats.short_slice) == 1,
            comm: n(&c.comm_short_slice) == 1,
            zenoh_io: n(&c.io_short_slices),
        },
        tick_wait: shared.wait.name(),
        tick_on: shared.config.tick_on.name(),
        poses: n(&c.poses),
        refused: Refused {
            wrong_size: n(&c.wrong_size),
            wrong_version: n(&c.wrong_version),
            non_finite: n(&c.non_finite),
            oversized: n(&c.oversized),
            unknown_key: n(&c.unknown_key),
            sessions: n(&c.sessions_refused),
            concurrent: n(&c.poses_concurrent),
            ended: n(&c.poses_ended),
        },
        model: ModelHealth {
            available,
            id: model_id,
            queries: n(&c.model_queries),
            bursts: n(&c.model_bursts),
            replies: n(&c.model_replies),
            errors: n(&c.model_errors),
            ignored: n(&c.model_ignored),
            unanswered: n(&c.model_unanswered),
            dropped: n(&c.model_dropped),
            latency_p50_s: quantile(&lat, 0.5),
            latency_p99_s: quantile(&lat, 0.99),
            workers,
            workers_refused,
        },
    }
}

/// Declares `<p>/session/*/<leaf>`, answering each query with `handle(shared, session id, query)`.
fn session_queryable(
    session: &zenoh::Session,
    shared: &Arc<Shared>,
    leaf: &'static str,
    handle: fn(&Shared, &str, &Query) -> SimResult<Value>,
) -> SimResult<()> {
    let s = shared.clone();
    session
        .declare_queryable(keys::session_leaf(&shared.prefix, "*", leaf))
        .callback(move |q| {
            let r = match keys::parse_session(&s.prefix, q.key_expr().as_str()) {
                Some((id, _)) => handle(&s, id, &q),
                None => Err(SimError::Engine("bad key".into())),
            };
            reply(&q, r);
        })
        .background()
        .wait()
        .map_err(|e| SimError::Transport(format!("cannot declare the {leaf} queryable: {e}")))?;
    Ok(())
}

/// Declares the pose subscriber (which also counts puts on unknown keys) and the queryables. They live as long as
/// the Zenoh session.
pub(crate) fn declare(session: &zenoh::Session, shared: &Arc<Shared>) -> SimResult<()> {
    let p = &shared.prefix;
    let err = |what: &'static str| move |e: zenoh::Error| SimError::Transport(format!("cannot declare {what}: {e}"));
    let s = shared.clone();
    session
        .declare_subscriber(format!("{p}/**"))
        .allowed_origin(Locality::Remote)
        .callback(move |sample| on_put(&s, &sample))
        .background()
        .wait()
        .map_err(err("the pose subscriber"))?;
    session_queryable(session, shared, "control", |s, id, q| query_json(q).and_then(|req| apply(s, id, &req)))?;
    // The session info alone, changing nothing: what a screen or a recorder asks, so that the lab's
    // access control can let them read it without letting them change a session (`control`).
    session_queryable(session, shared, "info", |s, id, _| session_info(s, id, None))?;
    session_queryable(session, shared, "metrics", |s, id, _| metrics(s, id).map(|m| json!(m)))?;
    let s = shared.clone();
    session
        .declare_queryable(keys::server(p, "health"))
        .callback(move |q| {
            let window = q.parameters().get("window").and_then(|w| w.parse::<f64>().ok()).unwrap_or(10.0);
            reply(&q, Ok(json!(health(&s, window))));
        })
        .background()
        .wait()
        .map_err(err("the health queryable"))?;
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The registry counts a slot's attempts as the engine does, so that the records of an attempt
    /// a reset ended, still on their way to the comm thread when it came, count in no later
    /// attempt: not in its metrics, and not as drilled when a second reset comes before the new
    /// attempt's first record (which would finish a fading attempt on them).
    #[test]
    fn records_of_an_ended_attempt_count_in_no_later_one() {
        use super::super::registry::{Owners, Registry};
        use crate::engine::{build, EngineConfig, OutputQueue, TickCore};
        use crate::protocol::{PoseMsg, StateMsg};
        use crate::session::Pose;
        use crate::volume::{layer::Layer, test_support::uniform_block};
        use nalgebra::{Point3, UnitQuaternion};

        /// `n` ticks with the burr held 1 mm into the block; the states the engine emitted.
        fn drill(core: &mut TickCore, outputs: &OutputQueue, reg: &mut Registry, n: u32) -> Vec<(u32, StateMsg)> {
            let pose = Pose {
                position_m: Point3::new(6e-3, 6e-3, 3e-3),
                orientation: UnitQuaternion::identity(),
                drill_on: true,
                spindle_rpm: 1250.0,
            };
            let mut states = Vec::new();
            for _ in 0..n {
                let seq = u32::try_from(reg.poses_received(0)).unwrap() + 1;
                reg.pose(0, &PoseMsg { seq, client_time_ns: 0, pose }, Instant::now());
                core.tick();
                while let Some(out) = outputs.pop() {
                    if let Output::State { attempt, msg, .. } = out {
                        states.push((attempt, msg));
                    }
                }
            }
            states
        }

        let vol = Arc::new(uniform_block(24, 0.5e-3, Layer::Cortical, 1500.0, 4));
        let path = PlannedPath::new(Point3::new(6e-3, 6e-3, 1e-3), Point3::new(6e-3, 6e-3, 10e-3)).unwrap();
        let mut cfg = EngineConfig::new(path.clone());
        (cfg.max_sessions, cfg.reserve_bricks) = (1, 64);
        let (mut core, link) = build(&vol, &cfg).unwrap();
        let outputs = link.outputs;
        let mut reg =
            Registry::new(link.commands, link.poses, path, (GuidanceMode::default(), 1.0), 1.25e-3, Owners::default());
        reg.open("s", None).unwrap();
        set_fading(&mut reg, 0, Some(FadingParams::default())).unwrap();

        // The first attempt records twice; the comm thread has not taken its records yet.
        let first = drill(&mut core, &outputs, &mut reg, 250);
        assert_eq!(first.len(), 2);
        reset(&mut reg, 0).unwrap();
        for (k, (attempt, msg)) in first.iter().enumerate() {
            assert!(!reg.slots[0].add_record(msg, *attempt, k as u32 + 1), "a record of the ended attempt");
        }
        assert_eq!(reg.slots[0].metrics.records(), 0);
        // Poses of the new attempt, but no record yet: a second reset finds nothing drilled.
        assert!(drill(&mut core, &outputs, &mut reg, 50).is_empty());
        reset(&mut reg, 0).unwrap();
        assert_eq!(reg.slots[0].fading.as_ref().map(Fading::attempts), Some(0), "no attempt finished on stragglers");
        // The third attempt's records are its own.
        let third = drill(&mut core, &outputs, &mut reg, 150);
        assert_eq!(third.len(), 1);
        let (attempt, msg) = third[0];
        assert_eq!(attempt, reg.slots[0].attempt, "the registry's count is the engine's");
        assert!(reg.slots[0].add_record(&msg, attempt, 3));
        assert_eq!((reg.slots[0].metrics.records(), reg.slots[0].attempt_first_window), (1, Some(3)));
    }

    #[test]
    fn a_request_of_several_commands_is_refused_whole_when_the_ring_cannot_take_them() {
        use super::super::registry::{Owners, Registry};
        use crate::engine::{build, EngineConfig};
        use crate::volume::{layer::Layer, test_support::uniform_block};
        use nalgebra::Point3;

        let vol = Arc::new(uniform_block(24, 0.5e-3, Layer::Cortical, 1500.0, 4));
        let path = PlannedPath::new(Point3::new(6e-3, 6e-3, 1e-3), Point3::new(6e-3, 6e-3, 10e-3)).unwrap();
        let mut cfg = EngineConfig::new(path.clone());
        (cfg.max_sessions, cfg.reserve_bricks) = (2, 64);
        let (_core, link) = build(&vol, &cfg).unwrap(); // no tick thread: nothing takes the commands
        let mut reg =
            Registry::new(link.commands, link.poses, path, (GuidanceMode::default(), 1.0), 1.25e-3, Owners::default());
        reg.open("a", None).unwrap();
        set_fading(&mut reg, 0, Some(FadingParams::default())).unwrap();
        while reg.room_for(2).is_ok() {
            set_guidance(&mut reg, 0, None, Some(0.5)).unwrap();
        }
        // One place left. A create needs three: refused, it opens nothing.
        let err = create(&mut reg, "b", None, Some(GuidanceMode::Brake), Some(0.5), Some(1e-3)).unwrap_err();
        assert!(err.to_string().contains("command ring is full"), "{err}");
        assert_eq!(reg.slot_of("b"), None);
        // A reset needs two (the fading schedule's next gain): refused, the attempt goes on.
        let attempt = reg.slots[0].attempt;
        assert!(reset(&mut reg, 0).is_err());
        assert_eq!(reg.slots[0].attempt, attempt, "a refused reset changed the registry");
        // One command still goes: a lone set_guidance.
        assert!(set_guidance(&mut reg, 0, None, Some(0.25)).is_ok());
    }

    #[allow(clippy::needless_pass_by_value)] // the tests read better with json!(...) by value
    fn parse(v: Value) -> SimResult<ControlRequest> {
        ControlRequest::from_json(&v)
    }

    #[test]
    fn every_op_parses_and_a_body_without_op_is_info() {
        assert_eq!(parse(json!({})).unwrap(), ControlRequest::Info);
        assert_eq!(parse(json!({"op": "reset"})).unwrap(), ControlRequest::Reset);
        assert_eq!(
            parse(json!({"op": "set_guidance", "mode": "brake"})).unwrap(),
            ControlRequest::SetGuidance { mode: Some(GuidanceMode::Brake), gain: None }
        );
        assert_eq!(
            parse(json!({"op": "set_fading", "fading": null})).unwrap(),
            ControlRequest::SetFading { fading: None }
        );
        let ops: Vec<String> = ControlRequest::fields().into_iter().map(|(op, _)| op).collect();
        assert_eq!(ops, OPS, "fields() covers every op, in order");
    }

    #[test]
    fn bad_requests_are_refused_saying_what_was_wrong() {
        let err = |v: Value| parse(v).unwrap_err().to_string();
        assert!(err(json!([1, 2])).contains("JSON object"));
        assert!(err(json!({"op": 7})).contains("must be a string"));
        assert!(err(json!({"op": "dance"})).contains("create, reset"));
        assert!(err(json!({"op": "set_guidance", "gian": 0.5})).contains("unknown field `gian`"));
        assert!(err(json!({"op": "set_fading"})).contains("missing field `fading`"));
        assert!(err(json!({"op": "set_drill", "burr_radius_m": "big"})).contains("invalid type"));
        assert!(err(json!({"op": "set_guidance", "mode": "stiff"})).contains("unknown variant `stiff`"));
        assert!(err(json!({"op": "set_fading", "fading": {"forgett": 0.5}})).contains("unknown field `forgett`"));
    }

    #[test]
    fn a_point_of_the_wrong_length_is_a_shape_error() {
        let e = path_of(&[0.0, 1.0], &[0.0, 0.0, 1.0]).unwrap_err();
        assert_eq!(e.kind(), "shape");
        assert!(e.to_string().contains("entry_m"));
    }
}
