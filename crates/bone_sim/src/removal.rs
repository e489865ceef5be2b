//! Material removal by a spherical burr.
//!
//! Each call erodes every voxel whose centre lies inside the burr (no per-call voxel cap: the
//! whole sphere is processed every time) and touches only the burr's bounding box. A voxel loses
//! `rate · dt` of its material per call, `rate = erosion_ref(layer, HU) · speed_factor(rpm) ·
//! contact` (see [`HuMapping`](crate::volume::material::HuMapping)); at zero material it is
//! removed.

use nalgebra::{Point3, Vector3};

use crate::error::{finite, non_negative, positive, SimError, SimResult};
use crate::volume::bricks::{MaterialOverlay, BRICK_EDGE};
use crate::volume::drilled::DrilledVolume;
use crate::volume::rounding;
use crate::volume::FULL_MATERIAL;

/// Largest burr radius accepted (m); surgical burrs and drills are a few millimetres.
pub const MAX_BURR_RADIUS_M: f64 = 0.02;
/// Smallest drill radius a session accepts (m): a 0.5 mm bit, below the thinnest Kirschner
/// wires (0.6 mm) used in orthopaedics, and a voxel's width at the phantom's 0.5 mm. A smaller
/// burr cuts nothing the volume can resolve.
pub const MIN_BURR_RADIUS_M: f64 = 0.25e-3;

/// A spherical burr in the world frame.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Burr {
    /// Centre of the burr (m, world frame).
    pub center_m: Point3<f64>,
    /// Radius (m).
    pub radius_m: f64,
}

/// How hard the burr is cutting during one call.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Cut {
    /// Spindle speed (rpm); zero or negative cuts nothing.
    pub spindle_rpm: f64,
    /// Duration of the call (s).
    pub dt_s: f64,
    /// Fraction of full cutting contact, 0..=1 (the force model sets it; 1 = fully engaged).
    pub contact: f64,
}

/// What one removal call did.
#[derive(Debug, Clone, Copy, Default, PartialEq, serde::Serialize)]
pub struct RemovalReport {
    /// Voxels inside the burr that held material and were eroded.
    pub voxels_eroded: u32,
    /// Voxels whose material reached zero in this call.
    pub voxels_removed: u32,
    /// Mass removed (kg).
    pub mass_removed_kg: f64,
    /// Material volume removed (m³): eroded fractions times the voxel volume.
    pub volume_removed_m3: f64,
}

impl RemovalReport {
    /// Adds another report's counts to this one.
    pub fn accumulate(&mut self, other: &RemovalReport) {
        self.voxels_eroded = self.voxels_eroded.saturating_add(other.voxels_eroded);
        self.voxels_removed = self.voxels_removed.saturating_add(other.voxels_removed);
        self.mass_removed_kg += other.mass_removed_kg;
        self.volume_removed_m3 += other.volume_removed_m3;
    }
}

impl Burr {
    /// Checks the burr's geometry.
    ///
    /// # Errors
    /// A non-finite centre, or a radius that is not in (0, [`MAX_BURR_RADIUS_M`]].
    pub fn validate(&self) -> SimResult<()> {
        finite("burr centre x (m)", self.center_m.x)?;
        finite("burr centre y (m)", self.center_m.y)?;
        finite("burr centre z (m)", self.center_m.z)?;
        positive("burr radius (m)", self.radius_m)?;
        if self.radius_m > MAX_BURR_RADIUS_M {
            return Err(SimError::InvalidParameter {
                name: "burr radius (m)",
                value: self.radius_m,
                reason: "must be at most 0.02 m",
            });
        }
        Ok(())
    }
}

impl Cut {
    /// Checks the cutting parameters.
    ///
    /// # Errors
    /// Non-finite values, a negative duration, or contact outside 0..=1.
    pub fn validate(&self) -> SimResult<()> {
        finite("spindle speed (rpm)", self.spindle_rpm)?;
        non_negative("dt (s)", self.dt_s)?;
        non_negative("contact", self.contact)?;
        if self.contact > 1.0 {
            return Err(SimError::InvalidParameter {
                name: "contact",
                value: self.contact,
                reason: "must be in 0..=1",
            });
        }
        Ok(())
    }
}

impl DrilledVolume {
    /// Erodes the material inside `burr` for one call of `cut`.
    ///
    /// # Errors
    /// An invalid burr or cut (nothing is changed then).
    pub fn remove(&mut self, burr: &Burr, cut: &Cut) -> SimResult<RemovalReport> {
        self.erode(burr, cut, None)
    }

    /// Erodes like [`remove`](Self::remove) a burr that has just advanced `advance_m` (m) along
    /// `axis` (the unit drilling direction), and removes at once what that advance swept: the
    /// burr's rear half (behind the plane through its centre normal to the axis), which its front
    /// has cut already, and the sliver of its front that the advance brought in (inside the burr
    /// now, outside it before). A drill occupies its own volume: the bore it leaves is as wide as
    /// its burr wherever its centre has passed, so it can always be withdrawn along it, and a
    /// burr carried on by the hand through the rim of an exit leaves no lip behind.
    ///
    /// # Errors
    /// An invalid burr, cut, axis or advance (nothing is changed then).
    pub fn remove_advancing(
        &mut self,
        burr: &Burr,
        cut: &Cut,
        axis: &Vector3<f64>,
        advance_m: f64,
    ) -> SimResult<RemovalReport> {
        if !(axis.iter().all(|v| v.is_finite()) && (axis.norm() - 1.0).abs() < 1e-6) {
            return Err(SimError::InvalidParameter {
                name: "drilling axis norm",
                value: axis.norm(),
                reason: "must be a finite unit vector",
            });
        }
        non_negative("advance (m)", advance_m)?;
        self.erode(burr, cut, Some((axis, advance_m)))
    }

