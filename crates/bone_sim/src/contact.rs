//! Contact between the burr and the remaining bone, sampled at points on the burr's surface.
//!
//! The burr is probed at 64 directions spread evenly over the sphere (a Fibonacci lattice). At
//! each probe point the remaining material fraction is interpolated trilinearly, so the surface
//! the proxy rests on moves smoothly as material erodes rather than in voxel steps. A point is
//! "in contact" where the fraction is at least one half (the iso-surface between full and empty
//! voxels).
//!
//! The cutting zone is the burr's front cap within 59° of the drill axis, like a 118° drill
//! point, sampled a voxel ahead of the burr along the axis: the bone the advancing burr meets
//! next, and never the wall of its own bore (a radial shell would read the wall at the cap's
//! edge, so a burr back in its bore would cut air as if it were bone). Its density falls over the
//! cap's axial length (≈ 0.5 r) as the burr leaves the bone, which makes the resistance collapse
//! progressively at breakthrough.

use nalgebra::{Point3, Vector3};

use crate::volume::drilled::DrilledVolume;
use crate::volume::grid::Grid;
use crate::volume::layer::Layer;

/// Probe points on the burr.
pub const PROBE_POINTS: usize = 64;
/// cos(59°): probe directions at least this aligned with the axis form the cutting cap. 59° is
/// half a 118° point angle, the standard twist drill's, which Saha, Pal & Albright (1982, J.
/// Biomech. Eng. 104:245) kept for their improved surgical drill (many orthopaedic drills are
/// ground to 90°); the cap then covers the lips that cut, not the flanks.
pub const CAP_COS: f64 = 0.515;
/// Material fraction from which a probe point counts as touching bone: half a voxel, the
/// project's choice (the surface of a partly drilled voxel is where its material halves).
const SOLID: f64 = 0.5;
/// Material fraction above which a cutting-cap point counts as bone ahead of the drill: the
/// project's choice, low so that a thin rim of bone left by the burr still cuts.
const PRESENT: f64 = 0.05;

/// What the probe points inside the burr's contact shell found.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Contact {
    /// Probe points touching bone.
    pub points: u32,
    /// Sum of the material gradients (world frame, per metre) at those points: it points into the
    /// bone, and on a flat face it is exactly the face's normal.
    pub gradient_sum: Vector3<f64>,
}

impl Contact {
    /// Outward surface normal at the contact (pointing from the bone to the burr centre), if any.
    #[must_use]
    pub fn normal(&self) -> Option<Vector3<f64>> {
        let n = self.gradient_sum.norm();
        (self.points > 0 && n > 1e-12).then(|| -self.gradient_sum / n)
    }
}

/// The bone in the burr's cutting cap.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CuttingZone {
    /// Mean over the cap's probe points of the (pristine) cutting density where bone remains,
    /// zero where it is gone (kg/m³).
    pub density_kg_m3: f64,
    /// The layer of most of the cap's points that still hold bone (`Outside` if none).
    pub layer: Layer,
    /// Mean pristine cutting density (kg/m³) straight ahead of the burr along its axis, half a
    /// voxel to a voxel and a half beyond its front: what the undrilled bone there is made of.
    /// A burr in its own bore sees the bone it drilled away; one at an exit sees what lies
    /// beyond the cortex.
    pub ahead_pristine_density_kg_m3: f64,
}

/// Probe points of a burr of a given radius, precomputed in the grid's index space so a
/// query does no trigonometry and no allocation.
#[derive(Debug, Clone)]
pub struct BurrProbe {
    radius_m: f64,
    directions: [Vector3<f64>; PROBE_POINTS],
    /// Offsets (index units) of the contact shell, half a voxel inside the burr's radius.
    contact_idx: [Vector3<f64>; PROBE_POINTS],
    /// Offsets (index units) of the burr's surface; the cutting cap samples it shifted a voxel
    /// forward along the drill axis (half a voxel beyond what the burr removes): the bone the
    /// burr's front would meet next, never the wall of its own bore.
    surface_idx: [Vector3<f64>; PROBE_POINTS],
    /// One voxel, the cap's forward shift (m).
    voxel_m: f64,
}

