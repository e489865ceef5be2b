//! Voxel grid geometry: where each voxel sits in the world frame.
//!
//! Frames (see `docs/frames.md`): the world frame is the DICOM patient frame LPS (x towards the
//! patient's left, y posterior, z superior), in metres. Voxel `(i, j, k)` has its centre at
//! `origin + direction * (i·sx, j·sy, k·sz)`; `direction`'s columns are the world directions of the
//! i, j and k axes. Arrays are stored k-major (numpy shape `(nz, ny, nx)`, x fastest).

use nalgebra::{Matrix3, Point3, Vector3};

use crate::error::{finite, positive, SimError, SimResult};

/// Largest number of voxels a grid may hold (4 Gi would overflow the `u32` brick tables).
pub const MAX_VOXELS: usize = 1 << 31;
/// Voxel spacings a grid takes (m): 1 µm (beyond micro-CT) to 10 cm, a plausibility range (a
/// spacing of 1e-20 m was taken). What guards the integer casts of index coordinates is
/// [`FAR_INDEX`].
pub const SPACING_RANGE_M: [f64; 2] = [1e-6, 0.1];
/// Index coordinates beyond ±this (voxels) are outside every grid (a side holds at most
/// `MAX_VOXELS`): readers treat them as outside before casting them to integers.
pub const FAR_INDEX: f64 = 4.0e9;

/// Geometry of a regular voxel grid.
#[derive(Debug, Clone, PartialEq)]
pub struct Grid {
    dims: [usize; 3],
    spacing_m: [f64; 3],
    origin_m: Point3<f64>,
    direction: Matrix3<f64>,
}

impl Grid {
    /// A grid of `dims = [nx, ny, nz]` voxels with the given spacing (m), origin (m, world
    /// position of voxel (0,0,0)'s centre) and orientation (a rotation matrix).
    ///
    /// # Errors
    /// Zero dimensions, too many voxels, a spacing outside `SPACING_RANGE_M`, a non-finite origin,
    /// or a `direction` that is not a proper rotation.
    pub fn new(dims: [usize; 3], spacing_m: [f64; 3], origin_m: [f64; 3], direction: Matrix3<f64>) -> SimResult<Self> {
        if dims.contains(&0) {
            return Err(SimError::InvalidGrid { reason: format!("dimensions {dims:?} contain a zero") });
        }
        let count = dims.iter().try_fold(1usize, |acc, &d| acc.checked_mul(d));
        if count.is_none_or(|c| c > MAX_VOXELS) {
            return Err(SimError::InvalidGrid { reason: format!("{dims:?} is more than {MAX_VOXELS} voxels") });
        }
        positive("voxel spacing x (m)", spacing_m[0])?;
        positive("voxel spacing y (m)", spacing_m[1])?;
        positive("voxel spacing z (m)", spacing_m[2])?;
        if spacing_m.iter().any(|h| !(SPACING_RANGE_M[0]..=SPACING_RANGE_M[1]).contains(h)) {
            return Err(SimError::InvalidGrid {
                reason: format!(
                    "voxel spacing {spacing_m:?} m: each must be within [{:e}, {}] m",
                    SPACING_RANGE_M[0], SPACING_RANGE_M[1]
                ),
            });
        }
        for (what, v) in [("origin x (m)", origin_m[0]), ("origin y (m)", origin_m[1]), ("origin z (m)", origin_m[2])] {
            finite(what, v)?;
        }
        if direction.iter().any(|v| !v.is_finite()) {
            return Err(SimError::InvalidGrid { reason: "direction contains NaN or inf".into() });
        }
        let orthonormal_error = (direction.transpose() * direction - Matrix3::identity()).abs().max();
        if orthonormal_error > 1e-6 || direction.determinant() < 0.0 {
            return Err(SimError::InvalidGrid {
                reason: format!("direction must be a rotation matrix (orthonormal, det +1); got {direction}"),
            });
        }
        Ok(Self { dims, spacing_m, origin_m: Point3::from(origin_m), direction })
    }

    /// An axis-aligned grid (identity orientation).
    ///
    /// # Errors
    /// As [`Grid::new`].
    pub fn axis_aligned(dims: [usize; 3], spacing_m: [f64; 3], origin_m: [f64; 3]) -> SimResult<Self> {
        Self::new(dims, spacing_m, origin_m, Matrix3::identity())
    }

    /// `[nx, ny, nz]`.
    #[must_use]
    pub fn dims(&self) -> [usize; 3] {
        self.dims
    }

    /// Voxel spacing along i, j, k (m).
    #[must_use]
    pub fn spacing_m(&self) -> [f64; 3] {
        self.spacing_m
    }

    /// World position of voxel (0,0,0)'s centre (m).
    #[must_use]
    pub fn origin_m(&self) -> Point3<f64> {
        self.origin_m
    }

    /// Orientation: columns are the world directions of the i, j, k axes.
    #[must_use]
    pub fn direction(&self) -> &Matrix3<f64> {
        &self.direction
    }

    /// Number of voxels.
    #[must_use]
    pub fn len(&self) -> usize {
        self.dims[0] * self.dims[1] * self.dims[2]
    }

    /// Always false: a grid has at least one voxel.
    #[must_use]
    pub fn is_empty(&self) -> bool {
        false
    }

    /// Volume of one voxel (m³).
    #[must_use]
    pub fn voxel_volume_m3(&self) -> f64 {
        self.spacing_m[0] * self.spacing_m[1] * self.spacing_m[2]
    }

