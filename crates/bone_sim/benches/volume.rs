//! Criterion benches of the bone volume on the default phantom at 0.5 mm voxels: one removal call
//! in cortical bone for three burr radii, the three X-ray views of a drilled session, and the
//! session's memory after drilling the whole default path (printed, not timed).
//!
//! Needs the phantom exported by `tests/benchmarks/export_phantom_raw.py` (`make bench` does it);
//! set `DHG_BENCH_DATA` to read it from elsewhere than `target/bench-data`.

use std::hint::black_box;
use std::time::{Duration, Instant};

use bone_sim::{Burr, Cut, DrilledVolume, Layer};
use criterion::{criterion_group, criterion_main, BenchmarkId, Criterion};
use nalgebra::{Point3, Vector3};

mod support;
use support::{load_phantom, Phantom};

/// Burr centres along A→B every `step_m`, starting 2 mm before A.
fn path_centres(p: &Phantom, step_m: f64) -> Vec<Point3<f64>> {
    let dir: Vector3<f64> = (p.target - p.entry).normalize();
    let len = (p.target - p.entry).norm();
    let n = ((len + 2e-3) / step_m) as usize;
    (0..=n).map(|i| p.entry + dir * (-2e-3 + i as f64 * step_m)).collect()
}

fn removal(c: &mut Criterion) {
    let p = load_phantom();
    let dir: Vector3<f64> = (p.target - p.entry).normalize();
    // 1.75 mm into the lateral cortex along the path.
    let centre = p.entry + dir * 1.75e-3;
    assert_eq!(p.volume.layer_at(&centre).unwrap(), Layer::Cortical);
    let cut = Cut { spindle_rpm: 1200.0, dt_s: 1e-3, contact: 1.0 };
    let mut group = c.benchmark_group("removal_in_cortical");
    for radius_mm in [1.25, 2.5, 4.0] {
        group.bench_with_input(BenchmarkId::from_parameter(format!("{radius_mm}mm")), &radius_mm, |b, &r| {
            let burr = Burr { center_m: centre, radius_m: r * 1e-3 };
            let mut d = DrilledVolume::new(p.volume.clone());
            b.iter_custom(|iters| {
                let mut total = Duration::ZERO;
                for i in 0..iters {
                    // Restore the bone now and then so the burr keeps cutting full cortical bone
                    // (0.2 s of 1 ms ticks; includes the first-contact brick copies).
                    if i % 200 == 0 {
                        d.reset();
                    }
                    let t = Instant::now();
                    black_box(d.remove(&burr, &cut).unwrap());
                    total += t.elapsed();
                }
                total
            });
        });
    }
    group.finish();
}

fn xray_and_memory(c: &mut Criterion) {
    let p = load_phantom();
    let mut d = DrilledVolume::new(p.volume.clone());
    let cut = Cut { spindle_rpm: 1200.0, dt_s: 1e-3, contact: 1.0 };
    // The default demo drill: 2.5 mm drill, 1.5 mm/s feed, 1 ms ticks.
    let centres = path_centres(&p, 1.5e-6);
    d.remove_along(&centres, 1.25e-3, &cut).unwrap();
    eprintln!(
        "session after drilling the default path (2.5 mm drill): {} bricks, {} bytes beyond the shared volume ({} bytes)",
        d.overlay().owned_count(),
        d.memory_bytes(),
        p.volume.memory_bytes()
    );
    let mut wide = DrilledVolume::new(p.volume.clone());
    wide.remove_along(&centres, 2.5e-3, &cut).unwrap();
    eprintln!(
        "session after drilling the default path (5 mm burr): {} bricks, {} bytes",
        wide.overlay().owned_count(),
        wide.memory_bytes()
    );
    c.bench_function("xray_three_views_drilled_session", |b| b.iter(|| black_box(d.xray())));
    c.bench_function("reset_drilled_session", |b| {
        b.iter_batched_ref(|| d.clone(), DrilledVolume::reset, criterion::BatchSize::LargeInput);
    });
}

criterion_group!(benches, removal, xray_and_memory);
criterion_main!(benches);
