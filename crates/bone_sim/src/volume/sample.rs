//! Point queries on a volume: layer, HU and density at any world point (m), nearest or trilinear.
//! Points outside the grid read as air (layer `Outside`, HU −1024, density 0); NaN or infinite
//! points are an error rather than a silent answer.

use nalgebra::Point3;

use super::grid::FAR_INDEX;
use super::layer::Layer;
use super::material::HU_MIN;
use super::rounding;
use super::Volume;
use crate::error::{SimError, SimResult};

/// How to sample between voxel centres.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Interp {
    /// The value of the nearest voxel centre.
    Nearest,
    /// Trilinear interpolation of the eight surrounding voxel centres.
    Linear,
}

pub(crate) fn check_point(p: &Point3<f64>) -> SimResult<()> {
    for (what, v) in [("point x (m)", p.x), ("point y (m)", p.y), ("point z (m)", p.z)] {
        if !v.is_finite() {
            return Err(SimError::NonFinite { what, value: v });
        }
    }
    Ok(())
}

impl Volume {
    /// The pristine layer at a world point (nearest voxel).
    ///
    /// # Errors
    /// A NaN or infinite coordinate.
    pub fn layer_at(&self, p_world_m: &Point3<f64>) -> SimResult<Layer> {
        check_point(p_world_m)?;
        Ok(match self.grid().nearest_voxel(p_world_m) {
            Some([i, j, k]) => Layer::from_id(self.labels()[self.grid().linear(i, j, k)]).unwrap_or(Layer::Outside),
            None => Layer::Outside,
        })
    }

    /// HU at a world point.
    ///
    /// # Errors
    /// A NaN or infinite coordinate.
    pub fn hu_at(&self, p_world_m: &Point3<f64>, interp: Interp) -> SimResult<f64> {
        check_point(p_world_m)?;
        Ok(self.interpolate(p_world_m, interp, |v, l| f64::from(v.hu()[l]), f64::from(HU_MIN)))
    }

    /// Apparent density (kg/m³) at a world point.
    ///
    /// # Errors
    /// A NaN or infinite coordinate.
    pub fn density_at(&self, p_world_m: &Point3<f64>, interp: Interp) -> SimResult<f64> {
        check_point(p_world_m)?;
        Ok(self.interpolate(
            p_world_m,
            interp,
            |v, l| f64::from(v.table().density_kg_m3(v.labels()[l], v.hu()[l])),
            0.0,
        ))
    }

    /// Samples `value(volume, linear_index)`; voxels outside the grid read `outside`.
    pub(crate) fn interpolate(
        &self,
        p: &Point3<f64>,
        interp: Interp,
        value: impl Fn(&Volume, usize) -> f64,
        outside: f64,
    ) -> f64 {
        let grid = self.grid();
        match interp {
            Interp::Nearest => match grid.nearest_voxel(p) {
                Some([i, j, k]) => value(self, grid.linear(i, j, k)),
                None => outside,
            },
            Interp::Linear => {
                let c = grid.world_to_index(p);
                if !(c.x.abs() < FAR_INDEX && c.y.abs() < FAR_INDEX && c.z.abs() < FAR_INDEX) {
                    return outside; // also NaN: before the integer casts below
                }
                let dims = grid.dims();
                let base = [rounding::floor(c.x), rounding::floor(c.y), rounding::floor(c.z)];
                let frac = [c.x - base[0], c.y - base[1], c.z - base[2]];
                let mut acc = 0.0;
                for corner in 0..8usize {
                    let mut w = 1.0;
                    let mut idx = [0i64; 3];
                    for axis in 0..3 {
                        let upper = (corner >> axis) & 1 == 1;
                        idx[axis] = base[axis] as i64 + i64::from(upper);
                        w *= if upper { frac[axis] } else { 1.0 - frac[axis] };
                    }
                    if w == 0.0 {
                        continue;
                    }
                    let inside = (0..3).all(|a| idx[a] >= 0 && (idx[a] as usize) < dims[a]);
                    acc += w * if inside {
                        value(self, grid.linear(idx[0] as usize, idx[1] as usize, idx[2] as usize))
                    } else {
                        outside
                    };
                }
                acc
            }
        }
    }
}

#[cfg(test)]
#[allow(clippy::float_cmp)] // exact values are intended here
mod tests {
    use super::*;
    use crate::volume::grid::Grid;
    use crate::volume::material::HuMapping;

    fn ramp() -> Volume {
        // HU rises 100 per voxel along x.
        let grid = Grid::axis_aligned([4, 2, 2], [1e-3; 3], [0.0; 3]).unwrap();
        let hu: Vec<f32> = (0..16).map(|l| 100.0 * (l % 4) as f32 + 200.0).collect();
        Volume::from_hu(grid, &hu, None, HuMapping::default()).unwrap()
    }

    #[test]
    fn nearest_and_trilinear() {
        let v = ramp();
        let p = Point3::new(1.25e-3, 0.5e-3, 0.5e-3);
        assert!((v.hu_at(&p, Interp::Nearest).unwrap() - 300.0).abs() < 1e-9);
        assert!((v.hu_at(&p, Interp::Linear).unwrap() - 325.0).abs() < 1e-6);
        assert_eq!(v.layer_at(&p).unwrap(), Layer::Cancellous);
    }

    #[test]
    fn outside_points_read_as_air_and_nan_is_an_error() {
        let v = ramp();
        let far = Point3::new(1.0, -2.0, 3.0);
        assert_eq!(v.layer_at(&far).unwrap(), Layer::Outside);
        assert_eq!(v.hu_at(&far, Interp::Linear).unwrap(), f64::from(HU_MIN));
        assert_eq!(v.density_at(&far, Interp::Nearest).unwrap(), 0.0);
        // Half a voxel beyond the last centre: blends with air.
        let edge = Point3::new(3.5e-3, 0.0, 0.0);
        let hu = v.hu_at(&edge, Interp::Linear).unwrap();
        assert!((hu - 0.5 * (500.0 + f64::from(HU_MIN))).abs() < 1e-6);
        assert!(v.layer_at(&Point3::new(f64::NAN, 0.0, 0.0)).is_err());
        assert!(v.hu_at(&Point3::new(0.0, f64::INFINITY, 0.0), Interp::Linear).is_err());
    }
}
