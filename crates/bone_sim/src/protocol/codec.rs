//! Encoders and decoders that follow the layout tables, and why a payload is refused.

use nalgebra::Vector3;

use super::{
    flags, Layout, FORCE, GUIDANCE, MAX_PAYLOAD_BYTES, MAX_QUERY_WINDOWS, POSE, PREDICT, PREDICTION, STATE, TICKS,
    TICK_ROW, VERSION, WINDOW_RECORDS,
};
use crate::error::{SimError, SimResult};
use crate::record::FEATURE_COUNT;
use crate::session::Pose;

/// A little-endian writer into a fixed buffer, at the offsets the layouts give.
pub(super) struct Writer<'a>(pub(super) &'a mut [u8]);

impl Writer<'_> {
    pub(super) fn header(&mut self, layout: &Layout, flags: u16) {
        self.0[0] = layout.kind;
        self.0[1] = VERSION;
        self.u16(2, flags);
    }
    pub(super) fn u16(&mut self, at: usize, v: u16) {
        self.0[at..at + 2].copy_from_slice(&v.to_le_bytes());
    }
    pub(super) fn u32(&mut self, at: usize, v: u32) {
        self.0[at..at + 4].copy_from_slice(&v.to_le_bytes());
    }
    pub(super) fn u64(&mut self, at: usize, v: u64) {
        self.0[at..at + 8].copy_from_slice(&v.to_le_bytes());
    }
    pub(super) fn f32(&mut self, at: usize, v: f64) {
        self.0[at..at + 4].copy_from_slice(&(v as f32).to_le_bytes());
    }
    pub(super) fn f64(&mut self, at: usize, v: f64) {
        self.0[at..at + 8].copy_from_slice(&v.to_le_bytes());
    }
    pub(super) fn vec3_f32(&mut self, at: usize, v: &Vector3<f64>) {
        for (i, x) in v.iter().enumerate() {
            self.f32(at + 4 * i, *x);
        }
    }
    /// A force on the wire: each component rounded toward zero, so the float32 vector is never
    /// longer than the limited one (rounding to nearest made about half the forces at the peak
    /// 1e-7 N over it, which a client's guard refuses).
    pub(super) fn force_f32(&mut self, at: usize, v: &Vector3<f64>) {
        for (i, x) in v.iter().enumerate() {
            self.0[at + 4 * i..at + 4 * i + 4].copy_from_slice(&f32_toward_zero(*x).to_le_bytes());
        }
    }
}

/// `x` as the nearest float32 no larger in magnitude (NaN stays NaN).
#[inline]
pub(crate) fn f32_toward_zero(x: f64) -> f32 {
    let y = x as f32;
    if f64::from(y).abs() <= x.abs() || y.is_infinite() {
        y
    } else {
        // |y| > |x| >= 0, so y is finite and not zero: one step down in magnitude, either sign.
        f32::from_bits(y.to_bits() - 1)
    }
}

pub(super) fn rd<const N: usize>(b: &[u8], at: usize) -> [u8; N] {
    let mut out = [0; N];
    out.copy_from_slice(&b[at..at + N]);
    out
}
pub(super) fn rd_u16(b: &[u8], at: usize) -> u16 {
    u16::from_le_bytes(rd(b, at))
}
pub(super) fn rd_u32(b: &[u8], at: usize) -> u32 {
    u32::from_le_bytes(rd(b, at))
}
pub(super) fn rd_u64(b: &[u8], at: usize) -> u64 {
    u64::from_le_bytes(rd(b, at))
}
pub(super) fn rd_f32(b: &[u8], at: usize) -> f64 {
    f64::from(f32::from_le_bytes(rd(b, at)))
}
pub(super) fn rd_f64(b: &[u8], at: usize) -> f64 {
    f64::from_le_bytes(rd(b, at))
}

/// Why a payload was refused; the server counts each kind separately.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Refusal {
    /// Shorter or longer than its layout.
    WrongSize,
    /// Another kind or protocol version.
    WrongVersion,
    /// A NaN or infinite number, or a zero quaternion.
    NonFinite,
    /// Longer than [`MAX_PAYLOAD_BYTES`].
    Oversized,
}

