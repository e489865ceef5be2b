//! A session's view of the bone: the shared pristine volume plus its own drilled-out bricks.

use std::sync::Arc;

use nalgebra::Point3;

use super::bricks::MaterialOverlay;
use super::grid::FAR_INDEX;
use super::layer::Layer;
use super::rounding;
use super::sample::{check_point, Interp};
use super::{Volume, FULL_MATERIAL};
use crate::error::{SimError, SimResult};

/// Bricks reserved up front for a new session (about 512 KiB); drilling the default planned path
/// of the phantom with a 2.5 mm burr touches fewer, so the drilling loop does not allocate.
///
/// Why this value: `docs/decisions/0014-reserved-bricks.md`.
pub const DEFAULT_RESERVED_BRICKS: usize = 512;

/// The bone as one session has drilled it.
#[derive(Debug, Clone)]
pub struct DrilledVolume {
    pub(crate) volume: Arc<Volume>,
    pub(crate) overlay: MaterialOverlay,
    pub(crate) removed_mass_kg: f64,
    pub(crate) removed_voxels: u64,
}

impl DrilledVolume {
    /// A fresh, undrilled view of `volume`.
    #[must_use]
    pub fn new(volume: Arc<Volume>) -> Self {
        Self::with_reserve(volume, DEFAULT_RESERVED_BRICKS)
    }

    /// As [`DrilledVolume::new`], reserving room for `reserve_bricks` drilled bricks.
    #[must_use]
    pub fn with_reserve(volume: Arc<Volume>, reserve_bricks: usize) -> Self {
        let overlay = MaterialOverlay::new(volume.grid(), reserve_bricks);
        Self { volume, overlay, removed_mass_kg: 0.0, removed_voxels: 0 }
    }

    /// The shared pristine volume.
    #[must_use]
    pub fn volume(&self) -> &Arc<Volume> {
        &self.volume
    }

    /// The session's copy-on-write bricks.
    #[must_use]
    pub fn overlay(&self) -> &MaterialOverlay {
        &self.overlay
    }

