//! The tick engine: commands in, forces/state/guidance out, guidance mixing and its fade-out,
//! stale input, slot generations. Driven tick by tick (no threads, no clocks) except the last test.

#![allow(clippy::float_cmp)]

mod common;

use std::sync::atomic::Ordering;

use bone_sim::engine::handoff::{Command, Output, PoseSample};
use bone_sim::engine::{build, EngineConfig, EngineLink, TickCore, TickThread};
use bone_sim::protocol::flags;
use bone_sim::{Layer, PlannedPath, Pose};
use common::{slab, H};
use nalgebra::{Point3, UnitQuaternion};

const NXY: usize = 24;
const CENTRE: f64 = 12.0 * H;
const PEAK_N: f64 = 3.3;

fn engine(slots: usize) -> (TickCore, EngineLink, f64) {
    let (vol, surface) = slab(NXY, &[(Layer::Cortical, 1500.0, 3e-3), (Layer::Cancellous, 300.0, 6e-3)]);
    let path =
        PlannedPath::new(Point3::new(CENTRE, CENTRE, surface), Point3::new(CENTRE, CENTRE, surface + 9e-3)).unwrap();
    let mut cfg = EngineConfig::new(path);
    cfg.max_sessions = slots;
    cfg.reserve_bricks = 64;
    let (core, link) = build(&vol, &cfg).unwrap();
    (core, link, surface)
}

fn pose_at(z: f64) -> Pose {
    Pose {
        position_m: Point3::new(CENTRE, CENTRE, z),
        orientation: UnitQuaternion::identity(),
        drill_on: true,
        spindle_rpm: 60_000.0,
    }
}

fn activate(link: &mut EngineLink, slot: u16, generation: u32, gain: f64) {
    link.commands.push(Command::Activate { slot, generation, path: None, gain }).unwrap();
}

fn send(link: &mut EngineLink, slot: usize, generation: u32, seq: u32, z: f64) {
    link.poses[slot].write(PoseSample { pose: Some(pose_at(z)), seq, client_time_ns: u64::from(seq) * 10, generation });
}

fn drain(link: &mut EngineLink) -> Vec<Output> {
    let mut out = Vec::new();
    while let Ok(o) = link.outputs.pop() {
        out.push(o);
    }
    out
}

/// Moves slot 0 from 2 mm above the surface to `depth` below it at 0.02 mm per tick, then holds.
fn press(core: &mut TickCore, link: &mut EngineLink, surface: f64, depth: f64, hold: u32) -> Vec<Output> {
    let mut out = Vec::new();
    let mut z = surface - 2e-3;
    let mut seq = 0;
    while z < surface + depth {
        z = (z + 0.02e-3).min(surface + depth);
        seq += 1;
        send(link, 0, 1, seq, z);
        core.tick();
        out.extend(drain(link));
    }
    for _ in 0..hold {
        seq += 1;
        send(link, 0, 1, seq, surface + depth);
        core.tick();
        out.extend(drain(link));
    }
    out
}

fn forces(out: &[Output]) -> Vec<bone_sim::protocol::ForceMsg> {
    out.iter().filter_map(|o| if let Output::Force { msg, .. } = o { Some(*msg) } else { None }).collect()
}

#[test]
fn an_active_slot_renders_one_force_per_tick_and_a_state_every_100() {
    let (mut core, mut link, surface) = engine(2);
    activate(&mut link, 0, 1, 1.0);
    let out = press(&mut core, &mut link, surface, 1e-3, 300);
    let f = forces(&out);
    let ticks = f.len();
    assert!(ticks > 300);
    assert!(out
        .iter()
        .all(|o| matches!(o, Output::Force { slot: 0, generation: 1, .. } | Output::State { slot: 0, .. })));
    let states = out.iter().filter(|o| matches!(o, Output::State { .. })).count();
    assert_eq!(states, ticks / 100);
    // The pose's sequence number and client time are echoed; the burr is on the bone, pushed back.
    let last = f.last().unwrap();
    assert_eq!(u64::from(last.pose_seq) * 10, last.pose_client_time_ns);
    assert!(last.flags & flags::IN_CONTACT != 0 && last.force_n.z < -0.1, "{last:?}");
    assert!(f.iter().all(|m| m.force_n.iter().all(|v| v.is_finite()) && m.force_n.norm() <= PEAK_N + 1e-9));
    // The idle slot 1 produced nothing.
    assert_eq!(core.session(1).unwrap().state().ticks, 0);
}