impl Refusal {
    fn error(self, message: &'static str, bytes: &[u8]) -> SimError {
        let reason = match self {
            Refusal::WrongSize => format!("{} bytes, expected the layout's size", bytes.len()),
            Refusal::WrongVersion => {
                format!(
                    "kind {} version {}, expected version {VERSION}",
                    bytes.first().unwrap_or(&0),
                    bytes.get(1).unwrap_or(&0)
                )
            }
            Refusal::NonFinite => "a NaN or infinite value, or a zero quaternion".to_owned(),
            Refusal::Oversized => format!("{} bytes, over the {MAX_PAYLOAD_BYTES}-byte limit", bytes.len()),
        };
        SimError::Payload { message, reason }
    }
}

pub(super) fn check(layout: &Layout, bytes: &[u8], exact: bool) -> Result<(), Refusal> {
    if bytes.len() > MAX_PAYLOAD_BYTES {
        return Err(Refusal::Oversized);
    }
    if bytes.len() < 2 {
        return Err(Refusal::WrongSize);
    }
    if bytes[0] != layout.kind || bytes[1] != VERSION {
        return Err(Refusal::WrongVersion);
    }
    if bytes.len() < layout.size || (exact && bytes.len() != layout.size) {
        return Err(Refusal::WrongSize);
    }
    Ok(())
}

/// A decoded stylus pose message.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PoseMsg {
    /// The client's sequence number (echoed in the force).
    pub seq: u32,
    /// The client's clock when it sent the pose (ns; opaque to the server, echoed).
    pub client_time_ns: u64,
    /// The pose.
    pub pose: Pose,
}

/// Encodes a pose message.
#[must_use]
pub fn encode_pose(msg: &PoseMsg) -> [u8; POSE.size] {
    let mut buf = [0u8; POSE.size];
    let mut w = Writer(&mut buf);
    w.header(&POSE, if msg.pose.drill_on { flags::DRILL_ON } else { 0 });
    w.u32(4, msg.seq);
    w.u64(8, msg.client_time_ns);
    for i in 0..3 {
        w.f64(16 + 8 * i, msg.pose.position_m[i]);
    }
    let q = msg.pose.orientation.quaternion();
    for (i, v) in [q.w, q.i, q.j, q.k].into_iter().enumerate() {
        w.f32(40 + 4 * i, v);
    }
    w.f32(56, msg.pose.spindle_rpm);
    buf
}

/// Decodes a pose message, refusing a wrong size or version and non-finite values.
///
/// # Errors
/// The [`Refusal`] that applies.
pub fn decode_pose(bytes: &[u8]) -> Result<PoseMsg, Refusal> {
    check(&POSE, bytes, true)?;
    let position = [rd_f64(bytes, 16), rd_f64(bytes, 24), rd_f64(bytes, 32)];
    let quat = [rd_f32(bytes, 40), rd_f32(bytes, 44), rd_f32(bytes, 48), rd_f32(bytes, 52)];
    let rpm = rd_f32(bytes, 56);
    let norm2: f64 = quat.iter().map(|x| x * x).sum();
    if !position.iter().chain(&quat).all(|x| x.is_finite()) || !rpm.is_finite() || rpm < 0.0 || norm2 < 1e-12 {
        return Err(Refusal::NonFinite);
    }
    let drill_on = rd_u16(bytes, 2) & flags::DRILL_ON != 0;
    Ok(PoseMsg {
        seq: rd_u32(bytes, 4),
        client_time_ns: rd_u64(bytes, 8),
        pose: Pose::new(position, quat, drill_on, rpm),
    })
}