    /// The bricks this session has drilled (owns), in no particular order: each one's first voxel
    /// (i, j, k) and its material (`u16`, 65535 = full), local index `(lk·8 + lj)·8 + li`. Every
    /// other voxel is pristine. A viewer re-meshes only these.
    pub fn bricks(&self) -> impl Iterator<Item = ([usize; 3], &super::bricks::Brick)> + '_ {
        self.overlay.owned().map(|(id, b)| (self.overlay.brick_origin(id), b))
    }

    /// Material fraction (0..=1) left in voxel (i, j, k).
    #[inline]
    #[must_use]
    pub fn material_fraction(&self, i: usize, j: usize, k: usize) -> f64 {
        f64::from(self.overlay.material(&self.volume, i, j, k)) / f64::from(FULL_MATERIAL)
    }

    /// Material fraction left at a world point (0 outside the grid).
    ///
    /// # Errors
    /// A NaN or infinite coordinate.
    pub fn material_at(&self, p_world_m: &Point3<f64>, interp: Interp) -> SimResult<f64> {
        check_point(p_world_m)?;
        let grid = self.volume.grid();
        Ok(self.volume.interpolate(
            p_world_m,
            interp,
            |_, l| {
                let nx = grid.dims()[0];
                let ny = grid.dims()[1];
                self.material_fraction(l % nx, (l / nx) % ny, l / (nx * ny))
            },
            0.0,
        ))
    }

    /// Material fraction (0..=1) at continuous index coordinates, trilinear; 0 outside the grid.
    #[inline]
    #[must_use]
    pub fn material_at_index(&self, c: &nalgebra::Vector3<f64>) -> f64 {
        self.material_and_gradient_at_index(c).0
    }

    /// Material fraction (0..=1) at continuous index coordinates and its gradient with respect to
    /// the index coordinates (per voxel), trilinear; 0 outside the grid.
    #[inline]
    #[must_use]
    pub fn material_and_gradient_at_index(&self, c: &nalgebra::Vector3<f64>) -> (f64, nalgebra::Vector3<f64>) {
        // Also false for NaN: far (or non-finite) coordinates are outside, before any integer cast.
        if !(c.x.abs() < FAR_INDEX && c.y.abs() < FAR_INDEX && c.z.abs() < FAR_INDEX) {
            return (0.0, nalgebra::Vector3::zeros());
        }
        let [nx, ny, nz] = self.volume.grid().dims();
        let (fx, fy, fz) = (rounding::floor(c.x), rounding::floor(c.y), rounding::floor(c.z));
        let (tx, ty, tz) = (c.x - fx, c.y - fy, c.z - fz);
        let (i0, j0, k0) = (fx as i64, fy as i64, fz as i64);
        let full = f64::from(FULL_MATERIAL);
        // The cell's eight voxels, [dz][dy][dx]: read together where the cell lies inside the grid
        // (the contact probes' case), voxel by voxel, 0 outside, at the grid's faces.
        let inside = i0 >= 0 && j0 >= 0 && k0 >= 0 && i0 + 1 < nx as i64 && j0 + 1 < ny as i64 && k0 + 1 < nz as i64;
        let cell = if inside {
            self.overlay.cell(&self.volume, i0 as usize, j0 as usize, k0 as usize)
        } else {
            let get = |i: i64, j: i64, k: i64| -> u16 {
                if i < 0 || j < 0 || k < 0 || i >= nx as i64 || j >= ny as i64 || k >= nz as i64 {
                    0
                } else {
                    self.overlay.material(&self.volume, i as usize, j as usize, k as usize)
                }
            };
            [
                [[get(i0, j0, k0), get(i0 + 1, j0, k0)], [get(i0, j0 + 1, k0), get(i0 + 1, j0 + 1, k0)]],
                [
                    [get(i0, j0, k0 + 1), get(i0 + 1, j0, k0 + 1)],
                    [get(i0, j0 + 1, k0 + 1), get(i0 + 1, j0 + 1, k0 + 1)],
                ],
            ]
        };
        // Spelt out: nested `array::map`s compiled to a loop of `try_map` steps that cost the
        // tick 15 % of its instructions (`examples/tick_cost.rs` under callgrind).
        let f = |z: usize, y: usize| [f64::from(cell[z][y][0]) / full, f64::from(cell[z][y][1]) / full];
        let v = [[f(0, 0), f(0, 1)], [f(1, 0), f(1, 1)]];
        let lerp = |a: f64, b: f64, t: f64| a + (b - a) * t;
        let x = |z: usize, y: usize| lerp(v[z][y][0], v[z][y][1], tx);
        let dx = |z: usize, y: usize| v[z][y][1] - v[z][y][0];
        let (x00, x10, x01, x11) = (x(0, 0), x(0, 1), x(1, 0), x(1, 1));
        let y0 = lerp(x00, x10, ty);
        let y1 = lerp(x01, x11, ty);
        let m = lerp(y0, y1, tz);
        let gx = lerp(lerp(dx(0, 0), dx(0, 1), ty), lerp(dx(1, 0), dx(1, 1), ty), tz);
        let gy = lerp(x10 - x00, x11 - x01, tz);
        let gz = y1 - y0;
        (m, nalgebra::Vector3::new(gx, gy, gz))
    }

    /// The layer at a world point as drilled: `Outside` where all material is gone.
    ///
    /// # Errors
    /// A NaN or infinite coordinate.
    pub fn layer_at(&self, p_world_m: &Point3<f64>) -> SimResult<Layer> {
        check_point(p_world_m)?;
        let grid = self.volume.grid();
        Ok(match grid.nearest_voxel(p_world_m) {
            Some([i, j, k]) if self.overlay.material(&self.volume, i, j, k) > 0 => {
                Layer::from_id(self.volume.labels()[grid.linear(i, j, k)]).unwrap_or(Layer::Outside)
            }
            _ => Layer::Outside,
        })
    }

    /// Total mass removed since creation or the last reset (kg).
    #[must_use]
    pub fn removed_mass_kg(&self) -> f64 {
        self.removed_mass_kg
    }

    /// Voxels fully removed since creation or the last reset.
    #[must_use]
    pub fn removed_voxels(&self) -> u64 {
        self.removed_voxels
    }

    /// Makes this a copy of `other`, a drilling of the same volume, without allocating while
    /// `other` has no more drilled bricks than this one has reserved (snapshots for X-ray views
    /// are taken this way on the tick thread).
    ///
    /// # Errors
    /// `other` drills another volume.
    pub fn copy_from(&mut self, other: &Self) -> SimResult<()> {
        if !Arc::ptr_eq(&self.volume, &other.volume) {
            return Err(SimError::Engine("copy_from: the two drillings are of different volumes".into()));
        }
        self.overlay.copy_from(&other.overlay);
        self.removed_mass_kg = other.removed_mass_kg;
        self.removed_voxels = other.removed_voxels;
        Ok(())
    }

    /// Restores the pristine bone: O(drilled bricks).
    pub fn reset(&mut self) {
        self.overlay.reset();
        self.removed_mass_kg = 0.0;
        self.removed_voxels = 0;
    }

    /// Heap bytes this session holds beyond the shared volume.
    #[must_use]
    pub fn memory_bytes(&self) -> usize {
        self.overlay.memory_bytes()
    }
}

#[cfg(test)]
#[allow(clippy::float_cmp)] // the same value, exactly, is the property tested
mod tests {
    use std::sync::Arc;

    use nalgebra::Vector3;

    use super::DrilledVolume;
    use crate::volume::grid::Grid;
    use crate::volume::material::HuMapping;
    use crate::volume::Volume;

    #[test]
    fn far_and_non_finite_index_coordinates_read_as_outside() {
        let grid = Grid::axis_aligned([4, 4, 4], [1e-3; 3], [0.0; 3]).unwrap();
        let vol = Volume::from_hu(grid, &[1500.0; 64], None, HuMapping::default()).unwrap();
        let bone = DrilledVolume::new(Arc::new(vol));
        assert!(bone.material_and_gradient_at_index(&Vector3::new(1.5, 1.5, 1.5)).0 > 0.99);
        for c in [1e18, -1e18, 9.3e18, f64::MAX, f64::INFINITY, f64::NAN, 4.0e9] {
            let (m, g) = bone.material_and_gradient_at_index(&Vector3::new(c, 1.5, 1.5));
            assert_eq!((m, g), (0.0, Vector3::zeros()), "{c}");
            let (m, _) = bone.material_and_gradient_at_index(&Vector3::new(1.5, 1.5, c));
            assert_eq!(m, 0.0, "{c}");
        }
    }
}
