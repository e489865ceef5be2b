//! Criterion benches of the bone volume on the default phantom at 0.5 mm voxels: one removal call
//! in cortical bone for three burr radii, the three X-ray views of a drilled session, and the
//! session's memory after drilling the whole default path (printed, not timed).
//!
//! Needs the phantom exported by `tests/benchmarks/export_phantom_raw.py` (`make bench` does it);
//! set `DHG_BENCH_DATA` to read it from elsewhere than `target/bench-data`.

use std::hint::black_box;
use std::path::PathBuf;
use std::sync::Arc;
use std::time::{Duration, Instant};

use bone_sim::{Burr, Cut, DrilledVolume, Grid, HuMapping, Layer, Volume};
use criterion::{criterion_group, criterion_main, BenchmarkId, Criterion};
use nalgebra::{Point3, Vector3};

struct Phantom {
    volume: Arc<Volume>,
    entry: Point3<f64>,
    target: Point3<f64>,
}

fn load_phantom() -> Phantom {
    let dir = std::env::var_os("DHG_BENCH_DATA")
        .map_or_else(|| PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../target/bench-data"), PathBuf::from);
    let hdr = std::fs::read_to_string(dir.join("phantom.hdr")).unwrap_or_else(|e| {
        panic!("{}: {e}; run `python tests/benchmarks/export_phantom_raw.py` first", dir.display())
    });
    let f: Vec<f64> = hdr.split_whitespace().map(|s| s.parse().expect("header number")).collect();
    let dims = [f[0] as usize, f[1] as usize, f[2] as usize];
    let grid = Grid::axis_aligned(dims, [f[3], f[4], f[5]], [f[6], f[7], f[8]]).expect("grid");
    let hu: Vec<f32> = std::fs::read(dir.join("phantom.hu.i16"))
        .expect("hu file")
        .chunks_exact(2)
        .map(|b| f32::from(i16::from_le_bytes([b[0], b[1]])))
        .collect();
    let labels = std::fs::read(dir.join("phantom.labels.u8")).expect("labels file");
    let volume = Volume::from_hu(grid, &hu, Some(&labels), HuMapping::default()).expect("volume");
    Phantom {
        volume: Arc::new(volume),
        entry: Point3::new(f[9], f[10], f[11]),
        target: Point3::new(f[12], f[13], f[14]),
    }
}

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
