//! The tick engine: commands in, forces/state/guidance out, guidance mixing and its fade-out,
//! stale input, slot generations. Driven tick by tick (no threads, no clocks) except the last test.

#![allow(clippy::float_cmp)]

mod common;

use std::sync::atomic::Ordering;

use bone_sim::engine::handoff::{Command, Output, PoseSample};
use bone_sim::engine::{EngineLink, TickCore, TickThread, WaitMode};
use bone_sim::protocol::flags;
use common::engine::*;

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
    let feedback = core.session(0).unwrap().state().feedback_n;
    // The model says the expert felt 0.3 N less push-back along z than the trainee does now.
    let predicted = [feedback.x, feedback.y, feedback.z + 0.3];
    link.commands.push(prediction(1, predicted, 5)).unwrap();
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
    let fb = core.session(0).unwrap().state().feedback_n;
    assert!((last.force_n - (fb + last.guidance_n)).norm() < 0.05, "{last:?} vs {fb:?}");

    // A wild prediction is clamped to the 0.88 N guidance limit.
    link.commands.push(prediction(2, [50.0, 0.0, 0.0], 6)).unwrap();
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
    let fb = core.session(0).unwrap().state().feedback_n;
    link.commands.push(prediction(1, [fb.x + 0.5, fb.y, fb.z], 1)).unwrap();
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
    link.commands.push(prediction(1, [0.5, 0.0, 0.0], 1)).unwrap();
    let out = press_hold(&mut core, &mut link, surface + 1e-3, 100);
    let g = out.iter().find_map(|o| if let Output::Guidance { msg, .. } = o { Some(*msg) } else { None }).unwrap();
    // The prediction is published; the guidance, times the gain, is zero, and none is rendered.
    assert!(g.predicted_force_n.norm() > 0.4 && g.gain == 0.0 && g.guidance_n == nalgebra::Vector3::zeros());
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
fn a_force_carries_the_arrival_of_the_pose_it_used_and_none_without_a_fresh_pose() {
    let (mut core, mut link, surface) = engine(1);
    activate(&mut link, 0, 1, 1.0);
    let arrived = std::time::Instant::now();
    let sample = PoseSample {
        pose: Some(pose_at(surface - 1e-3)),
        seq: 1,
        client_time_ns: 10,
        generation: 1,
        received: Some(arrived),
    };
    link.poses[0].write(sample);
    let received = |out: Vec<Output>| {
        out.iter().find_map(|o| if let Output::Force { received, .. } = o { Some(*received) } else { None })
    };
    core.tick();
    assert_eq!(received(drain(&mut link)), Some(Some(arrived)));
    core.tick(); // the same pose again: no fresh arrival to time
    assert_eq!(received(drain(&mut link)), Some(None));
}

#[test]
fn the_tick_thread_ticks_and_stops() {
    let (core, mut link, _) = engine(1);
    activate(&mut link, 0, 1, 1.0);
    let mut t = TickThread::spawn(core, None, WaitMode::Sleep, true).unwrap();
    while link.stats.ticks.load(Ordering::Relaxed) < 20 {
        std::thread::yield_now();
    }
    t.stop();
    let n = link.stats.ticks.load(Ordering::Relaxed);
    std::thread::sleep(std::time::Duration::from_millis(5));
    assert_eq!(link.stats.ticks.load(Ordering::Relaxed), n, "ticked after stop()");
}

#[cfg(target_os = "linux")]
#[test]
fn a_tick_thread_not_asked_for_real_time_priority_keeps_normal_scheduling() {
    // Where the poses' threads run the ticks (decision 0033); with it asked for, the thread has
    // SCHED_FIFO exactly where the process may have it (root, CAP_SYS_NICE or an rtprio limit).
    for asked in [false, true] {
        let (core, mut link, _) = engine(1);
        activate(&mut link, 0, 1, 1.0);
        let mut t = TickThread::spawn(core, None, WaitMode::Sleep, asked).unwrap();
        let got = link.stats.realtime.load(Ordering::Relaxed) == 1;
        t.stop();
        assert!(!got || asked, "SCHED_FIFO taken without being asked for");
        if asked {
            assert_eq!(got, may_use_sched_fifo(), "SCHED_FIFO asked for and allowed but not taken (or the reverse)");
        }
    }
}

/// Whether a thread of this process may switch to `SCHED_FIFO` at the tick thread's priority,
/// tried on a scratch thread.
#[cfg(target_os = "linux")]
#[allow(unsafe_code)]
fn may_use_sched_fifo() -> bool {
    std::thread::spawn(|| {
        let param = libc::sched_param { sched_priority: bone_sim::engine::realtime::FIFO_PRIORITY };
        // SAFETY: a valid sched_param; pid 0 is this scratch thread, which ends right after.
        unsafe { libc::sched_setscheduler(0, libc::SCHED_FIFO, &raw const param) == 0 }
    })
    .join()
    .unwrap_or(false)
}