    fn erode(&mut self, burr: &Burr, cut: &Cut, swept: Option<(&Vector3<f64>, f64)>) -> SimResult<RemovalReport> {
        burr.validate()?;
        cut.validate()?;
        // Borrow the shared volume and the overlay as disjoint fields (no Arc clone per call).
        let volume: &crate::volume::Volume = &self.volume;
        let table = volume.table();
        let scale = table.mapping().speed_factor(cut.spindle_rpm) * cut.contact * cut.dt_s;
        let mut report = RemovalReport::default();
        if scale <= 0.0 {
            return Ok(report);
        }
        // The swept test in metres along the grid's axes: with `a` the axis in the grid's frame,
        // a voxel at offset `d` from the centre is swept when d·a ≤ 0 (the rear half) or when it
        // lies outside the burr's sphere before the advance, |d + δ·a| > r.
        let swept = swept.map(|(axis, advance_m)| (volume.grid().direction().tr_mul(axis), advance_m));
        let grid = volume.grid();
        let dims = grid.dims();
        let h = grid.spacing_m();
        let c = grid.world_to_index(&burr.center_m);
        let r2 = burr.radius_m * burr.radius_m;
        let Some((k_lo, k_hi)) = span(c.z, burr.radius_m / h[2], dims[2]) else { return Ok(report) };
        let voxel_m3 = grid.voxel_volume_m3();
        let labels = volume.labels();
        let hus = volume.hu();
        let full = f64::from(FULL_MATERIAL);
        let mut mass_units = 0.0; // Σ decrement · density, in (material units · kg/m³)
        let mut material_units = 0u64;
        for k in k_lo..=k_hi {
            let dz = (k as f64 - c.z) * h[2];
            let rem_z = r2 - dz * dz;
            if rem_z < 0.0 {
                continue;
            }
            let Some((j_lo, j_hi)) = span(c.y, rem_z.sqrt() / h[1], dims[1]) else { continue };
            for j in j_lo..=j_hi {
                let dy = (j as f64 - c.y) * h[1];
                let rem_y = rem_z - dy * dy;
                if rem_y < 0.0 {
                    continue;
                }
                let Some((i_lo, i_hi)) = span(c.x, rem_y.sqrt() / h[0], dims[0]) else { continue };
                let row = grid.linear(0, j, k);
                // Walk the row one brick segment at a time: one table lookup per segment.
                let mut i = i_lo;
                while i <= i_hi {
                    let seg_end = ((i / BRICK_EDGE + 1) * BRICK_EDGE - 1).min(i_hi);
                    let brick_id = self.overlay.brick_id(i, j, k);
                    let owned = self.overlay.brick(brick_id).is_some();
                    // Copy a brick only if this segment has material to erode.
                    if owned || labels[row + i..=row + seg_end].iter().any(|&l| l != 0) {
                        let brick = self.overlay.brick_mut(volume, brick_id);
                        for ii in i..=seg_end {
                            let slot = &mut brick[MaterialOverlay::local(ii, j, k)];
                            if *slot == 0 {
                                continue;
                            }
                            let (label, hu) = (labels[row + ii], hus[row + ii]);
                            let cleared = swept.is_some_and(|(a, advance)| {
                                let d = Vector3::new((ii as f64 - c.x) * h[0], dy, dz);
                                d.dot(&a) <= 0.0 || (d + a * advance).norm_squared() > r2
                            });
                            let rate =
                                if cleared { 1.0 } else { f64::from(table.erosion_ref_per_s(label, hu)) * scale };
                            let dec = (rounding::ceil(rate * full) as u64).min(u64::from(*slot)) as u16;
                            *slot -= dec;
                            report.voxels_eroded += 1;
                            if *slot == 0 {
                                report.voxels_removed += 1;
                            }
                            material_units += u64::from(dec);
                            mass_units += f64::from(dec) * f64::from(table.density_kg_m3(label, hu));
                        }
                    }
                    i = seg_end + 1;
                }
            }
        }
        self.account(&mut report, mass_units / full * voxel_m3, material_units as f64 / full * voxel_m3);
        Ok(report)
    }

    /// Adds a call's removed mass (kg) and volume (m³) to its report and to the session's totals.
    fn account(&mut self, report: &mut RemovalReport, mass_kg: f64, volume_m3: f64) {
        report.mass_removed_kg = mass_kg;
        report.volume_removed_m3 = volume_m3;
        self.removed_mass_kg += mass_kg;
        self.removed_voxels += u64::from(report.voxels_removed);
    }

    /// Runs [`remove`](Self::remove) at each centre in turn (a scripted drill path), one `cut`
    /// per centre, and returns the summed report.
    ///
    /// # Errors
    /// An invalid burr radius, cut or centre; everything before the bad centre has been applied
    /// and stays applied.
    pub fn remove_along(&mut self, centers_m: &[Point3<f64>], radius_m: f64, cut: &Cut) -> SimResult<RemovalReport> {
        let mut total = RemovalReport::default();
        for center in centers_m {
            total.accumulate(&self.remove(&Burr { center_m: *center, radius_m }, cut)?);
        }
        Ok(total)
    }
}

/// Integer index range `[ceil(c − r), floor(c + r)]` clamped to `0..n`, or `None` if empty.
#[inline]
fn span(c: f64, r: f64, n: usize) -> Option<(usize, usize)> {
    let lo = rounding::ceil(c - r).max(0.0);
    let hi = rounding::floor(c + r).min(n as f64 - 1.0);
    if hi < lo {
        None
    } else {
        Some((lo as usize, hi as usize))
    }
}
