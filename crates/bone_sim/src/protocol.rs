//! Wire payloads of the real-time server: compact, versioned, little-endian binary layouts.
//!
//! Every layout is declared once here as a [`Layout`] table (field, type, byte offset, count,
//! unit). The encoders and decoders below follow those tables (a test checks each one), Python
//! builds its `struct` formats from the same tables (`dhg.core.protocol`), and `docs/protocol.md`
//! documents them (a test checks the document against the tables).
//!
//! Every payload starts with the same 4-byte header: `kind: u8`, `version: u8`, `flags: u16`.
//! Positions are in the world (LPS) frame in m, forces in N, times in s unless a name says `_ns`.

use nalgebra::Vector3;

use crate::error::{SimError, SimResult};
use crate::record::FEATURE_COUNT;
use crate::session::Pose;

/// The protocol version every layout here carries in its header.
pub const VERSION: u8 = 1;
/// Records in one model window (the paper's window of 20 records at 10 Hz).
pub const WINDOW_RECORDS: usize = 20;
/// The longest payload the server reads; anything longer is refused unread.
pub const MAX_PAYLOAD_BYTES: usize = 4096;

/// One field of a layout.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Field {
    /// Field name (with a unit suffix where it has one).
    pub name: &'static str,
    /// Element type: `u8`, `u16`, `u32`, `u64`, `f32` or `f64` (little-endian).
    pub ty: &'static str,
    /// Byte offset from the start of the payload.
    pub offset: usize,
    /// Number of elements (1 for a scalar).
    pub count: usize,
    /// Unit, or `1` for counts, ids and flags.
    pub unit: &'static str,
}

/// A payload layout.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Layout {
    /// Message name.
    pub name: &'static str,
    /// The `kind` byte of the header.
    pub kind: u8,
    /// Size in bytes of the fixed part.
    pub size: usize,
    /// Fields in order.
    pub fields: &'static [Field],
}

const fn f(name: &'static str, ty: &'static str, offset: usize, count: usize, unit: &'static str) -> Field {
    Field { name, ty, offset, count, unit }
}

macro_rules! header {
    () => {
        [f("kind", "u8", 0, 1, "1"), f("version", "u8", 1, 1, "1"), f("flags", "u16", 2, 1, "1")]
    };
}

const fn concat<const A: usize, const B: usize, const N: usize>(a: [Field; A], b: [Field; B]) -> [Field; N] {
    let mut out = [f("", "", 0, 0, ""); N];
    let mut i = 0;
    while i < A {
        out[i] = a[i];
        i += 1;
    }
    while i < N {
        out[i] = b[i - A];
        i += 1;
    }
    out
}

const POSE_FIELDS: [Field; 9] = concat(
    header!(),
    [
        f("seq", "u32", 4, 1, "1"),
        f("client_time_ns", "u64", 8, 1, "ns"),
        f("position_m", "f64", 16, 3, "m"),
        f("orientation_wxyz", "f32", 40, 4, "1"),
        f("spindle_rpm", "f32", 56, 1, "rpm"),
        f("reserved", "u32", 60, 1, "1"),
    ],
);
/// Stylus pose, client → server, up to 1 kHz. Flags: bit 0 drill on.
pub const POSE: Layout = Layout { name: "pose", kind: 1, size: 64, fields: &POSE_FIELDS };

const FORCE_FIELDS: [Field; 16] = concat(
    header!(),
    [
        f("pose_seq", "u32", 4, 1, "1"),
        f("pose_client_time_ns", "u64", 8, 1, "ns"),
        f("tick", "u64", 16, 1, "1"),
        f("force_n", "f32", 24, 3, "N"),
        f("guidance_n", "f32", 36, 3, "N"),
        f("tip_m", "f32", 48, 3, "m"),
        f("depth_m", "f32", 60, 1, "m"),
        f("deviation_m", "f32", 64, 1, "m"),
        f("temperature_c", "f32", 68, 1, "°C"),
        f("plunge_depth_m", "f32", 72, 1, "m"),
        f("layer", "u8", 76, 1, "1"),
        f("reserved", "u8", 77, 1, "1"),
        f("breakthroughs", "u16", 78, 1, "1"),
    ],
);
/// Rendered force, server → client, every tick (1 kHz). Flags: [`flags`].
pub const FORCE: Layout = Layout { name: "force", kind: 2, size: 80, fields: &FORCE_FIELDS };

