#![allow(clippy::float_cmp)] // exact values the controller copies through (speed, orientation)

use super::*;

fn novice() -> SurgeonStyle {
    SurgeonStyle {
        skill: Skill::Novice,
        push_cortical_n: 1.9,
        push_soft_n: 0.35,
        feed_m_s: 0.9e-3,
        feed_gain: 0.4,
        reaction_delay_s: 0.3,
        hand_damping_n_s_per_m: 9.0,
        tremor_m: 0.3e-3,
        tremor_hz: 10.0,
        noise_fraction: 0.2,
        drift_m: 1.2e-3,
        anticipates_breakthrough: false,
        anticipation_m: 0.0,
        hesitations_per_s: 0.07,
        hesitation_s: 2.0,
        caution_temp_c: 57.0,
        stop_margin_m: -1e-3,
        spindle_rpm: 1200.0,
        cue_follow_per_s: 2.0,
        arm_stiffness_n_per_m: 115.0,
        ease_fraction: 1.0,
        hand_mass_kg: HAND_MASS_KG,
        lateral_stiffness_n_per_m: LATERAL_STIFFNESS_N_PER_M,
    }
}

fn path() -> PlannedPath {
    PlannedPath::new(Point3::new(0.0, 0.0, 0.0), Point3::new(0.0, 0.0, 0.05)).unwrap()
}

fn still(depth_m: f64) -> Perception {
    Perception { depth_m, temperature_c: 37.0, layer: Layer::Outside, breakthroughs: 0, plunge_depth_m: 0.0 }
}

#[test]
fn the_same_seed_drills_the_same_poses_and_another_seed_other_ones() {
    let run = |seed| {
        let mut s = SurgeonController::new(&path(), novice(), seed, 5.0, None, CueMeaning::Felt).unwrap();
        (0..3000).map(|_| s.step(&still(0.0), &Vector3::zeros(), &Vector3::zeros()).unwrap()).collect::<Vec<_>>()
    };
    assert_eq!(run(7), run(7));
    assert_ne!(run(7), run(8));
}

#[test]
fn the_approach_ends_aligned_before_the_entry_with_the_drill_on() {
    let mut s = SurgeonController::new(&path(), novice(), 1, 5.0, None, CueMeaning::Felt).unwrap();
    let mut row = [0.0; 9];
    // A free hand (no force) reaches 3 mm before A within the approach and align phases.
    while s.phase() != Phase::Feed {
        row = s.step(&still(0.0), &Vector3::zeros(), &Vector3::zeros()).unwrap();
    }
    assert!((row[2] - ALIGNED_S_M).abs() < 1.5e-3, "z = {} m", row[2]);
    assert!(row[7] > 0.5 && row[8] == 1200.0, "drill on at its speed: {row:?}");
    // The stylus points the drill along A→B (+z): the identity orientation.
    assert_eq!(&row[3..7], &[1.0, 0.0, 0.0, 0.0]);
}

#[test]
fn a_felt_breakthrough_is_answered_after_the_reaction_delay_by_a_hold() {
    let steady = SurgeonStyle { hesitations_per_s: 0.0, ..novice() };
    let mut s = SurgeonController::new(&path(), steady, 3, 60.0, None, CueMeaning::Felt).unwrap();
    let zero = Vector3::zeros();
    while s.phase() != Phase::Feed {
        s.step(&still(0.0), &zero, &zero);
    }
    // Feeding in soft bone against a light resistance; then the cortex gives at tick `bt`.
    let resist = Vector3::new(0.0, 0.0, -0.3);
    for _ in 0..500 {
        s.step(&still(5e-3), &resist, &zero);
    }
    assert!(s.hold_s.is_none() && s.push > 0.0, "pushing before the breakthrough");
    let broke = Perception { breakthroughs: 1, ..still(5e-3) };
    let delay = s.delay;
    for k in 0..delay {
        s.step(&broke, &resist, &zero);
        assert!(s.retract_until < 0.0, "reacted {k} ticks after the breakthrough, before its delay");
    }
    s.step(&broke, &resist, &zero);
    assert!(s.retract_until > 0.0 && s.hold_s.is_some() && s.push == 0.0, "holds after the delay");
}

#[test]
fn the_surgeon_stops_at_b_and_finishes_half_a_second_later_with_the_drill_off() {
    let mut s = SurgeonController::new(&path(), novice(), 4, 60.0, None, CueMeaning::Felt).unwrap();
    let zero = Vector3::zeros();
    while s.phase() != Phase::Feed {
        s.step(&still(0.0), &zero, &zero);
    }
    // The tip reported past B less the stop margin (-1 mm: 51 mm), seen a reaction delay later.
    let at_b = still(0.0511);
    let mut before = 0;
    while s.phase() == Phase::Feed {
        s.step(&at_b, &zero, &zero).unwrap();
        before += 1;
    }
    assert_eq!(before, s.delay + 1, "stopped when the surgeon saw B, a reaction delay later");
    let mut ticks = 0;
    while let Some(row) = s.step(&at_b, &zero, &zero) {
        ticks += 1;
        assert!(s.phase() == Phase::Stop && row[7] < 0.5 && row[8] == 0.0, "stopping, drill off");
    }
    assert!(s.done() && s.phase() == Phase::Done);
    assert!((498..=500).contains(&ticks), "held {ticks} ticks");
    assert!(s.drilling_s() > 0.0);
}

