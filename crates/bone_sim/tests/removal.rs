//! Invariants of material removal by a spherical burr.

// Exact float comparisons are intended: untouched values must be bit-identical.
#![allow(clippy::float_cmp, clippy::cast_lossless)]

mod common;

use bone_sim::{Burr, Cut, DrilledVolume, Layer, SimError};
use common::{block, materials, volume_from, H};
use nalgebra::Point3;

const N: usize = 24;

fn centre() -> Point3<f64> {
    // Between voxel centres so no voxel sits exactly on the sphere.
    Point3::new(11.3 * H, 12.1 * H, 11.7 * H)
}

fn cut(dt_s: f64) -> Cut {
    Cut { spindle_rpm: 1000.0, dt_s, contact: 1.0 }
}

#[test]
fn removal_touches_only_voxels_inside_the_burr() {
    let v = block(N, Layer::Cancellous, 400.0);
    let mut d = DrilledVolume::new(v.clone());
    let burr = Burr { center_m: centre(), radius_m: 2.5e-3 };
    let before = materials(&d);
    let report = d.remove(&burr, &cut(0.01)).unwrap();
    let after = materials(&d);
    let grid = v.grid();
    let mut changed = 0;
    for (l, (b, a)) in before.iter().zip(&after).enumerate() {
        let [i, j, k] = [l % N, (l / N) % N, l / (N * N)];
        let p = grid.index_to_world(&nalgebra::Vector3::new(i as f64, j as f64, k as f64));
        let inside = (p - burr.center_m).norm() <= burr.radius_m;
        if a != b {
            changed += 1;
            assert!(inside, "voxel {:?} outside the burr changed", [i, j, k]);
            assert!(a < b, "material grew at {:?}", [i, j, k]);
        } else if inside && *b > 0.0 {
            panic!("voxel {:?} inside the burr kept its material", [i, j, k]);
        }
    }
    assert!(changed > 400, "a 2.5 mm burr at 0.5 mm voxels covers ~520 voxels, changed {changed}");
    assert_eq!(report.voxels_eroded as usize, changed);
}

#[test]
fn removal_is_monotone_and_reported_mass_matches_the_change() {
    let v = volume_from(N, |i, _, _| if i < 12 { (Layer::Cortical, 1600.0) } else { (Layer::Cancellous, 350.0) });
    let mut d = DrilledVolume::new(v.clone());
    let burr = Burr { center_m: centre(), radius_m: 2.5e-3 };
    let density: Vec<f64> =
        (0..v.grid().len()).map(|l| f64::from(v.table().density_kg_m3(v.labels()[l], v.hu()[l]))).collect();
    let mut prev = materials(&d);
    let mut total_reported = 0.0;
    for step in 0..200 {
        let report = d.remove(&burr, &cut(0.002)).unwrap();
        let now = materials(&d);
        let mut mass_change = 0.0;
        for l in 0..now.len() {
            assert!(now[l] <= prev[l], "step {step}: material grew at voxel {l}");
            mass_change += (prev[l] - now[l]) * density[l] * v.grid().voxel_volume_m3();
        }
        let tol = 1e-9 * mass_change.max(1e-12);
        assert!(
            (report.mass_removed_kg - mass_change).abs() <= tol,
            "step {step}: reported {} vs {}",
            report.mass_removed_kg,
            mass_change
        );
        total_reported += report.mass_removed_kg;
        prev = now;
    }
    assert!((d.removed_mass_kg() - total_reported).abs() < 1e-15);
    // 0.4 s of contact removes all the cancellous and the cortical inside the burr.
    assert!(d.removed_voxels() > 400);
}

/// Seconds of contact until every voxel inside the burr is gone.
fn time_to_clear(layer: Layer, hu: f32) -> f64 {
    let mut d = DrilledVolume::new(block(N, layer, hu));
    let burr = Burr { center_m: centre(), radius_m: 1.25e-3 };
    let dt = 0.001;
    // The first call that finds nothing left to erode ends the clock.
    for tick in 0..10_000 {
        if d.remove(&burr, &cut(dt)).unwrap().voxels_eroded == 0 {
            return tick as f64 * dt;
        }
    }
    f64::INFINITY
}