const GUIDANCE_FIELDS: [Field; 10] = concat(
    header!(),
    [
        f("window_seq", "u32", 4, 1, "1"),
        f("pose_client_time_ns", "u64", 8, 1, "ns"),
        f("tick", "u64", 16, 1, "1"),
        f("predicted_force_n", "f32", 24, 3, "N"),
        f("guidance_n", "f32", 36, 3, "N"),
        f("model_latency_s", "f32", 48, 1, "s"),
        f("gain", "f32", 52, 1, "1"),
    ],
);
/// Guidance, server → client, at 10 Hz while the model answers. Flags: bit 0 mixed into the force
/// (gain > 0).
pub const GUIDANCE: Layout = Layout { name: "guidance", kind: 3, size: 56, fields: &GUIDANCE_FIELDS };

const STATE_FIELDS: [Field; 18] = concat(
    header!(),
    [
        f("record_seq", "u32", 4, 1, "1"),
        f("time_s", "f64", 8, 1, "s"),
        f("features", "f32", 16, FEATURE_COUNT, "record"),
        f("removed_mass_kg", "f32", 52, 1, "kg"),
        f("removed_volume_m3", "f32", 56, 1, "m³"),
        f("peak_temperature_c", "f32", 60, 1, "°C"),
        f("time_above_47_s", "f32", 64, 1, "s"),
        f("thrust_n", "f32", 68, 1, "N"),
        f("spindle_rpm", "f32", 72, 1, "rpm"),
        f("plunge_depth_m", "f32", 76, 1, "m"),
        f("breakthroughs", "u16", 80, 1, "1"),
        f("reserved", "u16", 82, 1, "1"),
        f("rejected_poses", "u32", 84, 1, "1"),
        f("deviation_m", "f32", 88, 1, "m"),
        f("guidance_gain", "f32", 92, 1, "1"),
    ],
);
/// Session state, server → client, at 10 Hz: the record's nine features plus the drill status.
/// Flags: [`flags`].
pub const STATE: Layout = Layout { name: "state", kind: 4, size: 96, fields: &STATE_FIELDS };

const PREDICT_FIELDS: [Field; 8] = concat(
    header!(),
    [
        f("window_seq", "u32", 4, 1, "1"),
        f("rows", "u16", 8, 1, "1"),
        f("cols", "u16", 10, 1, "1"),
        f("reserved", "u32", 12, 1, "1"),
        f("window", "f32", 16, WINDOW_RECORDS * FEATURE_COUNT, "record"),
    ],
);
/// Model query, engine → model service: one window of records (rows × cols, row-major, oldest
/// first, columns in record order).
pub const PREDICT: Layout =
    Layout { name: "predict", kind: 5, size: 16 + 4 * WINDOW_RECORDS * FEATURE_COUNT, fields: &PREDICT_FIELDS };

const PREDICTION_FIELDS: [Field; 9] = concat(
    header!(),
    [
        f("window_seq", "u32", 4, 1, "1"),
        f("force_n", "f32", 8, 3, "N"),
        f("inference_s", "f32", 20, 1, "s"),
        f("model_id_len", "u16", 24, 1, "1"),
        f("reserved", "u16", 26, 1, "1"),
        f("reserved2", "u32", 28, 1, "1"),
    ],
);
/// Model reply, model service → engine: the predicted expert force, followed by `model_id_len`
/// bytes of UTF-8 model id.
pub const PREDICTION: Layout = Layout { name: "prediction", kind: 6, size: 32, fields: &PREDICTION_FIELDS };

/// Every layout, for the bindings and the documentation test.
pub const LAYOUTS: [Layout; 6] = [POSE, FORCE, GUIDANCE, STATE, PREDICT, PREDICTION];

