#![allow(clippy::float_cmp)] // exact round trips of exactly representable values

use nalgebra::Vector3;

use super::codec::{rd_f32, rd_f64, rd_u16, rd_u32, rd_u64, Writer};
use super::*;
use crate::record::FEATURE_COUNT;
use crate::session::Pose;

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

/// A prediction for `entry` with a model id of `id`.
fn prediction(entry: u32, window_seq: u32, z: f64, id: &[u8]) -> Vec<u8> {
    let mut reply = vec![0u8; PREDICTION.size];
    let mut w = Writer(&mut reply);
    w.header(&PREDICTION, 0);
    w.u32(4, window_seq);
    w.vec3_f32(8, &Vector3::new(0.0, 0.0, z));
    w.u16(24, id.len() as u16);
    w.u32(28, entry);
    reply.extend_from_slice(id);
    reply
}

#[test]
fn a_query_holds_windows_back_to_back_and_a_reply_their_predictions() {
    let mut window = [[0f32; FEATURE_COUNT]; WINDOW_RECORDS];
    let mut q = Vec::new();
    for entry in 0..3 {
        window[0][0] = entry as f32;
        push_predict(&mut q, entry, 40 + entry, &window);
    }
    assert_eq!(q.len(), 3 * PREDICT.size);
    let at = |entry: usize, name: &str| entry * PREDICT.size + field(&PREDICT, name).offset;
    for entry in 0..3 {
        assert_eq!(rd_u32(&q, at(entry, "entry")), entry as u32);
        assert_eq!(rd_u32(&q, at(entry, "window_seq")), 40 + entry as u32);
        assert_eq!(rd_f32(&q, at(entry, "window")), entry as f64);
    }
    let mut one = Vec::new();
    push_predict(&mut one, 0, 7, &window);
    assert_eq!(encode_predict(7, &window), one);

    let reply = [prediction(2, 42, 1.5, b"m"), prediction(0, 40, -1.0, b"model-7")].concat();
    let got: Vec<_> = decode_predictions(&reply).collect::<Result<_, _>>().unwrap();
    assert_eq!(
        got.iter().map(|p| (p.entry, p.window_seq, p.force_n.z)).collect::<Vec<_>>(),
        [(2, 42, 1.5), (0, 40, -1.0)]
    );
    assert_eq!((got[0].model_id.as_str(), got[1].model_id.as_str()), ("m", "model-7"));
    // A reply of one prediction is what `decode_prediction` takes; two are too many for it.
    assert_eq!(decode_prediction(&reply), Err(Refusal::WrongSize));
    assert_eq!(decode_prediction(&reply[..=PREDICTION.size]).unwrap().entry, 2);
}

#[test]
fn a_refused_prediction_ends_the_reply_and_too_many_are_oversized() {
    let mut nan = prediction(1, 5, 0.0, b"");
    nan[8..12].copy_from_slice(&f32::NAN.to_le_bytes());
    let reply = [prediction(0, 4, 1.0, b""), nan, prediction(2, 6, 1.0, b"")].concat();
    let got: Vec<_> = decode_predictions(&reply).collect();
    assert_eq!(got.len(), 2);
    assert!(got[0].is_ok());
    assert_eq!(got[1], Err(Refusal::NonFinite));
    // A truncated last one, a wrong kind.
    let cut = [prediction(0, 4, 1.0, b"ab"), prediction(1, 5, 1.0, b"ab")].concat();
    let got: Vec<_> = decode_predictions(&cut[..cut.len() - 1]).collect();
    assert_eq!((got[0].is_ok(), got[1].clone()), (true, Err(Refusal::WrongSize)));
    let mut wrong = prediction(0, 4, 1.0, b"");
    wrong[0] = PREDICT.kind;
    assert_eq!(decode_predictions(&wrong).collect::<Vec<_>>(), [Err(Refusal::WrongVersion)]);
    // One more than a query may hold.
    let many: Vec<u8> = (0..=MAX_QUERY_WINDOWS as u32).flat_map(|e| prediction(e, e, 0.0, b"")).collect();
    let got: Vec<_> = decode_predictions(&many).collect();
    assert_eq!(got.len(), MAX_QUERY_WINDOWS + 1);
    assert!(got[..MAX_QUERY_WINDOWS].iter().all(Result::is_ok));
    assert_eq!(got[MAX_QUERY_WINDOWS], Err(Refusal::Oversized));
    assert_eq!(decode_predictions(&[]).count(), 0);
}

#[test]
fn ticks_batch_round_trips_and_refuses_bad_payloads() {
    let row = |tick: u64| TickRow {
        tick,
        pose_seq: 3,
        flags: flags::DRILL_ON,
        position_m: [0.01, -0.02, 0.1],
        orientation_wxyz: [1.0, 0.0, 0.0, 0.0],
        spindle_rpm: 1250.0,
        force_n: Vector3::new(0.5, -1.0, 2.0),
        guidance_n: Vector3::new(0.0, 0.25, -0.5),
    };
    let mut batch = TickBatch::with_capacity(4);
    assert!(batch.is_empty());
    for t in 7..10 {
        batch.push(&row(t));
    }
    assert_eq!(batch.len(), 3);
    let bytes = batch.take();
    assert!(batch.is_empty(), "take leaves an empty batch");
    assert_eq!(bytes.len(), TICKS.size + 3 * TICK_ROW.size);
    assert_eq!((bytes[0], bytes[1]), (TICKS.kind, VERSION));
    assert_eq!(rd_u32(&bytes, field(&TICKS, "rows").offset), 3);
    assert_eq!(rd_u64(&bytes, field(&TICKS, "first_tick").offset), 7);
    let second = TICKS.size + TICK_ROW.size;
    assert_eq!(rd_u64(&bytes, second + field(&TICK_ROW, "tick").offset), 8);
    assert_eq!(rd_f64(&bytes, second + field(&TICK_ROW, "position_m").offset + 8), -0.02);
    assert_eq!(rd_f32(&bytes, second + field(&TICK_ROW, "guidance_n").offset + 4), 0.25);
    assert_eq!(rd_u16(&bytes, second + field(&TICK_ROW, "flags").offset), flags::DRILL_ON);
    assert_eq!(decode_ticks(&bytes).unwrap(), vec![row(7), row(8), row(9)]);
    assert_eq!(decode_ticks(&bytes[..bytes.len() - 1]), Err(Refusal::WrongSize));
    assert_eq!(decode_ticks(&bytes[..TICKS.size - 1]), Err(Refusal::WrongSize));
    let mut lying = bytes.clone();
    lying[4..8].copy_from_slice(&4u32.to_le_bytes());
    assert_eq!(decode_ticks(&lying), Err(Refusal::WrongSize));
    lying[4..8].copy_from_slice(&u32::MAX.to_le_bytes());
    assert_eq!(decode_ticks(&lying), Err(Refusal::WrongSize));
    let mut v2 = bytes.clone();
    v2[1] = 2;
    assert_eq!(decode_ticks(&v2), Err(Refusal::WrongVersion));
    let mut nan = bytes.clone();
    let at = second + field(&TICK_ROW, "force_n").offset;
    nan[at..at + 4].copy_from_slice(&f32::NAN.to_le_bytes());
    assert_eq!(decode_ticks(&nan), Err(Refusal::NonFinite));
    assert_eq!(decode_ticks(&vec![7u8; TICKS.size + (MAX_TICK_ROWS + 1) * TICK_ROW.size]), Err(Refusal::Oversized));
    let empty = TickBatch::with_capacity(0).take();
    assert_eq!(decode_ticks(&empty).unwrap(), vec![]);
}