#[test]
fn cortical_takes_longer_than_cancellous_than_marrow() {
    let cortical = time_to_clear(Layer::Cortical, 1800.0);
    let cancellous = time_to_clear(Layer::Cancellous, 350.0);
    let marrow = time_to_clear(Layer::Marrow, 0.0);
    assert!(cortical.is_finite());
    assert!(cortical > 5.0 * cancellous, "cortical {cortical} s vs cancellous {cancellous} s");
    assert!(cancellous > marrow, "cancellous {cancellous} s vs marrow {marrow} s");
    assert!(marrow <= 0.002, "marrow should go almost at once, took {marrow} s");
}

#[test]
fn faster_spindle_and_more_contact_remove_more() {
    let v = block(N, Layer::Cortical, 1500.0);
    let burr = Burr { center_m: centre(), radius_m: 2.5e-3 };
    let removed = |rpm: f64, contact: f64| {
        let mut d = DrilledVolume::new(v.clone());
        d.remove(&burr, &Cut { spindle_rpm: rpm, dt_s: 0.05, contact }).unwrap().mass_removed_kg
    };
    assert!(removed(2000.0, 1.0) > 1.5 * removed(1000.0, 1.0));
    assert!(removed(1000.0, 1.0) > 1.5 * removed(1000.0, 0.5));
    assert_eq!(removed(0.0, 1.0), 0.0, "a stopped drill cuts nothing");
    assert_eq!(removed(1000.0, 0.0), 0.0, "no contact, no cut");
}

#[test]
fn sessions_sharing_a_volume_are_isolated() {
    let v = block(N, Layer::Cortical, 1500.0);
    let mut a = DrilledVolume::new(v.clone());
    let b = DrilledVolume::new(v.clone());
    let pristine = materials(&b);
    a.remove(&Burr { center_m: centre(), radius_m: 2.5e-3 }, &cut(1.0)).unwrap();
    assert!(a.removed_voxels() > 0);
    assert_eq!(materials(&b), pristine, "drilling session a changed session b");
    let fresh = DrilledVolume::new(v.clone());
    assert_eq!(materials(&fresh), pristine, "drilling changed the shared volume");
    assert!(a.overlay().owned_count() > 0 && b.overlay().owned_count() == 0);
    a.reset();
    assert_eq!(materials(&a), pristine);
    assert_eq!(a.removed_mass_kg(), 0.0);
}

#[test]
fn burr_outside_the_volume_is_harmless() {
    let v = block(N, Layer::Cortical, 1500.0);
    let mut d = DrilledVolume::new(v);
    for center in [Point3::new(-1.0, 0.0, 0.0), Point3::new(0.5, 0.5, 0.5), Point3::new(-1.2e-3, 6e-3, 6e-3)] {
        let r = d.remove(&Burr { center_m: center, radius_m: 1e-3 }, &cut(1.0)).unwrap();
        assert_eq!(r.voxels_eroded, 0);
    }
    assert_eq!(d.overlay().owned_count(), 0, "no brick copied for air");
}

#[test]
fn bad_inputs_are_errors_and_change_nothing() {
    let v = block(N, Layer::Cortical, 1500.0);
    let mut d = DrilledVolume::new(v);
    let good = Burr { center_m: centre(), radius_m: 1e-3 };
    let nan = Burr { center_m: Point3::new(f64::NAN, 0.0, 0.0), ..good };
    assert!(matches!(d.remove(&nan, &cut(0.1)), Err(SimError::NonFinite { .. })));
    assert!(matches!(d.remove(&Burr { radius_m: 0.0, ..good }, &cut(0.1)), Err(SimError::InvalidParameter { .. })));
    assert!(matches!(d.remove(&Burr { radius_m: -1e-3, ..good }, &cut(0.1)), Err(SimError::InvalidParameter { .. })));
    assert!(d.remove(&Burr { radius_m: 1.0, ..good }, &cut(0.1)).is_err());
    assert!(d.remove(&good, &cut(-0.1)).is_err());
    assert!(d.remove(&good, &Cut { contact: 1.5, ..cut(0.1) }).is_err());
    assert!(d.remove(&good, &Cut { spindle_rpm: f64::INFINITY, ..cut(0.1) }).is_err());
    assert_eq!(d.removed_mass_kg(), 0.0);
    assert_eq!(d.overlay().owned_count(), 0);
}
