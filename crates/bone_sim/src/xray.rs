//! X-ray views (digitally reconstructed radiographs) like the paper's Figure 5: line integrals of
//! linear attenuation, `∫ μ dl` (dimensionless), through the current bone along the volume's three
//! axes. With the world frame LPS (`docs/frames.md`) and an axis-aligned grid, these are the top
//! (along z), front (along y) and side (along x) views.
//!
//! The undrilled integrals are computed once per volume; a session's views subtract what its
//! drilled bricks removed, so a view costs O(drilled voxels), not O(volume).

use crate::volume::bricks::{MaterialOverlay, BRICK_EDGE};
use crate::volume::drilled::DrilledVolume;
use crate::volume::grid::Grid;
use crate::volume::material::MaterialTable;
use crate::volume::FULL_MATERIAL;

/// One of the three views.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum View {
    /// Along k (z, superior–inferior): image rows j, columns i.
    Top,
    /// Along j (y, anterior–posterior): image rows k, columns i.
    Front,
    /// Along i (x, left–right): image rows k, columns j.
    Side,
}

impl View {
    /// All views in the order top, front, side.
    pub const ALL: [View; 3] = [View::Top, View::Front, View::Side];

    /// Lower-case name (`top`, `front`, `side`).
    #[must_use]
    pub fn name(self) -> &'static str {
        match self {
            View::Top => "top",
            View::Front => "front",
            View::Side => "side",
        }
    }
}

/// The three line-integral images, row-major.
#[derive(Debug, Clone, PartialEq)]
pub struct Projections {
    dims: [usize; 3],
    spacing_m: [f64; 3],
    top: Vec<f64>,
    front: Vec<f64>,
    side: Vec<f64>,
}

impl Projections {
    /// Integrates the pristine volume (HU per voxel) along all three axes.
    #[must_use]
    pub fn integrate(grid: &Grid, hu: &[i16], table: &MaterialTable) -> Self {
        let mut p = Self::zeros(grid);
        let [nx, ny, nz] = grid.dims();
        for k in 0..nz {
            for j in 0..ny {
                let row = grid.linear(0, j, k);
                for i in 0..nx {
                    p.add(i, j, k, f64::from(table.attenuation_per_m(hu[row + i])));
                }
            }
        }
        p
    }

    fn zeros(grid: &Grid) -> Self {
        let [nx, ny, nz] = grid.dims();
        Self {
            dims: grid.dims(),
            spacing_m: grid.spacing_m(),
            top: vec![0.0; ny * nx],
            front: vec![0.0; nz * nx],
            side: vec![0.0; nz * ny],
        }
    }

    /// Adds a voxel of attenuation `mu_per_m` (1/m; negative to take it away) to all three views.
    #[inline]
    fn add(&mut self, i: usize, j: usize, k: usize, mu_per_m: f64) {
        let [nx, ny, _] = self.dims;
        self.top[j * nx + i] += mu_per_m * self.spacing_m[2];
        self.front[k * nx + i] += mu_per_m * self.spacing_m[1];
        self.side[k * ny + j] += mu_per_m * self.spacing_m[0];
    }

    /// One view's image and its `(rows, cols)`.
    #[must_use]
    pub fn view(&self, view: View) -> (&[f64], [usize; 2]) {
        let [nx, ny, nz] = self.dims;
        match view {
            View::Top => (&self.top, [ny, nx]),
            View::Front => (&self.front, [nz, nx]),
            View::Side => (&self.side, [nz, ny]),
        }
    }

    /// Heap bytes of the three images.
    #[must_use]
    pub fn memory_bytes(&self) -> usize {
        8 * (self.top.capacity() + self.front.capacity() + self.side.capacity())
    }
}

impl DrilledVolume {
    /// The three X-ray views of the bone as this session has drilled it.
    #[must_use]
    pub fn xray(&self) -> Projections {
        let volume = self.volume();
        let mut p = volume.pristine_xray().clone();
        let grid = volume.grid();
        let dims = grid.dims();
        let full = f64::from(FULL_MATERIAL);
        for (brick_id, brick) in self.overlay().owned() {
            let [i0, j0, k0] = self.overlay().brick_origin(brick_id);
            for k in k0..(k0 + BRICK_EDGE).min(dims[2]) {
                for j in j0..(j0 + BRICK_EDGE).min(dims[1]) {
                    for i in i0..(i0 + BRICK_EDGE).min(dims[0]) {
                        let l = grid.linear(i, j, k);
                        let gone = volume.pristine_material(l) - brick[MaterialOverlay::local(i, j, k)];
                        if gone > 0 {
                            let mu = f64::from(volume.table().attenuation_per_m(volume.hu()[l]));
                            p.add(i, j, k, -mu * f64::from(gone) / full);
                        }
                    }
                }
            }
        }
        // Float cancellation can leave tiny negatives where a whole ray was drilled out.
        for v in p.top.iter_mut().chain(p.front.iter_mut()).chain(p.side.iter_mut()) {
            *v = v.max(0.0);
        }
        p
    }

    /// The same views integrated voxel by voxel over the whole volume (slow; the reference the
    /// incremental [`xray`](Self::xray) is tested against).
    #[must_use]
    pub fn xray_full(&self) -> Projections {
        let volume = self.volume();
        let grid = volume.grid();
        let mut p = Projections::zeros(grid);
        let [nx, ny, nz] = grid.dims();
        let full = f64::from(FULL_MATERIAL);
        for k in 0..nz {
            for j in 0..ny {
                for i in 0..nx {
                    let l = grid.linear(i, j, k);
                    let mu = f64::from(volume.table().attenuation_per_m(volume.hu()[l]));
                    let kept = if volume.pristine_material(l) == 0 {
                        1.0
                    } else {
                        f64::from(self.overlay().material(volume, i, j, k)) / full
                    };
                    p.add(i, j, k, mu * kept);
                }
            }
        }
        p
    }
}