#[test]
fn an_invalid_style_or_duration_is_refused_with_the_field_named() {
    let bad = SurgeonStyle { hand_mass_kg: 0.0, ..novice() };
    let e = SurgeonController::new(&path(), bad, 1, 5.0, None, CueMeaning::Felt).unwrap_err();
    assert!(e.to_string().contains("hand_mass_kg"), "{e}");
    let nan = SurgeonStyle { tremor_m: f64::NAN, ..novice() };
    let e = SurgeonController::new(&path(), nan, 1, 5.0, None, CueMeaning::Felt).unwrap_err();
    assert!(matches!(e, SimError::NonFinite { .. }) && e.to_string().contains("tremor_m"), "{e}");
    for bad in [0.0, -1.0, f64::NAN, f64::INFINITY, MAX_ATTEMPT_S * 1.001, 1e17] {
        let e = SurgeonController::new(&path(), novice(), 1, bad, None, CueMeaning::Felt).unwrap_err();
        assert!(matches!(e, SimError::InvalidParameter { .. }) && e.to_string().contains("max_duration_s"), "{e}");
    }
    assert!(SurgeonController::new(&path(), novice(), 1, MAX_ATTEMPT_S, None, CueMeaning::Felt).is_ok());
    assert!(CueMeaning::from_name("obey").is_err());
    // A reaction delay sizes the hand's history (a tick each): 1e300 s wrapped to a tiny buffer,
    // 1e6 s aborted the process allocating one.
    for bad in [MAX_REACTION_DELAY_S * 1.001, 1e6, 1e300] {
        let slow = SurgeonStyle { reaction_delay_s: bad, ..novice() };
        let e = SurgeonController::new(&path(), slow, 1, 5.0, None, CueMeaning::Felt).unwrap_err();
        assert!(e.to_string().contains("reaction_delay_s"), "{e}");
    }
    let slowest = SurgeonStyle { reaction_delay_s: MAX_REACTION_DELAY_S, ..novice() };
    assert!(SurgeonController::new(&path(), slowest, 1, 5.0, None, CueMeaning::Felt).is_ok());
}

#[test]
fn the_orientation_points_the_drill_along_the_direction() {
    for d in [Vector3::new(1.0, 0.0, 0.0), Vector3::new(0.0, -0.6, 0.8), Vector3::new(0.0, 0.0, -1.0)] {
        let q = axis_quaternion(&d);
        let r = nalgebra::UnitQuaternion::from_quaternion(nalgebra::Quaternion::new(q[0], q[1], q[2], q[3]));
        assert!((r * Vector3::z() - d).norm() < 1e-12, "{d:?}: {q:?}");
    }
}

/// Steps a feeding surgeon 900 ticks with `cue` as the guidance each tick; the drill-on column.
fn drill_on_under(meaning: CueMeaning, cue: impl Fn(usize) -> f64) -> Vec<bool> {
    let steady = SurgeonStyle { hesitations_per_s: 0.0, ..novice() };
    let mut s = SurgeonController::new(&path(), steady, 3, 60.0, None, meaning).unwrap();
    let zero = Vector3::zeros();
    while s.phase() != Phase::Feed {
        s.step(&still(0.0), &zero, &zero);
    }
    let resist = Vector3::new(0.0, 0.0, -0.5);
    (0..900).map(|k| s.step(&still(5e-3), &resist, &Vector3::new(0.0, 0.0, cue(k))).unwrap()[7] > 0.5).collect()
}

#[test]
fn a_surgeon_told_what_the_heat_cue_means_pauses_with_the_drill_off_while_it_buzzes() {
    use std::f64::consts::TAU;
    // 0.3 N at 100 Hz from tick 100 to 300, on a steady 0.2 N resistance.
    let buzz = |k: usize| {
        -0.2 - if (100..300).contains(&k) { 0.3 * (TAU * 100.0 * (k - 100) as f64 * 1e-3).sin() } else { 0.0 }
    };
    let on = drill_on_under(CueMeaning::Yield, buzz);
    let delay = 300; // novice()'s reaction delay, in ticks
    let off: Vec<usize> = (0..900).filter(|&k| !on[k]).collect();
    assert!(!off.is_empty(), "never paused");
    let (first, last) = (off[0], off[off.len() - 1]);
    // Recognised within about 30 ms of the buzz's start, acted on a reaction delay later.
    assert!((100 + delay..=100 + delay + 60).contains(&first), "drill off from tick {first}");
    assert!(off.len() == last - first + 1, "one pause: {off:?}");
    assert!(last < 899 && (300 + delay + 30..=300 + delay + 100).contains(&(last + 1)), "back on at {}", last + 1);
    // An arm that only feels the cue, and a step in the cue (a brake engaging), make no pause.
    assert!(drill_on_under(CueMeaning::Felt, buzz).iter().all(|&x| x), "the felt operator paused");
    let step = |k: usize| if k >= 100 { -2.2 } else { 0.0 };
    assert!(drill_on_under(CueMeaning::Yield, step).iter().all(|&x| x), "a step read as a buzz");
}
