#![allow(clippy::float_cmp)] // exact zeros are intended here

use super::*;

fn path() -> PlannedPath {
    PlannedPath::new(Point3::origin(), Point3::new(0.0, 0.0, 0.08)).unwrap()
}

fn input(path: &PlannedPath, tip: Point3<f64>, v: Vector3<f64>) -> GuideInput<'_> {
    GuideInput {
        tip_m: tip,
        tip_velocity_m_s: v,
        cutting_feed_m_s: v.z.max(0.0),
        axis: Vector3::z(),
        path,
        breakthrough_depth_m: Some(0.01),
        broken_through: false,
        giving: false,
        temperature_c: 37.0,
        necrosis_threshold_c: 47.0,
    }
}

/// Steps `input` for 1.5 s (thirty of the feed filter's time constants) and returns the last
/// share: the laws' response to a velocity held that long.
fn settled(g: &mut Guide, input: &GuideInput<'_>) -> Vector3<f64> {
    let mut f = Vector3::zeros();
    for _ in 0..1500 {
        f = g.step(input, 1e-3);
        g.set_target(Vector3::zeros());
    }
    f
}

fn live(mode: GuidanceMode) -> Guide {
    let mut g = Guide::new(GuidanceParams::default(), mode, 1.0);
    g.set_target(Vector3::zeros());
    for _ in 0..300 {
        let p = path();
        g.step(&input(&p, Point3::new(0.0, 0.0, 0.005), Vector3::zeros()), 1e-3);
        g.set_target(Vector3::zeros());
    }
    g
}

#[test]
fn the_paper_cue_ramps_clamps_and_fades_out_when_the_model_goes_quiet() {
    let p = GuidanceParams::default();
    let path = path();
    let at = input(&path, Point3::new(0.0, 0.0, 0.005), Vector3::zeros());
    let mut m = Guide::new(p.clone(), GuidanceMode::Paper, 1.0);
    let aimed = m.set_target(Vector3::new(5.0, 0.0, 0.0));
    assert!((aimed.norm() - p.max_n).abs() < 1e-12, "the target as mixed is clamped: {aimed}");
    let first = m.step(&at, 1e-3);
    assert!((first.x - p.max_rate_n_per_s * 1e-3).abs() < 1e-12, "a step is a ramp: {first}");
    let mut last = first;
    for _ in 0..300 {
        last = m.step(&at, 1e-3);
    }
    assert!((last.norm() - p.max_n).abs() < 1e-9, "clamped to max_n: {last}");
    let mut prev = last.norm();
    for _ in 0..1000 {
        let now = m.step(&at, 1e-3).norm();
        assert!(prev - now <= p.max_rate_n_per_s * 1e-3 + 1e-12);
        prev = now;
    }
    assert!(!m.is_live() && prev < 1e-12, "faded out: {prev}");
}

#[test]
fn zero_gain_mixes_nothing_and_bad_gains_and_modes_are_refused() {
    let path = path();
    for mode in GuidanceMode::ALL {
        let mut m = Guide::new(GuidanceParams::default(), mode, 0.0);
        for _ in 0..500 {
            m.set_target(Vector3::new(0.5, 0.5, -0.5));
            let mut i = input(&path, Point3::new(0.004, 0.0, 0.0095), Vector3::new(0.0, 0.0, 0.05));
            i.giving = true;
            assert_eq!(m.step(&i, 1e-3), Vector3::zeros(), "{mode:?}");
        }
    }
    assert!(check_gain(-0.1).is_err() && check_gain(f64::NAN).is_err() && check_gain(4.5).is_err());
    assert_eq!(check_gain(0.5), Ok(0.5));
    assert!(GuidanceMode::from_name("stiff").unwrap_err().to_string().contains("paper, corridor, brake, shaped"));
    for m in GuidanceMode::ALL {
        assert_eq!(GuidanceMode::from_name(m.name()), Ok(m));
    }
}