/// The per-tick force message.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct ForceMsg {
    /// Header flags ([`flags`]).
    pub flags: u16,
    /// Sequence number of the pose used this tick.
    pub pose_seq: u32,
    /// That pose's client time (ns), echoed.
    pub pose_client_time_ns: u64,
    /// The session's tick count.
    pub tick: u64,
    /// The force rendered on the device (N): bone feedback plus mixed guidance, after the device
    /// limits.
    pub force_n: Vector3<f64>,
    /// The guidance share mixed into it (N).
    pub guidance_n: Vector3<f64>,
    /// Drill tip (proxy burr centre) (m).
    pub tip_m: Vector3<f64>,
    /// Depth along A→B (m).
    pub depth_m: f64,
    /// Lateral deviation from the path (m).
    pub deviation_m: f64,
    /// Drill-tip temperature (°C).
    pub temperature_c: f64,
    /// Deepest plunge so far (m).
    pub plunge_depth_m: f64,
    /// Layer id at the burr's front.
    pub layer: u8,
    /// Breakthroughs so far.
    pub breakthroughs: u16,
}

/// Encodes a force message. Inlined where it is called: every pose's thread encodes its force
/// (`transport::comm::put_force`), so the call stays out of the 1 kHz path whatever module the
/// caller is in.
#[must_use]
#[inline]
pub fn encode_force(m: &ForceMsg) -> [u8; FORCE.size] {
    let mut buf = [0u8; FORCE.size];
    let mut w = Writer(&mut buf);
    w.header(&FORCE, m.flags);
    w.u32(4, m.pose_seq);
    w.u64(8, m.pose_client_time_ns);
    w.u64(16, m.tick);
    w.force_f32(24, &m.force_n);
    w.force_f32(36, &m.guidance_n);
    w.vec3_f32(48, &m.tip_m);
    w.f32(60, m.depth_m);
    w.f32(64, m.deviation_m);
    w.f32(68, m.temperature_c);
    w.f32(72, m.plunge_depth_m);
    w.0[76] = m.layer;
    w.u16(78, m.breakthroughs);
    buf
}

/// The 10 Hz guidance message.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct GuidanceMsg {
    /// Header flags (bit 0: mixed into the force).
    pub flags: u16,
    /// The model window's sequence number.
    pub window_seq: u32,
    /// Client time (ns) of the newest pose in that window, echoed.
    pub pose_client_time_ns: u64,
    /// Session tick at which the guidance took effect.
    pub tick: u64,
    /// The model's predicted expert force (N).
    pub predicted_force_n: Vector3<f64>,
    /// Guidance: predicted expert force − the trainee's force feedback at the reply (N).
    pub guidance_n: Vector3<f64>,
    /// Model query round trip (s).
    pub model_latency_s: f64,
    /// Guidance gain in effect.
    pub gain: f64,
}

/// Encodes a guidance message.
#[must_use]
pub fn encode_guidance(m: &GuidanceMsg) -> [u8; GUIDANCE.size] {
    let mut buf = [0u8; GUIDANCE.size];
    let mut w = Writer(&mut buf);
    w.header(&GUIDANCE, m.flags);
    w.u32(4, m.window_seq);
    w.u64(8, m.pose_client_time_ns);
    w.u64(16, m.tick);
    w.vec3_f32(24, &m.predicted_force_n);
    w.force_f32(36, &m.guidance_n); // a share of the hand's force: never over its cap on the wire
    w.f32(48, m.model_latency_s);
    w.f32(52, m.gain);
    buf
}

/// The 10 Hz state message.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct StateMsg {
    /// Header flags ([`flags`]).
    pub flags: u16,
    /// Record number in the session (1 for the first record).
    pub record_seq: u32,
    /// Session time (s).
    pub time_s: f64,
    /// The nine record features, in record order.
    pub features: [f64; FEATURE_COUNT],
    /// Bone mass removed (kg).
    pub removed_mass_kg: f64,
    /// Bone volume removed (m³).
    pub removed_volume_m3: f64,
    /// Peak drill-tip temperature (°C).
    pub peak_temperature_c: f64,
    /// Time the tip spent above 47 °C (s).
    pub time_above_47_s: f64,
    /// Thrust (N, physical).
    pub thrust_n: f64,
    /// Spindle speed (rpm).
    pub spindle_rpm: f64,
    /// Deepest plunge (m).
    pub plunge_depth_m: f64,
    /// Breakthroughs so far.
    pub breakthroughs: u16,
    /// Poses refused by the session (non-finite after decoding).
    pub rejected_poses: u32,
    /// Lateral deviation from the path (m).
    pub deviation_m: f64,
    /// Guidance gain in effect.
    pub guidance_gain: f64,
}

