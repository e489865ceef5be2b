//! A small engine over a cortex-over-cancellous slab, and helpers to drive it tick by tick.

use super::{slab, H};
use bone_sim::engine::handoff::{Command, Output, PoseSample};
use bone_sim::engine::{build, EngineConfig, EngineLink, TickCore};
use bone_sim::guidance::GuidanceMode;
use bone_sim::{Layer, PlannedPath, Pose};
use nalgebra::{Point3, UnitQuaternion};

pub const NXY: usize = 24;
pub const CENTRE: f64 = 12.0 * H;
pub const PEAK_N: f64 = 3.3;

pub fn engine(slots: usize) -> (TickCore, EngineLink, f64) {
    let (vol, surface) = slab(NXY, &[(Layer::Cortical, 1500.0, 3e-3), (Layer::Cancellous, 300.0, 6e-3)]);
    let path =
        PlannedPath::new(Point3::new(CENTRE, CENTRE, surface), Point3::new(CENTRE, CENTRE, surface + 9e-3)).unwrap();
    let mut cfg = EngineConfig::new(path);
    cfg.max_sessions = slots;
    cfg.reserve_bricks = 64;
    let (core, link) = build(&vol, &cfg).unwrap();
    (core, link, surface)
}

pub fn pose_at(z: f64) -> Pose {
    Pose {
        position_m: Point3::new(CENTRE, CENTRE, z),
        orientation: UnitQuaternion::identity(),
        drill_on: true,
        spindle_rpm: 1250.0,
    }
}

pub fn activate(link: &mut EngineLink, slot: u16, generation: u32, gain: f64) {
    link.commands.push(Command::Activate { slot, generation, path: None, mode: GuidanceMode::Paper, gain }).unwrap();
}

pub fn send(link: &mut EngineLink, slot: usize, generation: u32, seq: u32, z: f64) {
    let sample =
        PoseSample { pose: Some(pose_at(z)), seq, client_time_ns: u64::from(seq) * 10, generation, received: None };
    link.poses[slot].write(sample);
}

/// A model reply for slot 0, generation 1, that took 4 ms.
pub fn prediction(window_seq: u32, predicted_n: [f64; 3], pose_client_time_ns: u64) -> Command {
    Command::Prediction { slot: 0, generation: 1, window_seq, predicted_n, latency_s: 0.004, pose_client_time_ns }
}

pub fn drain(link: &mut EngineLink) -> Vec<Output> {
    let mut out = Vec::new();
    while let Some(o) = link.outputs.pop() {
        out.push(o);
    }
    out
}

/// Moves slot 0 from 2 mm above the surface to `depth` below it at 0.02 mm per tick, then holds.
pub fn press(core: &mut TickCore, link: &mut EngineLink, surface: f64, depth: f64, hold: u32) -> Vec<Output> {
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

pub fn forces(out: &[Output]) -> Vec<bone_sim::protocol::ForceMsg> {
    out.iter().filter_map(|o| if let Output::Force { msg, .. } = o { Some(*msg) } else { None }).collect()
}

/// The forces `out` holds, each as (the pose it used, whether the thread that ticked it puts it).
pub fn forces_published(out: &[Output]) -> Vec<(u32, bool)> {
    out.iter()
        .filter_map(
            |o| if let Output::Force { msg, published, .. } = o { Some((msg.pose_seq, *published)) } else { None },
        )
        .collect()
}