#[test]
fn the_corridor_acts_only_across_the_axis_beyond_its_deadband_and_is_capped() {
    let path = path();
    let mut g = live(GuidanceMode::Corridor);
    let p = g.params().clone();
    let mut last = 0.0;
    for off_mm in [0.0, 0.3, 0.5, 0.8, 1.5, 3.0, 10.0, 50.0] {
        let tip = Point3::new(off_mm * 1e-3, 0.0, 0.02);
        let f = g.step(&input(&path, tip, Vector3::new(0.0, 0.0, 0.003)), 1e-3);
        g.set_target(Vector3::zeros());
        assert!(f.z.abs() < 1e-12, "{off_mm} mm: a force {f} along the drill axis");
        if off_mm * 1e-3 <= p.corridor_deadband_m {
            assert_eq!(f, Vector3::zeros(), "{off_mm} mm is inside the deadband");
        } else {
            assert!(f.x < 0.0 && f.y.abs() < 1e-12, "{off_mm} mm: {f} does not point back to the line");
            assert!(f.norm() >= last - 1e-12 && f.norm() <= p.max_n + 1e-12, "{off_mm} mm: {f}");
        }
        last = f.norm();
    }
    assert!((last - p.max_n).abs() < 1e-9, "far off the path the corridor is capped: {last}");
}

#[test]
fn a_corridor_profile_sets_the_stiffness_per_depth() {
    let path = path();
    let mut g = live(GuidanceMode::Corridor);
    let mut p = g.params().clone();
    p.corridor_damping_n_s_per_m = 0.0;
    p.corridor_integral_s = 0.0;
    p.corridor_profile_n_per_m = vec![400.0, 100.0];
    p.corridor_profile_bin_m = 5e-3;
    g.set_params(p.clone()).unwrap();
    // 1.5 mm off the line (1 mm past the deadband): 0.4 N in the first 5 mm, 0.1 N after, and
    // the last bin's stiffness beyond the path's end.
    for (z, want) in [(-0.002, 0.4), (0.002, 0.4), (0.007, 0.1), (0.5, 0.1)] {
        let f = g.step(&input(&path, Point3::new(1.5e-3, 0.0, z), Vector3::zeros()), 1e-3);
        assert!((f.x + want).abs() < 1e-9 && f.z.abs() < 1e-12, "z {z}: {f}");
    }
    p.corridor_profile_n_per_m = vec![f64::NAN];
    assert!(g.set_params(p).is_err(), "a NaN stiffness was accepted");
}

#[test]
fn the_corridor_pull_grows_with_an_offset_held_capped_and_leaks_away_inside_the_deadband() {
    let path = path();
    let mut g = live(GuidanceMode::Corridor);
    let mut p = g.params().clone();
    p.corridor_damping_n_s_per_m = 0.0;
    p.corridor_integral_s = 1.0;
    g.set_params(p.clone()).unwrap();
    let at = |g: &mut Guide, off_m: f64| {
        let f = g.step(&input(&path, Point3::new(off_m, 0.0, 0.02), Vector3::zeros()), 1e-3);
        g.set_target(Vector3::zeros());
        assert!(f.z.abs() < 1e-12 && f.y.abs() < 1e-12 && f.x <= 0.0, "{f}");
        -f.x
    };
    // 1 mm past the deadband at 400 N/m: 0.4 N of spring at once, and after 0.5 s held there
    // 0.4 N × (1 + 0.5 s / 1 s) = 0.6 N.
    let off = p.corridor_deadband_m + 1e-3;
    let first = at(&mut g, off);
    assert!((first - 0.4).abs() < 1e-3, "{first}");
    let mut half = 0.0;
    for _ in 1..500 {
        half = at(&mut g, off);
    }
    assert!((half - 0.6).abs() < 2e-3, "after 0.5 s: {half}");
    // Held on, the integral winds up no further than the device's continuous limit.
    for _ in 0..5000 {
        assert!(at(&mut g, off) <= p.max_n + 1e-12);
    }
    assert!((at(&mut g, off) - p.max_n).abs() < 1e-9);
    // Back inside the deadband there is no force, and the held error leaks away: after 5 s
    // there the same offset meets the spring, e^-5 of the wound-up pull (at most 0.88 N) and
    // the new tick's 0.4 mN.
    for _ in 0..5000 {
        assert_eq!(at(&mut g, 0.0), 0.0);
    }
    let again = at(&mut g, off);
    assert!(again > 0.4 && again < 0.4 + 0.88 * 0.0068 + 0.4e-3, "the integral did not leak: {again}");
    // A reset forgets it at once.
    for _ in 0..1000 {
        at(&mut g, off);
    }
    g.reset();
    g.set_target(Vector3::zeros());
    // (0.3 s on the line for the cue to fade back in after the reset: a leak alone would
    // leave 74 % of the pull.)
    for _ in 0..300 {
        at(&mut g, 0.0);
    }
    let after_reset = at(&mut g, off);
    assert!((after_reset - 0.4).abs() < 1e-3, "{after_reset}");
    p.corridor_integral_s = -1.0;
    assert!(g.set_params(p).is_err(), "a negative integral time was accepted");
}