    /// Linear index of voxel (i, j, k); the caller guarantees it is inside.
    #[inline]
    #[must_use]
    pub fn linear(&self, i: usize, j: usize, k: usize) -> usize {
        (k * self.dims[1] + j) * self.dims[0] + i
    }

    /// Continuous index coordinates of a world point (voxel centres at integers).
    #[inline]
    #[must_use]
    pub fn world_to_index(&self, p_world_m: &Point3<f64>) -> Vector3<f64> {
        let local = self.direction.tr_mul(&(p_world_m - self.origin_m));
        Vector3::new(local.x / self.spacing_m[0], local.y / self.spacing_m[1], local.z / self.spacing_m[2])
    }

    /// World position (m) of continuous index coordinates.
    #[inline]
    #[must_use]
    pub fn index_to_world(&self, ijk: &Vector3<f64>) -> Point3<f64> {
        let local = Vector3::new(ijk.x * self.spacing_m[0], ijk.y * self.spacing_m[1], ijk.z * self.spacing_m[2]);
        self.origin_m + self.direction * local
    }

    /// The voxel whose centre is nearest to `p_world_m`, or `None` outside the grid.
    #[inline]
    #[must_use]
    pub fn nearest_voxel(&self, p_world_m: &Point3<f64>) -> Option<[usize; 3]> {
        let c = self.world_to_index(p_world_m);
        let mut out = [0usize; 3];
        for axis in 0..3 {
            let r = super::rounding::round(c[axis]);
            if r.is_nan() || r < 0.0 || r >= self.dims[axis] as f64 {
                return None;
            }
            out[axis] = r as usize;
        }
        Some(out)
    }

    /// World-frame axis-aligned bounds (m) of the grid's voxel centres.
    #[must_use]
    pub fn world_bounds_m(&self) -> (Point3<f64>, Point3<f64>) {
        let mut lo = Point3::new(f64::INFINITY, f64::INFINITY, f64::INFINITY);
        let mut hi = Point3::new(f64::NEG_INFINITY, f64::NEG_INFINITY, f64::NEG_INFINITY);
        for corner in 0..8 {
            let ijk = Vector3::new(
                if corner & 1 == 0 { 0.0 } else { (self.dims[0] - 1) as f64 },
                if corner & 2 == 0 { 0.0 } else { (self.dims[1] - 1) as f64 },
                if corner & 4 == 0 { 0.0 } else { (self.dims[2] - 1) as f64 },
            );
            let p = self.index_to_world(&ijk);
            lo = lo.inf(&p);
            hi = hi.sup(&p);
        }
        (lo, hi)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::Rotation3;

    #[test]
    fn world_index_round_trip_with_rotation() {
        let rot = Rotation3::from_euler_angles(0.3, -0.2, 1.1).into_inner();
        let g = Grid::new([10, 20, 30], [0.5e-3, 0.6e-3, 0.7e-3], [0.01, -0.02, 0.03], rot).unwrap();
        let ijk = Vector3::new(3.25, 7.5, 11.0);
        let back = g.world_to_index(&g.index_to_world(&ijk));
        assert!((back - ijk).norm() < 1e-9);
    }

    #[test]
    fn rejects_bad_geometry() {
        let id = Matrix3::identity();
        assert!(Grid::new([0, 2, 2], [1e-3; 3], [0.0; 3], id).is_err());
        assert!(Grid::new([2, 2, 2], [0.0, 1e-3, 1e-3], [0.0; 3], id).is_err());
        assert!(Grid::new([2, 2, 2], [-1e-3, 1e-3, 1e-3], [0.0; 3], id).is_err());
        assert!(Grid::new([2, 2, 2], [1e-3; 3], [f64::NAN, 0.0, 0.0], id).is_err());
        assert!(Grid::new([2, 2, 2], [1e-3; 3], [0.0; 3], id * 2.0).is_err());
        let mirror = Matrix3::from_diagonal(&Vector3::new(-1.0, 1.0, 1.0));
        assert!(Grid::new([2, 2, 2], [1e-3; 3], [0.0; 3], mirror).is_err());
        assert!(Grid::new([1 << 11, 1 << 11, 1 << 10], [1e-3; 3], [0.0; 3], id).is_err());
        // Spacings outside SPACING_RANGE_M: a 1e-20 m voxel put points 0.2 m away at index
        // coordinates no integer holds.
        assert!(Grid::new([2, 2, 2], [1e-20, 1e-3, 1e-3], [0.0; 3], id).is_err());
        assert!(Grid::new([2, 2, 2], [1e-3, 1e-3, 0.5], [0.0; 3], id).is_err());
        assert!(
            Grid::new([2, 2, 2], [super::SPACING_RANGE_M[0], 1e-3, super::SPACING_RANGE_M[1]], [0.0; 3], id).is_ok()
        );
    }

    #[test]
    fn nearest_voxel_outside_and_nan() {
        let g = Grid::axis_aligned([4, 4, 4], [1e-3; 3], [0.0; 3]).unwrap();
        assert_eq!(g.nearest_voxel(&Point3::new(1.2e-3, 2.6e-3, 0.0)), Some([1, 3, 0]));
        assert_eq!(g.nearest_voxel(&Point3::new(-0.6e-3, 0.0, 0.0)), None);
        assert_eq!(g.nearest_voxel(&Point3::new(3.6e-3, 0.0, 0.0)), None);
        assert_eq!(g.nearest_voxel(&Point3::new(f64::NAN, 0.0, 0.0)), None);
    }
}