/// Encodes a state message.
#[must_use]
pub fn encode_state(m: &StateMsg) -> [u8; STATE.size] {
    let mut buf = [0u8; STATE.size];
    let mut w = Writer(&mut buf);
    w.header(&STATE, m.flags);
    w.u32(4, m.record_seq);
    w.f64(8, m.time_s);
    for (i, v) in m.features.iter().enumerate() {
        w.f32(16 + 4 * i, *v);
    }
    for (at, v) in [
        (52, m.removed_mass_kg),
        (56, m.removed_volume_m3),
        (60, m.peak_temperature_c),
        (64, m.time_above_47_s),
        (68, m.thrust_n),
        (72, m.spindle_rpm),
        (76, m.plunge_depth_m),
        (88, m.deviation_m),
        (92, m.guidance_gain),
    ] {
        w.f32(at, v);
    }
    w.u16(80, m.breakthroughs);
    w.u32(84, m.rejected_poses);
    buf
}

/// Encodes a model query for one window of `WINDOW_RECORDS` records (oldest first), as entry 0.
#[must_use]
pub fn encode_predict(window_seq: u32, window: &[[f32; FEATURE_COUNT]; WINDOW_RECORDS]) -> Vec<u8> {
    let mut buf = Vec::with_capacity(PREDICT.size);
    push_predict(&mut buf, 0, window_seq, window);
    buf
}

/// Appends one window of a model query to `out` (a query holds up to [`MAX_QUERY_WINDOWS`],
/// `entry` 0, 1, … in order).
pub fn push_predict(out: &mut Vec<u8>, entry: u32, window_seq: u32, window: &[[f32; FEATURE_COUNT]; WINDOW_RECORDS]) {
    let start = out.len();
    out.resize(start + PREDICT.size, 0);
    let buf = &mut out[start..];
    let mut w = Writer(buf);
    w.header(&PREDICT, 0);
    w.u32(4, window_seq);
    w.u16(8, WINDOW_RECORDS as u16);
    w.u16(10, FEATURE_COUNT as u16);
    w.u32(12, entry);
    for (r, row) in window.iter().enumerate() {
        for (c, v) in row.iter().enumerate() {
            let at = 16 + 4 * (r * FEATURE_COUNT + c);
            buf[at..at + 4].copy_from_slice(&v.to_le_bytes());
        }
    }
}

/// A decoded model reply.
#[derive(Debug, Clone, PartialEq)]
pub struct Prediction {
    /// The query's window sequence number.
    pub window_seq: u32,
    /// Which of the query's windows this answers (its `entry`).
    pub entry: u32,
    /// Predicted expert force (N).
    pub force_n: Vector3<f64>,
    /// The model's inference time (s).
    pub inference_s: f64,
    /// The model's id.
    pub model_id: String,
}

/// Decodes a model reply that holds one prediction.
///
/// # Errors
/// The [`Refusal`] that applies.
pub fn decode_prediction(bytes: &[u8]) -> Result<Prediction, Refusal> {
    let (p, rest) = split_prediction(bytes)?;
    if rest.is_empty() {
        Ok(p)
    } else {
        Err(Refusal::WrongSize)
    }
}

/// The predictions of a model reply (one or more back to back, at most [`MAX_QUERY_WINDOWS`]),
/// in order; the first that is refused ends them.
#[must_use]
pub fn decode_predictions(bytes: &[u8]) -> Predictions<'_> {
    Predictions { rest: bytes, left: MAX_QUERY_WINDOWS }
}