#[test]
fn the_brake_holds_at_once_never_pushes_forward_and_lets_go() {
    let path = path();
    let mut g = live(GuidanceMode::Brake);
    let p = g.params().clone();
    // The cortex gives at z = 10 mm; the tip surges on at 50 mm/s.
    let mut z = 0.01;
    let mut max_hold = 0.0_f64;
    for tick in 0..2000 {
        let mut i = input(&path, Point3::new(0.0, 0.0, z), Vector3::new(0.0, 0.0, 0.05));
        i.giving = tick < 30;
        let f = g.step(&i, 1e-3);
        g.set_target(Vector3::zeros());
        assert!(f.z <= 0.0, "tick {tick}: the brake pushed forward: {f}");
        assert!(f.x == 0.0 && f.y == 0.0);
        if tick == 1 {
            assert!(f.z < -0.05, "no hold within 2 ms of the give: {f}");
        }
        max_hold = max_hold.max(-f.z);
        z += 0.05e-3;
    }
    // The spring–damper's resistance grows as the tip runs on, under a cap that decays.
    assert!(max_hold <= p.brake_hold_n + 1e-12 && max_hold > 0.6 * p.brake_hold_n, "hold {max_hold} N");
    assert!(!g.is_braking(), "the hold is over after 2 s");
    // And the model's axial cue, within the warning span before the predicted breakthrough
    // (10 mm here): where the expert pushed less (the paper's cue pulls in), a resistance as
    // large (the tip cutting on at twice `warning_feed_m_s`); where the expert pushed
    // harder, nothing.
    let near = input(&path, Point3::new(0.0, 0.0, 0.0095), Vector3::new(0.0, 0.0, 1e-3));
    for _ in 0..300 {
        g.set_target(Vector3::new(0.0, 0.0, 0.5)); // the expert pushed 0.5 N less
        assert!(g.step(&near, 1e-3).z <= 0.0);
    }
    assert!((g.share_n().z + 0.5).abs() < 1e-6, "{}", g.share_n());
    // Elsewhere, nothing: well before the breakthrough, and once the cortex is through.
    let early = input(&path, Point3::new(0.0, 0.0, 0.005), Vector3::zeros());
    let mut through = input(&path, Point3::new(0.0, 0.0, 0.03), Vector3::zeros());
    through.broken_through = true;
    for i in [&early, &through] {
        g.set_target(Vector3::new(0.0, 0.0, 0.5));
        assert!(g.step(i, 1e-3).z.abs() < 1e-12, "{}", g.share_n());
    }
    for _ in 0..300 {
        g.set_target(Vector3::new(0.0, 0.0, -0.5)); // the expert pushed 0.5 N harder
        g.step(&near, 1e-3);
    }
    assert!(g.share_n().z.abs() < 1e-12, "{}", g.share_n());
}

