//! The layout tables: every payload's fields, types, offsets and units, declared once.

use super::WINDOW_RECORDS;
use crate::record::FEATURE_COUNT;

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
        f("entry", "u32", 12, 1, "1"),
        f("window", "f32", 16, WINDOW_RECORDS * FEATURE_COUNT, "record"),
    ],
);
/// Model query, engine → model service: one window of records (rows × cols, row-major, oldest
/// first, columns in record order). A query holds 1 to [`MAX_QUERY_WINDOWS`] of them back to
/// back, `entry` 0, 1, … in order.
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
        f("entry", "u32", 28, 1, "1"),
    ],
);
/// Model reply, model service → engine: the predicted expert force, followed by `model_id_len`
/// bytes of UTF-8 model id. A reply holds one or more of them back to back, each naming the
/// `entry` of the query's window it answers.
pub const PREDICTION: Layout = Layout { name: "prediction", kind: 6, size: 32, fields: &PREDICTION_FIELDS };

const TICKS_FIELDS: [Field; 6] = concat(
    header!(),
    [f("rows", "u32", 4, 1, "1"), f("first_tick", "u64", 8, 1, "1"), f("reserved", "u64", 16, 1, "1")],
);
/// The 1 kHz stream for recorders, server → client, at 10 Hz: `rows` [`TICK_ROW`]s (oldest
/// first) follow the fixed part, one per tick since the last batch. Unlike `force` it is
/// published for recovery (a recorder that missed a batch asks the server's cache for it).
pub const TICKS: Layout = Layout { name: "ticks", kind: 7, size: 24, fields: &TICKS_FIELDS };

const TICK_ROW_FIELDS: [Field; 10] = [
    f("tick", "u64", 0, 1, "1"),
    f("pose_seq", "u32", 8, 1, "1"),
    f("flags", "u16", 12, 1, "1"),
    f("reserved", "u16", 14, 1, "1"),
    f("position_m", "f64", 16, 3, "m"),
    f("orientation_wxyz", "f32", 40, 4, "1"),
    f("spindle_rpm", "f32", 56, 1, "rpm"),
    f("force_n", "f32", 60, 3, "N"),
    f("guidance_n", "f32", 72, 3, "N"),
    f("reserved2", "u32", 84, 1, "1"),
];
/// One tick of a [`TICKS`] batch (no header of its own; kind 0 is never a payload): the pose the
/// tick used (burr centre, orientation w, x, y, z, spindle speed; zero before the session's
/// first pose, `pose_seq` 0), the force rendered on the device and its guidance share, and the
/// force's flags ([`flags`]).
pub const TICK_ROW: Layout = Layout { name: "tick_row", kind: 0, size: 88, fields: &TICK_ROW_FIELDS };

/// Every layout, for the bindings and the documentation test.
pub const LAYOUTS: [Layout; 8] = [POSE, FORCE, GUIDANCE, STATE, PREDICT, PREDICTION, TICKS, TICK_ROW];
