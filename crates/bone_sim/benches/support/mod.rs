//! Loading the default phantom exported by `tests/benchmarks/export_phantom_raw.py`.
#![allow(dead_code)]

use std::path::PathBuf;
use std::sync::Arc;

use bone_sim::{Grid, HuMapping, Volume};
use nalgebra::Point3;

/// The phantom volume and its planned path.
pub struct Phantom {
    /// The shared volume.
    pub volume: Arc<Volume>,
    /// A (m).
    pub entry: Point3<f64>,
    /// B (m).
    pub target: Point3<f64>,
}

/// Reads the exported phantom (`DHG_BENCH_DATA` or `target/bench-data`).
pub fn load_phantom() -> Phantom {
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
