//! The session tick's cost in instructions, for before/after comparisons that the shared VM's
//! timing noise cannot blur: a steady 11 N push through a thick cortical slab.
//!
//! ```text
//! cargo build --release -p bone_sim --example tick_cost
//! valgrind --tool=callgrind --callgrind-out-file=/dev/null target/release/examples/tick_cost 0
//! valgrind --tool=callgrind --callgrind-out-file=/dev/null target/release/examples/tick_cost 8000
//! ```
//!
//! (instructions at 8000 ticks − at 0) / 8000 is the cost of one tick (docs/benchmarks.md).

use std::sync::Arc;

use bone_sim::{DrillingSession, Grid, HuMapping, Layer, PlannedPath, Pose, SessionConfig, Volume};
use nalgebra::{Point3, UnitQuaternion};

fn main() {
    let ticks: usize = std::env::args().nth(1).map_or(8000, |a| a.parse().expect("ticks: a number"));
    let (n, h) = (48usize, 0.5e-3);
    let grid = Grid::axis_aligned([n; 3], [h; 3], [0.0; 3]).expect("a valid grid");
    let mut labels = vec![0u8; grid.len()];
    let mut hu = vec![-1000f32; grid.len()];
    for k in 8..n {
        for j in 0..n {
            for i in 0..n {
                labels[grid.linear(i, j, k)] = Layer::Cortical.id();
                hu[grid.linear(i, j, k)] = 1800.0;
            }
        }
    }
    let vol = Arc::new(Volume::from_hu(grid, &hu, Some(&labels), HuMapping::default()).expect("a valid volume"));
    let c = 24.0 * h;
    let path = PlannedPath::new(Point3::new(c, c, 8.0 * h), Point3::new(c, c, 40.0 * h)).expect("a valid path");
    let mut s = DrillingSession::new(vol, path, SessionConfig::default()).expect("a valid session");
    s.reserve_bricks(4096);
    let mut total = 0.0;
    for t in 0..ticks {
        // The stylus 3 mm ahead of the tip (1.2 N on the device), trembling sideways.
        let z = if t == 0 { 2.0e-3 } else { s.state().tip_m.z + 3e-3 };
        let wobble = 1e-4 * (t as f64 * 0.06).sin();
        let p = Pose {
            position_m: Point3::new(c + wobble, c, z),
            orientation: UnitQuaternion::identity(),
            drill_on: true,
            spindle_rpm: 1250.0,
        };
        total += s.tick(Some(&p)).force_n.z;
    }
    println!("sum of Fz {total:.3} N, tip at z {:.4} m", s.state().tip_m.z);
}