#[test]
fn the_shaped_warning_ramps_up_before_the_predicted_breakthrough() {
    let path = path();
    let mut g = live(GuidanceMode::Shaped);
    let p = g.params().clone();
    // A tip cutting on at 1 mm/s, twice `warning_feed_m_s`: the warning in full.
    let at = |g: &mut Guide, depth: f64, broken: bool| {
        let mut i = input(&path, Point3::new(0.0, 0.0, depth), Vector3::new(0.0, 0.0, 1e-3));
        i.broken_through = broken;
        settled(g, &i).z
    };
    assert_eq!(at(&mut g, 0.008, false), 0.0);
    let half = at(&mut g, 0.0095, false);
    assert!((half + 0.5 * p.warning_n).abs() < 1e-9, "{half}");
    assert!((at(&mut g, 0.0101, false) + p.warning_n).abs() < 1e-9);
    assert_eq!(at(&mut g, 0.0101, true), 0.0, "once through, no warning");
}

#[test]
fn the_warning_asks_to_slow_down_and_never_holds_a_still_tip() {
    let path = path();
    let mut g = live(GuidanceMode::Shaped);
    let p = g.params().clone();
    let tip = Point3::new(0.0, 0.0, 0.0101); // past the ramp: the full warning
    let mut at = |v: f64| settled(&mut g, &input(&path, tip, Vector3::new(0.0, 0.0, v))).z;
    assert!((at(2.0 * p.warning_feed_m_s) + p.warning_n).abs() < 1e-9, "twice the safe feed: in full");
    assert!((at(1.5 * p.warning_feed_m_s) + 0.5 * p.warning_n).abs() < 1e-9, "half-way: half");
    assert!(at(p.warning_feed_m_s).abs() < 1e-9, "at the safe feed: nothing");
    assert!(at(0.5 * p.warning_feed_m_s).abs() < 1e-12, "a slower feed is not resisted");
    assert!(at(0.0).abs() < 1e-12, "a still tip is not held");
    assert_eq!(at(-1e-3), 0.0, "nor one pulled back");
    // With warning_feed_m_s = 0 the warning is by position alone.
    let mut by_position = live(GuidanceMode::Shaped);
    by_position.set_params(GuidanceParams { warning_feed_m_s: 0.0, ..p.clone() }).unwrap();
    let still = by_position.step(&input(&path, tip, Vector3::zeros()), 1e-3).z;
    assert!((still + p.warning_n).abs() < 1e-9, "{still}");
}