/// The iterator [`decode_predictions`] returns.
#[derive(Debug)]
pub struct Predictions<'a> {
    rest: &'a [u8],
    left: usize,
}

impl Iterator for Predictions<'_> {
    type Item = Result<Prediction, Refusal>;

    fn next(&mut self) -> Option<Self::Item> {
        if self.rest.is_empty() {
            return None;
        }
        if self.left == 0 {
            self.rest = &[];
            return Some(Err(Refusal::Oversized));
        }
        self.left -= 1;
        match split_prediction(self.rest) {
            Ok((p, rest)) => {
                self.rest = rest;
                Some(Ok(p))
            }
            Err(r) => {
                self.rest = &[];
                Some(Err(r))
            }
        }
    }
}

/// The first prediction of `bytes` and what follows it.
fn split_prediction(bytes: &[u8]) -> Result<(Prediction, &[u8]), Refusal> {
    check(&PREDICTION, &bytes[..bytes.len().min(PREDICTION.size)], false)?;
    let id_len = rd_u16(bytes, 24) as usize;
    let size = PREDICTION.size + id_len;
    if bytes.len() < size || size > MAX_PAYLOAD_BYTES {
        return Err(if size > MAX_PAYLOAD_BYTES { Refusal::Oversized } else { Refusal::WrongSize });
    }
    let force_n = Vector3::new(rd_f32(bytes, 8), rd_f32(bytes, 12), rd_f32(bytes, 16));
    let inference_s = rd_f32(bytes, 20);
    if !force_n.iter().all(|x| x.is_finite()) || !inference_s.is_finite() {
        return Err(Refusal::NonFinite);
    }
    let model_id = String::from_utf8_lossy(&bytes[PREDICTION.size..size]).into_owned();
    let p = Prediction { window_seq: rd_u32(bytes, 4), entry: rd_u32(bytes, 28), force_n, inference_s, model_id };
    Ok((p, &bytes[size..]))
}

/// One tick of the recorders' 1 kHz stream ([`TICK_ROW`]).
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct TickRow {
    /// The session's tick count (as in the force message).
    pub tick: u64,
    /// Sequence number of the pose the tick used (0: it had none, before the first pose or since
    /// a reset).
    pub pose_seq: u32,
    /// The force message's flags ([`flags`]).
    pub flags: u16,
    /// The pose's burr centre (m, world; zero before the first pose).
    pub position_m: [f64; 3],
    /// The pose's orientation quaternion, w, x, y, z (zero before the first pose).
    pub orientation_wxyz: [f64; 4],
    /// The pose's spindle speed (rpm).
    pub spindle_rpm: f64,
    /// The force rendered on the device (N).
    pub force_n: Vector3<f64>,
    /// Its guidance share (N).
    pub guidance_n: Vector3<f64>,
}

/// Rows a [`TICKS`] payload may carry: a decoder refuses a longer batch unread (the server sends
/// one per 100 ticks).
pub const MAX_TICK_ROWS: usize = 1000;

/// A batch of ticks being filled: the [`TICKS`] payload, its rows appended in place.
#[derive(Debug, Clone)]
pub struct TickBatch {
    buf: Vec<u8>,
    rows: usize,
}

impl TickBatch {
    /// An empty batch with room for `rows` rows (no allocation until more are pushed).
    #[must_use]
    pub fn with_capacity(rows: usize) -> Self {
        let mut buf = Vec::with_capacity(TICKS.size + rows * TICK_ROW.size);
        buf.resize(TICKS.size, 0);
        Writer(&mut buf).header(&TICKS, 0);
        Self { buf, rows: 0 }
    }

    /// Rows in the batch.
    #[must_use]
    pub fn len(&self) -> usize {
        self.rows
    }

    /// Whether the batch has no rows.
    #[must_use]
    pub fn is_empty(&self) -> bool {
        self.rows == 0
    }