/// Flag bits of the force and state headers.
pub mod flags {
    /// The drill is running.
    pub const DRILL_ON: u16 = 1 << 0;
    /// The burr touches bone.
    pub const IN_CONTACT: u16 = 1 << 1;
    /// The burr is cutting.
    pub const CUTTING: u16 = 1 << 2;
    /// A plunge after a breakthrough is under way.
    pub const PLUNGING: u16 = 1 << 3;
    /// No fresh pose for the device's stale time: the force is ramping to zero.
    pub const STALE: u16 = 1 << 4;
    /// The model answered recently (guidance is live).
    pub const MODEL_AVAILABLE: u16 = 1 << 5;
    /// Guidance is mixed into the rendered force (gain > 0 and non-zero guidance).
    pub const GUIDANCE_ACTIVE: u16 = 1 << 6;

    /// Every flag by its name in `docs/protocol.md` (Python's `dhg.core.protocol.FLAGS` is this).
    pub const ALL: [(&str, u16); 7] = [
        ("drill_on", DRILL_ON),
        ("in_contact", IN_CONTACT),
        ("cutting", CUTTING),
        ("plunging", PLUNGING),
        ("stale", STALE),
        ("model_available", MODEL_AVAILABLE),
        ("guidance_active", GUIDANCE_ACTIVE),
    ];
}

/// A little-endian writer into a fixed buffer, at the offsets the layouts give.
struct Writer<'a>(&'a mut [u8]);

impl Writer<'_> {
    fn header(&mut self, layout: &Layout, flags: u16) {
        self.0[0] = layout.kind;
        self.0[1] = VERSION;
        self.u16(2, flags);
    }
    fn u16(&mut self, at: usize, v: u16) {
        self.0[at..at + 2].copy_from_slice(&v.to_le_bytes());
    }
    fn u32(&mut self, at: usize, v: u32) {
        self.0[at..at + 4].copy_from_slice(&v.to_le_bytes());
    }
    fn u64(&mut self, at: usize, v: u64) {
        self.0[at..at + 8].copy_from_slice(&v.to_le_bytes());
    }
    fn f32(&mut self, at: usize, v: f64) {
        self.0[at..at + 4].copy_from_slice(&(v as f32).to_le_bytes());
    }
    fn f64(&mut self, at: usize, v: f64) {
        self.0[at..at + 8].copy_from_slice(&v.to_le_bytes());
    }
    fn vec3_f32(&mut self, at: usize, v: &Vector3<f64>) {
        for (i, x) in v.iter().enumerate() {
            self.f32(at + 4 * i, *x);
        }
    }
}