#[test]
fn the_heat_hold_resists_advance_while_hot_until_the_tip_has_cooled() {
    let path = path();
    let mut g = live(GuidanceMode::Shaped);
    assert_eq!(g.params().heat_hold_n, 0.0, "off by default");
    // The hold alone (the heat cue's vibration has its own test).
    g.set_params(GuidanceParams { heat_hold_n: 1.5, heat_buzz_n: 0.0, ..GuidanceParams::default() }).unwrap();
    let p = g.params().clone();
    // Tip at 5 mm (no warning there), advancing at 1 mm/s.
    let at = |g: &mut Guide, z: f64, vz: f64, t: f64| {
        let mut i = input(&path, Point3::new(0.0, 0.0, z), Vector3::new(0.0, 0.0, vz));
        i.temperature_c = t;
        let f = g.step(&i, 1e-3);
        g.set_target(Vector3::zeros());
        f
    };
    assert_eq!(at(&mut g, 0.005, 1e-3, 44.9), Vector3::zeros(), "cooler than 45 °C: nothing");
    assert!(!g.is_heat_holding());
    let mut cool = input(&path, Point3::new(0.0, 0.0, 0.005), Vector3::new(0.0, 0.0, 1e-3));
    cool.temperature_c = 44.9;
    assert_eq!(settled(&mut g, &cool), Vector3::zeros(), "advancing at 1 mm/s for 1.5 s, cooler than 45 °C");
    let f = at(&mut g, 0.005, 1e-3, 45.0);
    assert!(g.is_heat_holding(), "engages 2 °C short of 47 °C");
    assert!((f.z + p.brake_damping_n_s_per_m * 1e-3).abs() < 1e-12 && f.x == 0.0 && f.y == 0.0, "{f}");
    // Pushed on past where it engaged: the spring, capped; backing off: nothing (never forward).
    let far = at(&mut g, 0.009, 0.0, 46.0);
    assert!((far.z + p.heat_hold_n).abs() < 1e-12, "{far}");
    let mut back = input(&path, Point3::new(0.0, 0.0, 0.004), Vector3::new(0.0, 0.0, -1e-3));
    back.temperature_c = 46.0;
    assert_eq!(settled(&mut g, &back), Vector3::zeros());
    // Still holding at 43.1 °C (engaged at 45); released at 43.
    assert!(at(&mut g, 0.006, 0.0, 43.1).z < 0.0);
    assert_eq!(at(&mut g, 0.006, 0.0, 43.0), Vector3::zeros());
    assert!(!g.is_heat_holding());
    // The other modes have no heat hold; a reset drops it.
    let mut c = live(GuidanceMode::Brake);
    c.set_params(p.clone()).unwrap();
    assert_eq!(at(&mut c, 0.006, 1e-3, 50.0), Vector3::zeros());
    at(&mut g, 0.006, 1e-3, 46.0);
    g.reset();
    assert!(!g.is_heat_holding());
}

#[test]
fn every_mode_fades_out_when_the_model_is_lost() {
    let path = path();
    for mode in GuidanceMode::ALL {
        let mut g = live(mode);
        let i = input(&path, Point3::new(0.003, 0.0, 0.0099), Vector3::new(0.0, 0.0, 1e-3));
        let mut on = Vector3::zeros();
        for _ in 0..200 {
            // Long enough for the feed (twice the safe feed) to be seen through its filter.
            g.set_target(Vector3::new(0.3, 0.0, 0.3));
            on = g.step(&i, 1e-3);
        }
        assert!(on.norm() > 0.0, "{mode:?}");
        let mut f = on;
        for _ in 0..2000 {
            f = g.step(&i, 1e-3);
        }
        assert!(!g.is_live() && f == Vector3::zeros(), "{mode:?}: {f}");
    }
}

