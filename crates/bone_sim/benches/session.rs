//! Criterion bench of the drilling session's 1 ms tick on the default phantom at 0.5 mm voxels:
//! one tick while cutting the lateral cortex, for several burr radii, plus the tick's latency
//! distribution (p50/p99/max, printed) and the sessions one core can tick at 1 kHz.
//!
//! Needs the exported phantom (see `benches/volume.rs`; `make bench` does it).

use std::hint::black_box;
use std::time::{Duration, Instant};

use bone_sim::{DrillingSession, Layer, PlannedPath, Pose, SessionConfig};
use criterion::{criterion_group, criterion_main, BenchmarkId, Criterion};
use nalgebra::{UnitQuaternion, Vector3};

mod support;
use support::{load_phantom, Phantom};

/// A hand that keeps the device `LEAD_M` ahead of the tip along the path: a steady push of
/// 400 N/m × 3 mm = 1.2 N on the device (≈ 11 N of physical thrust).
const LEAD_M: f64 = 3e-3;

struct Driver {
    session: DrillingSession,
    axis: Vector3<f64>,
    orientation: UnitQuaternion<f64>,
}

impl Driver {
    fn new(p: &Phantom, radius_m: f64) -> Self {
        let path = PlannedPath::new(p.entry, p.target).unwrap();
        let axis = path.direction();
        let orientation =
            UnitQuaternion::rotation_between(&Vector3::z(), &axis).unwrap_or_else(UnitQuaternion::identity);
        let config = SessionConfig { burr_radius_m: radius_m, ..SessionConfig::default() };
        let session = DrillingSession::new(p.volume.clone(), path, config).unwrap();
        let mut d = Self { session, axis, orientation };
        d.restart();
        d
    }

    fn pose(&self) -> Pose {
        let tip = self.session.state().tip_m;
        Pose {
            position_m: tip + self.axis * LEAD_M,
            orientation: self.orientation,
            drill_on: true,
            spindle_rpm: 1250.0,
        }
    }

    /// Resets the bone and drills until the burr is cutting the lateral cortex.
    fn restart(&mut self) {
        self.session.reset();
        let start = self.session.path().entry_m() - self.axis * 4e-3;
        let mut pose = Pose { position_m: start, orientation: self.orientation, drill_on: true, spindle_rpm: 1250.0 };
        self.session.tick(Some(&pose));
        for _ in 0..20_000 {
            if self.cutting_cortex() {
                return;
            }
            pose = self.pose();
            self.session.tick(Some(&pose));
        }
        panic!("never reached cortical cutting");
    }

    fn cutting_cortex(&self) -> bool {
        let s = self.session.state();
        s.cutting && s.layer == Layer::Cortical
    }

    /// Times one tick while cutting cortical bone (restarting, untimed, when the cortex is through).
    fn timed_tick(&mut self) -> Duration {
        if !self.cutting_cortex() {
            self.restart();
        }
        let pose = self.pose();
        let t = Instant::now();
        black_box(self.session.tick(Some(&pose)));
        t.elapsed()
    }
}

fn tick(c: &mut Criterion) {
    let p = load_phantom();
    let mut group = c.benchmark_group("tick_cutting_cortical");
    for radius_mm in [0.75, 1.25, 2.5, 4.0] {
        let mut driver = Driver::new(&p, radius_mm * 1e-3);
        // The latency distribution, which criterion's mean does not show.
        let mut samples: Vec<f64> = (0..20_000).map(|_| driver.timed_tick().as_secs_f64() * 1e6).collect();
        samples.sort_by(f64::total_cmp);
        let q = |f: f64| samples[((samples.len() - 1) as f64 * f) as usize];
        let mean = samples.iter().sum::<f64>() / samples.len() as f64;
        eprintln!(
            "burr r = {radius_mm} mm, cutting cortical: tick p50 {:.2} µs, p99 {:.2} µs, p99.9 {:.2} µs, max {:.2} µs, mean {:.2} µs → {:.0} sessions per core at 1 kHz",
            q(0.5),
            q(0.99),
            q(0.999),
            samples[samples.len() - 1],
            mean,
            1000.0 / mean
        );
        group.bench_with_input(BenchmarkId::from_parameter(format!("{radius_mm}mm")), &radius_mm, |b, _| {
            b.iter_custom(|iters| (0..iters).map(|_| driver.timed_tick()).sum());
        });
    }
    group.finish();
    // A session whose stylus hovers in free space: the floor of the per-session cost.
    let mut free = Driver::new(&p, 1.25e-3);
    free.session.reset();
    let far = free.session.path().entry_m() - free.axis * 20e-3;
    let hover = Pose { position_m: far, orientation: free.orientation, drill_on: false, spindle_rpm: 0.0 };
    c.bench_function("tick_free_space", |b| b.iter(|| black_box(free.session.tick(Some(&hover)))));
}

criterion_group!(benches, tick);
criterion_main!(benches);