#[test]
fn guidance_is_prediction_minus_feedback_scaled_clamped_and_mixed_in() {
    let (mut core, mut link, surface) = engine(1);
    activate(&mut link, 0, 1, 1.0);
    press(&mut core, &mut link, surface, 1e-3, 200);
    let feedback = core.session(0).unwrap().state().force_n;
    // The model says the expert felt 0.3 N less push-back along z than the trainee does now.
    let predicted = [feedback.x, feedback.y, feedback.z + 0.3];
    link.commands
        .push(Command::Prediction {
            slot: 0,
            generation: 1,
            window_seq: 1,
            predicted_n: predicted,
            latency_s: 0.004,
            pose_client_time_ns: 5,
        })
        .unwrap();
    let out = press_hold(&mut core, &mut link, surface + 1e-3, 100);
    let g = out.iter().find_map(|o| if let Output::Guidance { msg, .. } = o { Some(*msg) } else { None }).unwrap();
    assert!((g.guidance_n.z - 0.3).abs() < 1e-6, "{g:?}");
    assert_eq!(g.window_seq, 1);
    let f = forces(&out);
    let last = f.last().unwrap();
    // Rate-limited at 8 N/s: after 100 ms the share has reached the full 0.3 N.
    assert!((last.guidance_n.z - 0.3).abs() < 1e-6, "{last:?}");
    assert!(last.flags & flags::MODEL_AVAILABLE != 0 && last.flags & flags::GUIDANCE_ACTIVE != 0);
    // Feedback + share is what the device gets.
    let fb = core.session(0).unwrap().state().force_n;
    assert!((last.force_n - (fb + last.guidance_n)).norm() < 0.05, "{last:?} vs {fb:?}");

    // A wild prediction is clamped to the 0.88 N guidance limit.
    link.commands
        .push(Command::Prediction {
            slot: 0,
            generation: 1,
            window_seq: 2,
            predicted_n: [50.0, 0.0, 0.0],
            latency_s: 0.004,
            pose_client_time_ns: 6,
        })
        .unwrap();
    let f = forces(&press_hold(&mut core, &mut link, surface + 1e-3, 300));
    assert!(f.iter().all(|m| m.guidance_n.norm() <= 0.88 + 1e-9));
    assert!(f.last().unwrap().guidance_n.norm() > 0.87);
}

fn press_hold(core: &mut TickCore, link: &mut EngineLink, z: f64, ticks: u32) -> Vec<Output> {
    let mut out = Vec::new();
    for k in 0..ticks {
        send(link, 0, 1, 10_000 + k, z);
        core.tick();
        out.extend(drain(link));
    }
    out
}

#[test]
fn without_replies_guidance_fades_out_and_the_model_is_reported_unavailable() {
    let (mut core, mut link, surface) = engine(1);
    activate(&mut link, 0, 1, 1.0);
    press(&mut core, &mut link, surface, 1e-3, 100);
    let fb = core.session(0).unwrap().state().force_n;
    link.commands
        .push(Command::Prediction {
            slot: 0,
            generation: 1,
            window_seq: 1,
            predicted_n: [fb.x + 0.5, fb.y, fb.z],
            latency_s: 0.004,
            pose_client_time_ns: 1,
        })
        .unwrap();
    let f = forces(&press_hold(&mut core, &mut link, surface + 1e-3, 1000));
    // Live for the 0.35 s timeout, then faded at 8 N/s: gone well before 1 s.
    assert!(f[200].flags & flags::MODEL_AVAILABLE != 0 && f[200].guidance_n.x > 0.4);
    let last = f.last().unwrap();
    assert_eq!(last.guidance_n.norm(), 0.0);
    assert_eq!(last.flags & (flags::MODEL_AVAILABLE | flags::GUIDANCE_ACTIVE), 0);
    // Never a step: the share changes by at most 8 N/s · 1 ms per tick.
    assert!(f.windows(2).all(|w| (w[1].guidance_n - w[0].guidance_n).norm() <= 8e-3 + 1e-9));
}