    /// Appends one row.
    pub fn push(&mut self, r: &TickRow) {
        if self.rows == 0 {
            Writer(&mut self.buf).u64(8, r.tick);
        }
        let at = self.buf.len();
        self.buf.resize(at + TICK_ROW.size, 0);
        let mut w = Writer(&mut self.buf[at..]);
        w.u64(0, r.tick);
        w.u32(8, r.pose_seq);
        w.u16(12, r.flags);
        for (i, v) in r.position_m.iter().enumerate() {
            w.f64(16 + 8 * i, *v);
        }
        for (i, v) in r.orientation_wxyz.iter().enumerate() {
            w.f32(40 + 4 * i, *v);
        }
        w.f32(56, r.spindle_rpm);
        w.force_f32(60, &r.force_n);
        w.force_f32(72, &r.guidance_n);
        self.rows += 1;
        Writer(&mut self.buf).u32(4, self.rows as u32);
    }

    /// The payload, leaving an empty batch of the same capacity in its place.
    pub fn take(&mut self) -> Vec<u8> {
        let fresh = Self::with_capacity(self.buf.capacity().saturating_sub(TICKS.size) / TICK_ROW.size);
        let out = std::mem::replace(self, fresh);
        out.buf
    }
}

/// Decodes a [`TICKS`] payload into its rows, refusing a wrong kind or version, a size that does
/// not match its row count, more than [`MAX_TICK_ROWS`] rows, and non-finite values.
///
/// # Errors
/// The [`Refusal`] that applies.
pub fn decode_ticks(bytes: &[u8]) -> Result<Vec<TickRow>, Refusal> {
    if bytes.len() > TICKS.size + MAX_TICK_ROWS * TICK_ROW.size {
        return Err(Refusal::Oversized);
    }
    if bytes.len() < 2 {
        return Err(Refusal::WrongSize);
    }
    if bytes[0] != TICKS.kind || bytes[1] != VERSION {
        return Err(Refusal::WrongVersion);
    }
    if bytes.len() < TICKS.size {
        return Err(Refusal::WrongSize);
    }
    let rows = rd_u32(bytes, 4) as usize;
    if rows > MAX_TICK_ROWS || bytes.len() != TICKS.size + rows * TICK_ROW.size {
        return Err(Refusal::WrongSize);
    }
    let mut out = Vec::with_capacity(rows);
    for b in bytes[TICKS.size..].chunks_exact(TICK_ROW.size) {
        let v3 = |at: usize| Vector3::new(rd_f32(b, at), rd_f32(b, at + 4), rd_f32(b, at + 8));
        let r = TickRow {
            tick: rd_u64(b, 0),
            pose_seq: rd_u32(b, 8),
            flags: rd_u16(b, 12),
            position_m: [rd_f64(b, 16), rd_f64(b, 24), rd_f64(b, 32)],
            orientation_wxyz: [rd_f32(b, 40), rd_f32(b, 44), rd_f32(b, 48), rd_f32(b, 52)],
            spindle_rpm: rd_f32(b, 56),
            force_n: v3(60),
            guidance_n: v3(72),
        };
        let finite = r.position_m.iter().chain(&r.orientation_wxyz).all(|x| x.is_finite())
            && r.spindle_rpm.is_finite()
            && r.force_n.iter().chain(r.guidance_n.iter()).all(|x| x.is_finite());
        if !finite {
            return Err(Refusal::NonFinite);
        }
        out.push(r);
    }
    Ok(out)
}

/// [`decode_pose`] with the refusal as a [`SimError`].
///
/// # Errors
/// A payload that does not follow the pose layout.
pub fn parse_pose(bytes: &[u8]) -> SimResult<PoseMsg> {
    decode_pose(bytes).map_err(|r| r.error("pose", bytes))
}

/// [`decode_prediction`] with the refusal as a [`SimError`].
///
/// # Errors
/// A payload that does not follow the prediction layout.
pub fn parse_prediction(bytes: &[u8]) -> SimResult<Prediction> {
    decode_prediction(bytes).map_err(|r| r.error("prediction", bytes))
}
