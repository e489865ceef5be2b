//! The pristine bone volume: labels and HU per voxel, shared read-only by every session.
//!
//! A session's drilling never writes here; its edits live in a copy-on-write
//! [`MaterialOverlay`](bricks::MaterialOverlay) (see [`DrilledVolume`](drilled::DrilledVolume)).

pub mod bricks;
pub mod drilled;
pub mod grid;
pub mod layer;
pub mod material;
pub mod rounding;
pub mod sample;

use grid::Grid;
use layer::Layer;
use material::{clamp_hu, HuMapping, MaterialTable};

use crate::error::{SimError, SimResult};
use crate::xray::Projections;

/// Full material of a voxel in the `u16` fixed-point material fraction (1.0 = 65535).
pub const FULL_MATERIAL: u16 = u16::MAX;

/// A CT-derived bone volume: geometry, per-voxel layer and HU, and the derived material tables.
#[derive(Debug)]
pub struct Volume {
    grid: Grid,
    labels: Vec<u8>,
    hu: Vec<i16>,
    table: MaterialTable,
    pristine_xray: Projections,
}

impl Volume {
    /// Builds a volume from HU values (k-major, x fastest) and optional layer labels.
    ///
    /// Without labels, layers come from the mapping's HU thresholds. HU are rounded and clamped
    /// to the 12-bit CT range.
    ///
    /// # Errors
    /// Lengths that do not match the grid, a NaN or infinite HU, an unknown layer id, or an invalid
    /// mapping.
    pub fn from_hu(grid: Grid, hu: &[f32], labels: Option<&[u8]>, mapping: HuMapping) -> SimResult<Self> {
        let table = MaterialTable::new(mapping)?;
        if hu.len() != grid.len() {
            return Err(SimError::ShapeMismatch {
                what: "HU array length",
                expected: format!("{} voxels for dims {:?}", grid.len(), grid.dims()),
                got: hu.len().to_string(),
            });
        }
        if let Some(bad) = hu.iter().find(|v| !v.is_finite()) {
            return Err(SimError::NonFinite { what: "HU value", value: f64::from(*bad) });
        }
        let labels = match labels {
            Some(labels) => {
                if labels.len() != grid.len() {
                    return Err(SimError::ShapeMismatch {
                        what: "label array length",
                        expected: format!("{} voxels (same as HU)", grid.len()),
                        got: labels.len().to_string(),
                    });
                }
                if let Some(voxel) = labels.iter().position(|&l| Layer::from_id(l).is_none()) {
                    return Err(SimError::UnknownLayer { id: labels[voxel], voxel, max: (Layer::COUNT - 1) as u8 });
                }
                labels.to_vec()
            }
            None => hu.iter().map(|&v| table.mapping().threshold_layer(f64::from(v)).id()).collect(),
        };
        let hu: Vec<i16> = hu.iter().map(|&v| clamp_hu(f64::from(v))).collect();
        let pristine_xray = Projections::integrate(&grid, &hu, &table);
        Ok(Self { grid, labels, hu, table, pristine_xray })
    }

    /// The voxel grid.
    #[must_use]
    pub fn grid(&self) -> &Grid {
        &self.grid
    }

    /// Layer ids, k-major.
    #[must_use]
    pub fn labels(&self) -> &[u8] {
        &self.labels
    }

    /// Stored HU, k-major.
    #[must_use]
    pub fn hu(&self) -> &[i16] {
        &self.hu
    }

    /// The material tables.
    #[must_use]
    pub fn table(&self) -> &MaterialTable {
        &self.table
    }

    /// The X-ray line integrals of the undrilled volume.
    #[must_use]
    pub fn pristine_xray(&self) -> &Projections {
        &self.pristine_xray
    }

    /// Pristine material of a voxel: full for solid layers, none outside.
    #[inline]
    #[must_use]
    pub fn pristine_material(&self, linear: usize) -> u16 {
        if self.labels[linear] == Layer::Outside.id() {
            0
        } else {
            FULL_MATERIAL
        }
    }

    /// Linear index of the voxel nearest to continuous index coordinates, if inside the grid.
    #[inline]
    #[must_use]
    pub fn nearest_index(&self, c: &nalgebra::Vector3<f64>) -> Option<usize> {
        let dims = self.grid.dims();
        let (i, j, k) = (rounding::round(c.x), rounding::round(c.y), rounding::round(c.z));
        let inside = i >= 0.0 && j >= 0.0 && k >= 0.0 && i < dims[0] as f64 && j < dims[1] as f64 && k < dims[2] as f64;
        inside.then(|| self.grid.linear(i as usize, j as usize, k as usize))
    }

    /// Bytes held by this volume (shared by all its sessions).
    #[must_use]
    pub fn memory_bytes(&self) -> usize {
        self.labels.len() + self.hu.len() * 2 + self.pristine_xray.memory_bytes()
    }
}

#[cfg(test)]
pub(crate) mod test_support {
    //! Small synthetic volumes for the unit and integration tests.
    use super::*;

    /// A box of `n³` voxels at `h` m, filled with one layer/HU, with a margin of air.
    pub fn uniform_block(n: usize, h: f64, layer: Layer, hu: f32, margin: usize) -> Volume {
        let grid = Grid::axis_aligned([n; 3], [h; 3], [0.0; 3]).unwrap();
        let mut labels = vec![0u8; grid.len()];
        let mut hus = vec![-1000f32; grid.len()];
        for k in margin..n - margin {
            for j in margin..n - margin {
                for i in margin..n - margin {
                    let l = grid.linear(i, j, k);
                    labels[l] = layer.id();
                    hus[l] = hu;
                }
            }
        }
        Volume::from_hu(grid, &hus, Some(&labels), HuMapping::default()).unwrap()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn rejects_mismatched_and_invalid_arrays() {
        let grid = Grid::axis_aligned([2, 2, 2], [1e-3; 3], [0.0; 3]).unwrap();
        let m = HuMapping::default;
        assert!(matches!(Volume::from_hu(grid.clone(), &[0.0; 7], None, m()), Err(SimError::ShapeMismatch { .. })));
        assert!(matches!(
            Volume::from_hu(grid.clone(), &[0.0; 8], Some(&[0; 9]), m()),
            Err(SimError::ShapeMismatch { .. })
        ));
        let mut labels = [0u8; 8];
        labels[3] = 9;
        assert!(matches!(
            Volume::from_hu(grid.clone(), &[0.0; 8], Some(&labels), m()),
            Err(SimError::UnknownLayer { id: 9, voxel: 3, .. })
        ));
        let mut hu = [0f32; 8];
        hu[1] = f32::NAN;
        assert!(matches!(Volume::from_hu(grid, &hu, None, m()), Err(SimError::NonFinite { .. })));
    }

    #[test]
    fn threshold_labels_without_segmentation() {
        let grid = Grid::axis_aligned([3, 1, 1], [1e-3; 3], [0.0; 3]).unwrap();
        let v = Volume::from_hu(grid, &[1200.0, 300.0, -50.0], None, HuMapping::default()).unwrap();
        assert_eq!(v.labels(), &[1, 2, 0]);
        assert_eq!(v.pristine_material(0), FULL_MATERIAL);
        assert_eq!(v.pristine_material(2), 0);
    }
}
