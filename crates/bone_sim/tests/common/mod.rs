//! Small synthetic volumes shared by the integration tests.
#![allow(dead_code)]

pub mod engine;

use std::sync::Arc;

use bone_sim::{Grid, HuMapping, Layer, Volume};

/// Voxel size of the test volumes (m).
pub const H: f64 = 0.5e-3;

/// An `n³` grid at [`H`] whose voxels get `(layer, hu)` from `f(i, j, k)`.
pub fn volume_from(n: usize, f: impl Fn(usize, usize, usize) -> (Layer, f32)) -> Arc<Volume> {
    let grid = Grid::axis_aligned([n; 3], [H; 3], [0.0; 3]).unwrap();
    let mut labels = vec![0u8; grid.len()];
    let mut hu = vec![0f32; grid.len()];
    for k in 0..n {
        for j in 0..n {
            for i in 0..n {
                let (layer, v) = f(i, j, k);
                labels[grid.linear(i, j, k)] = layer.id();
                hu[grid.linear(i, j, k)] = v;
            }
        }
    }
    Arc::new(Volume::from_hu(grid, &hu, Some(&labels), HuMapping::default()).unwrap())
}

/// A uniform block of one layer with a 2-voxel air margin.
pub fn block(n: usize, layer: Layer, hu: f32) -> Arc<Volume> {
    volume_from(n, |i, j, k| {
        let inside = [i, j, k].iter().all(|&c| c >= 2 && c < n - 2);
        if inside {
            (layer, hu)
        } else {
            (Layer::Outside, -1000.0)
        }
    })
}

/// Material fraction of every voxel, k-major.
pub fn materials(d: &bone_sim::DrilledVolume) -> Vec<f64> {
    let [nx, ny, nz] = d.volume().grid().dims();
    let mut out = Vec::with_capacity(nx * ny * nz);
    for k in 0..nz {
        for j in 0..ny {
            for i in 0..nx {
                out.push(d.material_fraction(i, j, k));
            }
        }
    }
    out
}

/// A flat slab for drilling along +z: `nxy × nxy` voxels across, air for the first 4 mm of z,
/// then `layers` (layer, HU, thickness in m) stacked along +z, then 6 mm of air.
/// Returns the volume and the z (m) of the slab's first surface.
pub fn slab(nxy: usize, layers: &[(Layer, f32, f64)]) -> (Arc<Volume>, f64) {
    let air_before = 4e-3;
    let total: f64 = air_before + layers.iter().map(|l| l.2).sum::<f64>() + 6e-3;
    let nz = (total / H).ceil() as usize;
    let grid = Grid::axis_aligned([nxy, nxy, nz], [H; 3], [0.0; 3]).unwrap();
    let mut labels = vec![0u8; grid.len()];
    let mut hu = vec![-1000f32; grid.len()];
    for k in 0..nz {
        let z = k as f64 * H;
        let mut top = air_before;
        let mut found = None;
        for &(layer, v, t) in layers {
            if z >= top && z < top + t {
                found = Some((layer, v));
            }
            top += t;
        }
        if let Some((layer, v)) = found {
            for j in 0..nxy {
                for i in 0..nxy {
                    labels[grid.linear(i, j, k)] = layer.id();
                    hu[grid.linear(i, j, k)] = v;
                }
            }
        }
    }
    (Arc::new(Volume::from_hu(grid, &hu, Some(&labels), HuMapping::default()).unwrap()), air_before)
}