#[test]
fn a_spinning_tick_thread_uses_a_pose_nobody_woke_it_for_ticks_at_most_1_khz_and_stops() {
    let (core, mut link, surface) = engine(1);
    activate(&mut link, 0, 1, 1.0);
    let t0 = std::time::Instant::now();
    let mut t = TickThread::spawn(core, None, WaitMode::Spin, true).unwrap();
    // Handed over without an unpark: only a thread that keeps looking finds it.
    send(&mut link, 0, 1, 7, surface - 1e-3);
    let mut echoed = false;
    while !echoed {
        assert!(t0.elapsed().as_secs() < 5, "the pose was never used");
        echoed = drain(&mut link).iter().any(|o| matches!(o, Output::Force { msg, .. } if msg.pose_seq == 7));
    }
    std::thread::sleep(std::time::Duration::from_millis(50));
    t.stop();
    let elapsed_ms = t0.elapsed().as_secs_f64() * 1e3;
    let ticks = link.stats.ticks.load(Ordering::Relaxed) as f64;
    // Spinning must not tick faster: the budget allows one tick per 1 ms plus the bank (1.3).
    assert!(ticks >= 1.0 && ticks <= elapsed_ms + 2.0, "{ticks} ticks in {elapsed_ms:.1} ms");
    let n = link.stats.ticks.load(Ordering::Relaxed);
    std::thread::sleep(std::time::Duration::from_millis(5));
    assert_eq!(link.stats.ticks.load(Ordering::Relaxed), n, "ticked after stop()");
}

#[test]
fn set_burr_swaps_the_drill_of_one_slot_and_a_new_session_gets_the_default_again() {
    let (mut core, mut link, surface) = engine(2);
    let r0 = core.session(0).unwrap().config().burr_radius_m;
    activate(&mut link, 0, 1, 1.0);
    activate(&mut link, 1, 1, 1.0);
    link.commands.push(Command::SetBurr { slot: 1, radius_m: 2.0 * r0 }).unwrap();
    core.tick();
    assert_eq!(core.session(0).unwrap().config().burr_radius_m, r0);
    assert_eq!(core.session(1).unwrap().config().burr_radius_m, 2.0 * r0);
    // Both slots drill the same 2 mm: the wider burr removes more bone.
    let mut z = surface - 2e-3;
    for seq in 1..6000 {
        z = (z + 0.002e-3).min(surface + 2e-3);
        send(&mut link, 0, 1, seq, z);
        send(&mut link, 1, 1, seq, z);
        core.tick();
        drain(&mut link);
    }
    let removed = |core: &TickCore, s: usize| core.session(s).unwrap().bone().removed_voxels();
    assert!(removed(&core, 0) > 0, "slot 0 never cut");
    assert!(removed(&core, 1) > 2 * removed(&core, 0), "{} vs {}", removed(&core, 1), removed(&core, 0));
    // A bad radius sent anyway leaves the slot as it was; a re-activated slot starts with the default.
    link.commands.push(Command::SetBurr { slot: 1, radius_m: f64::NAN }).unwrap();
    core.tick();
    assert_eq!(core.session(1).unwrap().config().burr_radius_m, 2.0 * r0);
    activate(&mut link, 1, 2, 1.0);
    core.tick();
    assert_eq!(core.session(1).unwrap().config().burr_radius_m, r0);
}

#[test]
fn outputs_the_comm_side_cannot_take_are_dropped_and_counted_and_the_tick_goes_on() {
    let (mut core, mut link, surface) = engine(1);
    activate(&mut link, 0, 1, 1.0);
    let capacity = link.outputs.capacity();
    // Nobody drains the outputs: one force a tick (and a state every 100) fill the ring.
    let ticks = capacity + 500;
    for seq in 1..=ticks {
        send(&mut link, 0, 1, seq as u32, surface - 1e-3);
        core.tick();
    }
    let produced = ticks + ticks / 100;
    let dropped = link.stats.dropped_outputs.load(Ordering::Relaxed) as usize;
    assert_eq!(dropped, produced - capacity, "every output beyond the ring's capacity is counted");
    assert_eq!(core.session(0).unwrap().state().ticks as usize, ticks, "the tick never waited for the ring");
    // Once the comm side drains, outputs flow again and none is lost.
    let kept = drain(&mut link).len();
    assert_eq!(kept, capacity);
    send(&mut link, 0, 1, ticks as u32 + 1, surface - 1e-3);
    core.tick();
    assert_eq!(forces(&drain(&mut link)).len(), 1);
    assert_eq!(link.stats.dropped_outputs.load(Ordering::Relaxed) as usize, dropped);
}