impl BurrProbe {
    /// Probe points for a burr of `radius_m` (m) on `grid`.
    #[must_use]
    pub fn new(grid: &Grid, radius_m: f64) -> Self {
        let golden = std::f64::consts::PI * (3.0 - 5f64.sqrt());
        let mut directions = [Vector3::zeros(); PROBE_POINTS];
        for (i, d) in directions.iter_mut().enumerate() {
            let z = 1.0 - (i as f64 + 0.5) * 2.0 / PROBE_POINTS as f64;
            let r = (1.0 - z * z).sqrt();
            let phi = golden * i as f64;
            *d = Vector3::new(r * phi.cos(), r * phi.sin(), z);
        }
        let h = grid.spacing_m();
        let half_voxel = 0.5 * h[0].min(h[1]).min(h[2]);
        let to_idx = |v: Vector3<f64>| {
            let local = grid.direction().tr_mul(&v);
            Vector3::new(local.x / h[0], local.y / h[1], local.z / h[2])
        };
        // The contact shell sits half a voxel inside the burr and removal reaches half a voxel
        // beyond it: the interpolated surface of what the burr has cut then always lies clear of
        // the contact shell, so a proxy can never be held by material its burr cannot reach.
        let contact_idx = directions.map(|d| to_idx(d * (radius_m - half_voxel).max(0.5 * radius_m)));
        let surface_idx = directions.map(|d| to_idx(d * radius_m));
        Self { radius_m, directions, contact_idx, surface_idx, voxel_m: 2.0 * half_voxel }
    }

    /// The burr radius (m).
    #[must_use]
    pub fn radius_m(&self) -> f64 {
        self.radius_m
    }

    /// Radius (m) of the sphere whose material the burr removes: half a voxel beyond its radius.
    #[must_use]
    pub fn cutting_radius_m(&self, grid: &Grid) -> f64 {
        let h = grid.spacing_m();
        self.radius_m + 0.5 * h[0].min(h[1]).min(h[2])
    }

    /// Probe points touching bone for a burr centred at `center_m`. With
    /// `ignore = Some((axis, cos))` the points within `acos(cos)` of `axis` are ignored: with
    /// [`CAP_COS`], the cutting cap (while drilling, the cap is the cutting law's business, not the
    /// contact's); with 0, the whole front half (a burr running on through the rim of an exit).
    #[must_use]
    pub fn contact(
        &self,
        bone: &DrilledVolume,
        center_m: &Point3<f64>,
        ignore: Option<(Vector3<f64>, f64)>,
    ) -> Contact {
        let c = bone.volume().grid().world_to_index(center_m);
        let grid = bone.volume().grid();
        let h = grid.spacing_m();
        let mut out = Contact { points: 0, gradient_sum: Vector3::zeros() };
        for (dir, off) in self.directions.iter().zip(&self.contact_idx) {
            if ignore.is_some_and(|(axis, cos)| dir.dot(&axis) >= cos) {
                continue;
            }
            let (m, g) = bone.material_and_gradient_at_index(&(c + off));
            if m >= SOLID {
                out.points += 1;
                out.gradient_sum += grid.direction() * Vector3::new(g.x / h[0], g.y / h[1], g.z / h[2]);
            }
        }
        out
    }

    /// The bone in the cutting cap of a burr centred at `center_m` drilling along `axis` (unit).
    #[must_use]
    pub fn cutting_zone(&self, bone: &DrilledVolume, center_m: &Point3<f64>, axis: &Vector3<f64>) -> CuttingZone {
        let volume = bone.volume();
        // The cap's shell: the burr's front surface shifted forward by a voxel.
        let c = volume.grid().world_to_index(&(center_m + axis * self.voxel_m));
        let mut density_sum = 0.0;
        let mut count = 0u32;
        let mut per_layer = [0.0f64; Layer::COUNT];
        for (dir, off) in self.directions.iter().zip(&self.surface_idx) {
            if dir.dot(axis) < CAP_COS {
                continue;
            }
            count += 1;
            let p = c + off;
            // The drill point meets intact bone wherever any material is left: the erosion lag
            // of the removal model must not make bone ahead look softer (or harder) than it is.
            let m = bone.material_at_index(&p);
            if m <= PRESENT {
                continue;
            }
            if let Some(l) = volume.nearest_index(&p) {
                let (label, hu) = (volume.labels()[l], volume.hu()[l]);
                density_sum += f64::from(volume.table().cutting_density_kg_m3(label, hu));
                per_layer[usize::from(label)] += 1.0;
            }
        }
        // Straight ahead along the axis, in the pristine bone: the nearest voxel's density at two
        // points half a voxel and a voxel and a half beyond the front.
        let mut ahead = 0.0;
        for beyond in [0.5 * self.voxel_m, 1.5 * self.voxel_m] {
            let p = volume.grid().world_to_index(&(center_m + axis * (self.radius_m + beyond)));
            if let Some(l) = volume.nearest_index(&p) {
                let (label, hu) = (volume.labels()[l], volume.hu()[l]);
                ahead += 0.5 * f64::from(volume.table().cutting_density_kg_m3(label, hu));
            }
        }
        let layer = (1..Layer::COUNT)
            .filter(|&i| per_layer[i] > 0.0)
            .max_by(|&a, &b| per_layer[a].total_cmp(&per_layer[b]))
            .and_then(|i| Layer::from_id(i as u8))
            .unwrap_or(Layer::Outside);
        CuttingZone {
            density_kg_m3: if count > 0 { density_sum / f64::from(count) } else { 0.0 },
            layer,
            ahead_pristine_density_kg_m3: ahead,
        }
    }
}