#[test]
fn fading_assists_as_needed_and_probes_without_guidance() {
    let mut f = Fading::new(FadingParams::default()).unwrap();
    assert_eq!((f.attempts(), f.gain()), (0, 1.0));
    // Within tolerance (0.5 mm plunge, 1.5 mm off the line): the gain falls, attempt after attempt.
    let mut gains = vec![];
    for _ in 0..6 {
        f.finish_attempt(0.5e-3, 1.5e-3);
        gains.push(f.assistance());
    }
    assert!(gains.windows(2).all(|w| w[1] < w[0]), "{gains:?}");
    let p = FadingParams::default();
    let eq = p.learn * 0.5 / (1.0 - p.forget);
    assert!((gains[5] - eq).abs() < 0.1, "{gains:?} against the equilibrium {eq}");
    // Every 4th attempt is a probe: gain 0, whatever the assistance.
    let mut f = Fading::new(FadingParams::default()).unwrap();
    let probes: Vec<bool> = (0..8)
        .map(|_| {
            let probe = f.is_probe();
            assert_eq!(f.gain() == 0.0, probe);
            f.finish_attempt(0.5e-3, 0.0);
            probe
        })
        .collect();
    assert_eq!(probes, [false, false, false, true, false, false, false, true]);
    // A bad attempt (6 mm plunge) brings the assistance back up to the cap.
    let mut f = Fading::new(FadingParams { start_gain: 0.2, ..FadingParams::default() }).unwrap();
    f.finish_attempt(6e-3, 0.0);
    assert_eq!(f.assistance(), 1.0);
    assert!((f.last_error() - 6.0).abs() < 1e-12);
    // Non-finite measurements change nothing but the count; bad params are refused.
    let a = f.assistance();
    f.finish_attempt(f64::NAN, f64::INFINITY);
    assert!(f.assistance() <= a + 1e-12);
    for bad in [
        FadingParams { forget: 1.0, ..FadingParams::default() },
        FadingParams { learn: -1.0, ..FadingParams::default() },
        FadingParams { max_gain: 5.0, ..FadingParams::default() },
        FadingParams { plunge_tolerance_m: 0.0, ..FadingParams::default() },
    ] {
        assert!(matches!(Fading::new(bad), Err(SimError::InvalidParameter { .. })));
    }
    // A tolerance so small that the error ratio overflows, with nothing learned from it
    // (learn 0: 0 · inf was NaN, and NaN stayed through the clamp): the gain stays a number.
    let tiny = FadingParams { learn: 0.0, plunge_tolerance_m: 1e-320, ..FadingParams::default() };
    let mut f = Fading::new(tiny).unwrap();
    let next = f.finish_attempt(1e-3, 0.0);
    assert!(next.is_finite() && f.assistance().is_finite(), "gain {next}, assistance {}", f.assistance());
    let greedy = FadingParams { learn: 1e308, ..FadingParams::default() };
    let mut f = Fading::new(greedy).unwrap();
    assert_eq!(f.finish_attempt(1.0, 1.0), 1.0, "an overflowing update is the most assistance");
}

#[test]
fn the_heat_cue_vibrates_along_the_axis_while_hot_with_no_mean_push_and_stops_once_cooled() {
    let path = path();
    let mut g = live(GuidanceMode::Shaped);
    let p = g.params().clone();
    assert!(p.heat_buzz_n > 0.0 && p.heat_hold_n == 0.0, "the cue is on by default, the hold off");
    // A still tip at 5 mm (no warning, no corridor), hot: one second of the cue.
    let mut i = input(&path, Point3::new(0.0, 0.0, 0.005), Vector3::zeros());
    i.temperature_c = 45.5;
    let forces: Vec<Vector3<f64>> = (0..1000)
        .map(|_| {
            let f = g.step(&i, 1e-3);
            g.set_target(Vector3::zeros());
            f
        })
        .collect();
    assert!(g.is_heat_holding());
    assert!(forces.iter().all(|f| f.x == 0.0 && f.y == 0.0), "along the axis only");
    let peak = forces.iter().map(|f| f.z.abs()).fold(0.0, f64::max);
    // (Sampled at 1 kHz, a 100 Hz sine's largest sample is sin 72° of its amplitude.)
    assert!(peak <= p.heat_buzz_n + 1e-12 && peak >= 0.95 * p.heat_buzz_n, "amplitude {peak} N");
    let mean = forces.iter().map(|f| f.z).sum::<f64>() / 1000.0;
    assert!(mean.abs() < 1e-9, "no mean push: {mean} N");
    let sign_changes = forces.windows(2).filter(|w| w[0].z * w[1].z < 0.0).count();
    assert!((195..=201).contains(&sign_changes), "{sign_changes} sign changes in 1 s at 100 Hz");
    // Scaled by the gain; gone once the tip has cooled 2 °C below where it engaged (45.5 °C).
    g.set_gain(0.5);
    let half = (0..10).map(|_| g.step(&i, 1e-3).z.abs()).fold(0.0, f64::max);
    assert!((half - 0.5 * p.heat_buzz_n).abs() < 0.05 * p.heat_buzz_n, "{half}");
    i.temperature_c = 43.5;
    assert_eq!(g.step(&i, 1e-3), Vector3::zeros());
    assert!(!g.is_heat_holding());
    // Within the device's peak on top of everything else shaped renders.
    i.temperature_c = 50.0;
    g.set_gain(4.0);
    let most = (0..100).map(|_| g.step(&i, 1e-3).norm()).fold(0.0, f64::max);
    assert!(most <= 4.0 * p.heat_buzz_n + 1e-9, "{most}");
}