fn rd<const N: usize>(b: &[u8], at: usize) -> [u8; N] {
    let mut out = [0; N];
    out.copy_from_slice(&b[at..at + N]);
    out
}
fn rd_u16(b: &[u8], at: usize) -> u16 {
    u16::from_le_bytes(rd(b, at))
}
fn rd_u32(b: &[u8], at: usize) -> u32 {
    u32::from_le_bytes(rd(b, at))
}
fn rd_u64(b: &[u8], at: usize) -> u64 {
    u64::from_le_bytes(rd(b, at))
}
fn rd_f32(b: &[u8], at: usize) -> f64 {
    f64::from(f32::from_le_bytes(rd(b, at)))
}
fn rd_f64(b: &[u8], at: usize) -> f64 {
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

fn check(layout: &Layout, bytes: &[u8], exact: bool) -> Result<(), Refusal> {
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

/// Encodes a force message.
#[must_use]
pub fn encode_force(m: &ForceMsg) -> [u8; FORCE.size] {
    let mut buf = [0u8; FORCE.size];
    let mut w = Writer(&mut buf);
    w.header(&FORCE, m.flags);
    w.u32(4, m.pose_seq);
    w.u64(8, m.pose_client_time_ns);
    w.u64(16, m.tick);
    w.vec3_f32(24, &m.force_n);
    w.vec3_f32(36, &m.guidance_n);
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
    w.vec3_f32(36, &m.guidance_n);
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

/// Encodes a model query for one window of `WINDOW_RECORDS` records (oldest first).
#[must_use]
pub fn encode_predict(window_seq: u32, window: &[[f32; FEATURE_COUNT]; WINDOW_RECORDS]) -> Vec<u8> {
    let mut buf = vec![0u8; PREDICT.size];
    let mut w = Writer(&mut buf);
    w.header(&PREDICT, 0);
    w.u32(4, window_seq);
    w.u16(8, WINDOW_RECORDS as u16);
    w.u16(10, FEATURE_COUNT as u16);
    for (r, row) in window.iter().enumerate() {
        for (c, v) in row.iter().enumerate() {
            let at = 16 + 4 * (r * FEATURE_COUNT + c);
            buf[at..at + 4].copy_from_slice(&v.to_le_bytes());
        }
    }
    buf
}

/// A decoded model reply.
#[derive(Debug, Clone, PartialEq)]
pub struct Prediction {
    /// The query's window sequence number.
    pub window_seq: u32,
    /// Predicted expert force (N).
    pub force_n: Vector3<f64>,
    /// The model's inference time (s).
    pub inference_s: f64,
    /// The model's id.
    pub model_id: String,
}

/// Decodes a model reply.
///
/// # Errors
/// The [`Refusal`] that applies.
pub fn decode_prediction(bytes: &[u8]) -> Result<Prediction, Refusal> {
    check(&PREDICTION, bytes, false)?;
    let id_len = rd_u16(bytes, 24) as usize;
    if bytes.len() != PREDICTION.size + id_len {
        return Err(Refusal::WrongSize);
    }
    let force_n = Vector3::new(rd_f32(bytes, 8), rd_f32(bytes, 12), rd_f32(bytes, 16));
    let inference_s = rd_f32(bytes, 20);
    if !force_n.iter().all(|x| x.is_finite()) || !inference_s.is_finite() {
        return Err(Refusal::NonFinite);
    }
    let model_id = String::from_utf8_lossy(&bytes[PREDICTION.size..]).into_owned();
    Ok(Prediction { window_seq: rd_u32(bytes, 4), force_n, inference_s, model_id })
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

#[cfg(test)]
#[allow(clippy::float_cmp)] // exact round trips of exactly representable values
mod tests {
    use super::*;

    fn size_of(ty: &str) -> usize {
        match ty {
            "u8" => 1,
            "u16" => 2,
            "u32" | "f32" => 4,
            "u64" | "f64" => 8,
            other => panic!("unknown type {other}"),
        }
    }

    #[test]
    fn layouts_are_contiguous_and_aligned() {
        for l in LAYOUTS {
            let mut at = 0;
            for fl in l.fields {
                assert_eq!(fl.offset, at, "{}.{} offset", l.name, fl.name);
                assert_eq!(fl.offset % size_of(fl.ty), 0, "{}.{} is unaligned", l.name, fl.name);
                at += size_of(fl.ty) * fl.count;
            }
            assert_eq!(at, l.size, "{} size", l.name);
        }
        let kinds: std::collections::BTreeSet<u8> = LAYOUTS.iter().map(|l| l.kind).collect();
        assert_eq!(kinds.len(), LAYOUTS.len(), "kinds must be unique");
    }

    fn field(l: &Layout, name: &str) -> Field {
        *l.fields.iter().find(|x| x.name == name).unwrap()
    }

    #[test]
    fn pose_round_trips_and_refuses_bad_payloads() {
        let msg = PoseMsg {
            seq: 7,
            client_time_ns: 123_456_789,
            pose: Pose::new([0.01, -0.02, 0.1], [1.0, 0.0, 0.0, 0.0], true, 1200.0),
        };
        let bytes = encode_pose(&msg);
        assert_eq!(rd_f64(&bytes, field(&POSE, "position_m").offset + 8), -0.02);
        assert_eq!(rd_f32(&bytes, field(&POSE, "spindle_rpm").offset), 1200.0);
        assert_eq!(decode_pose(&bytes).unwrap(), msg);
        assert_eq!(decode_pose(&bytes[..63]), Err(Refusal::WrongSize));
        let mut long = bytes.to_vec();
        long.push(0);
        assert_eq!(decode_pose(&long), Err(Refusal::WrongSize));
        assert_eq!(decode_pose(&vec![1u8; MAX_PAYLOAD_BYTES + 1]), Err(Refusal::Oversized));
        let mut v2 = bytes;
        v2[1] = 2;
        assert_eq!(decode_pose(&v2), Err(Refusal::WrongVersion));
        let mut nan = bytes;
        nan[16..24].copy_from_slice(&f64::NAN.to_le_bytes());
        assert_eq!(decode_pose(&nan), Err(Refusal::NonFinite));
        let mut zero_q = bytes;
        zero_q[40..56].fill(0);
        assert_eq!(decode_pose(&zero_q), Err(Refusal::NonFinite));
        let err = parse_pose(&bytes[..10]).unwrap_err().to_string();
        assert!(err.contains("pose") && err.contains("10 bytes"), "{err}");
    }

    #[test]
    fn force_state_guidance_follow_their_tables() {
        let m = ForceMsg {
            flags: flags::DRILL_ON | flags::CUTTING,
            pose_seq: 9,
            pose_client_time_ns: 42,
            tick: 1000,
            force_n: Vector3::new(0.5, -1.0, 2.0),
            guidance_n: Vector3::new(0.25, 0.0, -0.5),
            tip_m: Vector3::new(0.01, 0.02, 0.03),
            depth_m: 0.004,
            deviation_m: 0.001,
            temperature_c: 40.0,
            plunge_depth_m: 0.002,
            layer: 2,
            breakthroughs: 3,
        };
        let b = encode_force(&m);
        assert_eq!(rd_u16(&b, 2), flags::DRILL_ON | flags::CUTTING);
        assert_eq!(rd_u64(&b, field(&FORCE, "pose_client_time_ns").offset), 42);
        assert_eq!(rd_f32(&b, field(&FORCE, "force_n").offset + 8), 2.0);
        assert_eq!(rd_f32(&b, field(&FORCE, "guidance_n").offset + 8), -0.5);
        assert_eq!(rd_f32(&b, field(&FORCE, "temperature_c").offset), 40.0);
        assert_eq!(b[field(&FORCE, "layer").offset], 2);
        assert_eq!(rd_u16(&b, field(&FORCE, "breakthroughs").offset), 3);

        let mut s = StateMsg { record_seq: 5, time_s: 0.5, guidance_gain: 0.5, ..StateMsg::default() };
        s.features[8] = 37.0;
        let b = encode_state(&s);
        assert_eq!(rd_f64(&b, field(&STATE, "time_s").offset), 0.5);
        assert_eq!(rd_f32(&b, field(&STATE, "features").offset + 32), 37.0);
        assert_eq!(rd_f32(&b, field(&STATE, "guidance_gain").offset), 0.5);

        let g = GuidanceMsg { window_seq: 4, model_latency_s: 0.25, ..GuidanceMsg::default() };
        let b = encode_guidance(&g);
        assert_eq!(rd_u32(&b, 4), 4);
        assert_eq!(rd_f32(&b, field(&GUIDANCE, "model_latency_s").offset), 0.25);
    }

    #[test]
    fn predict_and_prediction_round_trip() {
        let mut window = [[0f32; FEATURE_COUNT]; WINDOW_RECORDS];
        window[19][8] = 41.5;
        let b = encode_predict(3, &window);
        assert_eq!(b.len(), PREDICT.size);
        let last = field(&PREDICT, "window").offset + 4 * (19 * FEATURE_COUNT + 8);
        assert_eq!(rd_f32(&b, last), 41.5);

        let mut reply = vec![0u8; PREDICTION.size];
        let mut w = Writer(&mut reply);
        w.header(&PREDICTION, 0);
        w.u32(4, 3);
        w.vec3_f32(8, &Vector3::new(1.0, 2.0, 3.0));
        w.u16(24, 2);
        reply.extend_from_slice(b"m1");
        let p = decode_prediction(&reply).unwrap();
        assert_eq!((p.window_seq, p.model_id.as_str()), (3, "m1"));
        assert_eq!(p.force_n, Vector3::new(1.0, 2.0, 3.0));
        assert_eq!(decode_prediction(&reply[..33]), Err(Refusal::WrongSize));
    }
}