#[test]
fn gain_zero_publishes_guidance_but_renders_none() {
    let (mut core, mut link, surface) = engine(1);
    activate(&mut link, 0, 1, 0.0);
    press(&mut core, &mut link, surface, 1e-3, 100);
    link.commands
        .push(Command::Prediction {
            slot: 0,
            generation: 1,
            window_seq: 1,
            predicted_n: [0.5, 0.0, 0.0],
            latency_s: 0.004,
            pose_client_time_ns: 1,
        })
        .unwrap();
    let out = press_hold(&mut core, &mut link, surface + 1e-3, 100);
    let g = out.iter().find_map(|o| if let Output::Guidance { msg, .. } = o { Some(*msg) } else { None }).unwrap();
    assert!(g.guidance_n.norm() > 0.1 && g.gain == 0.0);
    assert!(forces(&out).iter().all(|m| m.guidance_n.norm() == 0.0));
}

#[test]
fn a_silent_client_gets_its_force_ramped_to_zero() {
    let (mut core, mut link, surface) = engine(1);
    activate(&mut link, 0, 1, 1.0);
    let f = forces(&press(&mut core, &mut link, surface, 1.5e-3, 200));
    assert!(f.last().unwrap().force_n.norm() > 0.2);
    let mut quiet = Vec::new();
    for _ in 0..300 {
        core.tick(); // no new poses
        quiet.extend(forces(&drain(&mut link)));
    }
    let last = quiet.last().unwrap();
    assert_eq!(last.force_n.norm(), 0.0);
    assert!(last.flags & flags::STALE != 0);
    assert!(quiet.windows(2).all(|w| (w[1].force_n - w[0].force_n).norm() <= 0.2 + 1e-9), "the ramp jumped");
}

#[test]
fn poses_and_predictions_of_an_earlier_owner_of_the_slot_are_ignored() {
    let (mut core, mut link, surface) = engine(1);
    activate(&mut link, 0, 1, 1.0);
    press(&mut core, &mut link, surface, 1e-3, 50);
    link.commands.push(Command::Release { slot: 0 }).unwrap();
    activate(&mut link, 0, 2, 1.0);
    send(&mut link, 0, 1, 777, surface + 1e-3); // a late pose of the old owner
    link.commands
        .push(Command::Prediction {
            slot: 0,
            generation: 1,
            window_seq: 9,
            predicted_n: [1.0, 0.0, 0.0],
            latency_s: 0.0,
            pose_client_time_ns: 0,
        })
        .unwrap();
    core.tick();
    let out = drain(&mut link);
    let f = forces(&out);
    assert_eq!(f.len(), 1);
    assert_eq!(f[0].pose_seq, 0, "the new owner's session used the old owner's pose");
    assert!(!out.iter().any(|o| matches!(o, Output::Guidance { .. })));
    assert!(out.iter().all(|o| matches!(o, Output::Force { generation: 2, .. })));
    // The new session starts from untouched bone.
    assert_eq!(core.session(0).unwrap().bone().removed_voxels(), 0);
}

#[test]
fn the_tick_thread_ticks_and_stops() {
    let (core, link, _) = engine(1);
    let mut t = TickThread::spawn(core, None).unwrap();
    while link.stats.ticks.load(Ordering::Relaxed) < 20 {
        std::thread::yield_now();
    }
    t.stop();
    let n = link.stats.ticks.load(Ordering::Relaxed);
    std::thread::sleep(std::time::Duration::from_millis(5));
    assert_eq!(link.stats.ticks.load(Ordering::Relaxed), n, "ticked after stop()");
}