#[test]
fn a_jittery_tip_velocity_does_not_make_the_brake_chatter() {
    // The tip's velocity is a finite difference of a tip that moves in voxel steps: here it
    // alternates between 0 and 10 mm/s every tick while the brake holds. A damper on it raw
    // would swing by 0.2 N every tick (a 500 Hz buzz in the handle); through the filter the
    // hold changes by under a tenth of that from tick to tick.
    let path = path();
    let mut g = live(GuidanceMode::Brake);
    let mut last: Option<f64> = None;
    let mut largest_swing = 0.0_f64;
    for tick in 0..300 {
        let v = if tick % 2 == 0 { 0.0 } else { 0.01 };
        let mut i = input(&path, Point3::new(0.0, 0.0, 0.01), Vector3::new(0.0, 0.0, v));
        i.giving = tick < 5;
        let f = g.step(&i, 1e-3).z;
        g.set_target(Vector3::zeros());
        assert!(f <= 0.0, "the brake pushed forward");
        if tick > 20 {
            largest_swing = largest_swing.max((f - last.unwrap_or(f)).abs());
        }
        last = Some(f);
    }
    assert!(g.is_braking() && last.unwrap() < -0.05, "the brake is holding: {last:?}");
    assert!(largest_swing < 0.02, "the hold swings by {largest_swing} N from tick to tick");
}

#[test]
fn the_warning_resists_the_feed_into_bone_not_motion_through_the_bore() {
    // A hand that eased back and comes forward again through the hole it drilled moves the tip
    // fast but cuts nothing: no warning (it would meet the yielding trainee at every return to
    // the bone face and push them back out). The same speed cutting: the warning in full.
    let path = path();
    let mut g = live(GuidanceMode::Shaped);
    let p = g.params().clone();
    let tip = Point3::new(0.0, 0.0, 0.0101);
    let mut bore = input(&path, tip, Vector3::new(0.0, 0.0, 3e-3));
    bore.cutting_feed_m_s = 0.0;
    assert_eq!(settled(&mut g, &bore).z, 0.0, "the bore");
    bore.cutting_feed_m_s = 3e-3;
    assert!((settled(&mut g, &bore).z + p.warning_n).abs() < 1e-9, "cutting");
}

#[test]
fn a_tip_that_advances_in_voxel_steps_gets_a_steady_warning() {
    // A feed that comes in steps: 100 µm in one tick every 50 ticks, 2 mm/s on average, 0 or
    // 100 mm/s per tick. The warning scales by the feed over tens of milliseconds, so it stays
    // at its full force (the feed is four times `warning_feed_m_s`) instead of switching
    // between nothing and all of it from tick to tick.
    let path = path();
    let mut g = live(GuidanceMode::Shaped);
    let p = g.params().clone();
    let mut z = 0.0101; // past the ramp, before the breakthrough (10 mm): the full warning
    let mut shares = Vec::new();
    for tick in 0..1000 {
        let step = tick % 50 == 0;
        if step {
            z += 100e-6;
        }
        let v = if step { 100e-6 / 1e-3 } else { 0.0 };
        let i = input(&path, Point3::new(0.0, 0.0, z), Vector3::new(0.0, 0.0, v));
        shares.push(g.step(&i, 1e-3).z);
        g.set_target(Vector3::zeros());
    }
    let late = &shares[500..];
    let swing = late.windows(2).map(|w| (w[1] - w[0]).abs()).fold(0.0, f64::max);
    assert!(swing < 0.05 * p.warning_n, "the warning swings by {swing} N from tick to tick");
    assert!(late.iter().all(|&f| f <= 0.0), "the warning pushed forward");
    assert!(late.iter().all(|&f| f < -0.8 * p.warning_n), "not the full warning at four times the feed");
}
