//! The planned path A → B and where the drill is relative to it.

use nalgebra::{Point3, Vector3};
use parry3d::query::PointQuery;
use parry3d::shape::Segment;

use crate::error::{finite, SimError, SimResult};
use crate::volume::grid::Grid;
use crate::volume::layer::Layer;
use crate::volume::Volume;

/// The shortest planned path (m): 0.1 mm, under which A→B has no usable direction.
pub const MIN_PATH_LENGTH_M: f64 = 1e-4;
/// The finest sampling step [`PlannedPath::layer_runs`] takes (m): bounds the work to about a
/// million samples per metre of path.
pub const MIN_LAYER_STEP_M: f64 = 1e-6;

/// A stretch of the path over which the pristine bone reads one layer: the samples from
/// `start_m` to `end_m` (depths from A, m). A boundary lies between one run's end and the next
/// run's start.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LayerRun {
    /// The layer every sample of the run reads.
    pub layer: Layer,
    /// Depth of the run's first sample (m).
    pub start_m: f64,
    /// Depth of the run's last sample (m).
    pub end_m: f64,
}

/// A straight planned path from the entry point A to the target B (m, world frame).
#[derive(Debug, Clone)]
pub struct PlannedPath {
    entry_m: Point3<f64>,
    target_m: Point3<f64>,
    direction: Vector3<f64>,
    length_m: f64,
    /// The segment in parry's f32, relative to A (keeps f32 rounding at the micrometre level).
    segment: Segment,
}

impl PlannedPath {
    /// The path from `entry_m` to `target_m`.
    ///
    /// # Errors
    /// Non-finite points, or points closer than 0.1 mm.
    pub fn new(entry_m: Point3<f64>, target_m: Point3<f64>) -> SimResult<Self> {
        for (what, v) in [
            ("entry x (m)", entry_m.x),
            ("entry y (m)", entry_m.y),
            ("entry z (m)", entry_m.z),
            ("target x (m)", target_m.x),
            ("target y (m)", target_m.y),
            ("target z (m)", target_m.z),
        ] {
            finite(what, v)?;
        }
        let ab = target_m - entry_m;
        let length_m = ab.norm();
        if !length_m.is_finite() {
            return Err(SimError::InvalidParameter {
                name: "path length (m)",
                value: length_m,
                reason: "entry and target must be a finite distance apart",
            });
        }
        if length_m < MIN_PATH_LENGTH_M {
            return Err(SimError::InvalidParameter {
                name: "path length (m)",
                value: length_m,
                reason: "entry and target must be at least 0.1 mm apart",
            });
        }
        let b = ab.cast::<f32>();
        let segment = Segment::new(parry3d::math::Point::origin(), parry3d::math::Point::from(b));
        Ok(Self { entry_m, target_m, direction: ab / length_m, length_m, segment })
    }

    /// A (m).
    #[must_use]
    pub fn entry_m(&self) -> Point3<f64> {
        self.entry_m
    }

    /// B (m).
    #[must_use]
    pub fn target_m(&self) -> Point3<f64> {
        self.target_m
    }

    /// Unit vector from A to B.
    #[must_use]
    pub fn direction(&self) -> Vector3<f64> {
        self.direction
    }

    /// |AB| (m).
    #[must_use]
    pub fn length_m(&self) -> f64 {
        self.length_m
    }

    /// Penetration depth (m): the projection of `p` on A→B, measured from A (negative before A).
    #[must_use]
    pub fn depth_m(&self, p: &Point3<f64>) -> f64 {
        (p - self.entry_m).dot(&self.direction)
    }

    /// Lateral deviation (m): distance from `p` to the segment AB (the perpendicular distance to
    /// the path while the tip is between A and B).
    #[must_use]
    pub fn deviation_m(&self, p: &Point3<f64>) -> f64 {
        let rel = parry3d::math::Point::from((p - self.entry_m).cast::<f32>());
        f64::from(self.segment.distance_to_local_point(&rel, true))
    }

    /// Offset across the path (m): distance from `p` to the line through A and B, wherever along
    /// it, so a tip past B counts its offset across the path but not its overshoot along it
    /// (decision 0015).
    #[must_use]
    pub fn offset_from_line_m(&self, p: &Point3<f64>) -> f64 {
        let rel = p - self.entry_m;
        (rel - self.direction * rel.dot(&self.direction)).norm()
    }

    /// The pristine layers along A → B, as a surgeon reads them off the planning CT: samples
    /// every `step_m` (m) from A to B (the last at most `step_m / 2` past B), merged into runs.
    ///
    /// # Errors
    /// A step that is not finite or below [`MIN_LAYER_STEP_M`].
    pub fn layer_runs(&self, volume: &Volume, step_m: f64) -> SimResult<Vec<LayerRun>> {
        if !(step_m.is_finite() && step_m >= MIN_LAYER_STEP_M) {
            return Err(SimError::InvalidParameter {
                name: "layer sampling step (m)",
                value: step_m,
                reason: "must be finite and at least 1e-6 m",
            });
        }
        // As many samples as numpy's arange(0, L + step/2, step) gives, so Python agrees.
        let n = ((self.length_m + step_m / 2.0) / step_m).ceil().max(1.0) as usize;
        let last_m = (n - 1) as f64 * step_m;
        let mut runs: Vec<LayerRun> = Vec::new();
        let mut add = |layer: Layer, from_m: f64, to_m: f64| match runs.last_mut() {
            Some(run) if run.layer == layer => run.end_m = to_m,
            _ => runs.push(LayerRun { layer, start_m: from_m, end_m: to_m }),
        };
        // Only samples near the grid are looked up, so a path of any length costs what the
        // volume's size allows; the rest read outside.
        let inside = self
            .span_near(volume.grid(), last_m)
            .map(|(lo, hi)| ((lo / step_m).ceil() as usize, ((hi / step_m).floor() as usize).min(n - 1)));
        match inside {
            Some((first, last)) if first <= last => {
                if first > 0 {
                    add(Layer::Outside, 0.0, (first - 1) as f64 * step_m);
                }
                for i in first..=last {
                    let depth_m = i as f64 * step_m;
                    add(volume.layer_at(&(self.entry_m + self.direction * depth_m))?, depth_m, depth_m);
                }
                if last + 1 < n {
                    add(Layer::Outside, (last + 1) as f64 * step_m, last_m);
                }
            }
            _ => add(Layer::Outside, 0.0, last_m),
        }
        Ok(runs)
    }

    /// Where along the path (m from A) the pristine bone's first cortical stretch ends, sampled
    /// every `step_m` as [`layer_runs`](Self::layer_runs) samples it: halfway between the run's
    /// last sample and the next (at most |AB|). `None` when the path crosses no cortex or the
    /// step is invalid. Allocation-free, so a tick thread may call it.
    #[must_use]
    pub fn first_cortex_exit_m(&self, volume: &Volume, step_m: f64) -> Option<f64> {
        if !(step_m.is_finite() && step_m >= MIN_LAYER_STEP_M) {
            return None;
        }
        let n = ((self.length_m + step_m / 2.0) / step_m).ceil().max(1.0) as usize;
        let (first, last) = self
            .span_near(volume.grid(), (n - 1) as f64 * step_m)
            .map(|(lo, hi)| ((lo / step_m).ceil() as usize, ((hi / step_m).floor() as usize).min(n - 1)))?;
        let mut in_cortex = false;
        for i in first..=last {
            let depth_m = i as f64 * step_m;
            let cortical = volume.layer_at(&(self.entry_m + self.direction * depth_m)).ok() == Some(Layer::Cortical);
            if in_cortex && !cortical {
                return Some((depth_m - step_m / 2.0).min(self.length_m));
            }
            in_cortex |= cortical;
        }
        in_cortex.then(|| ((last as f64 + 0.5) * step_m).min(self.length_m))
    }

    /// The depths (m, within `0..=max_depth_m`) between which the path passes within a voxel of
    /// `grid`'s voxels (a slab test in index space), or `None` where it never does.
    fn span_near(&self, grid: &Grid, max_depth_m: f64) -> Option<(f64, f64)> {
        let a = grid.world_to_index(&self.entry_m);
        let per_m = grid.world_to_index(&(self.entry_m + self.direction)) - a;
        let dims = grid.dims();
        let (mut lo, mut hi) = (0.0_f64, max_depth_m);
        for k in 0..3 {
            // Nearest-voxel lookups hit the grid for index coordinates in [-0.5, dims - 0.5).
            let (min, max) = (-1.5, dims[k] as f64 + 0.5);
            if per_m[k].abs() < 1e-12 {
                if !(min..=max).contains(&a[k]) {
                    return None;
                }
            } else {
                let (t1, t2) = ((min - a[k]) / per_m[k], (max - a[k]) / per_m[k]);
                lo = lo.max(t1.min(t2));
                hi = hi.min(t1.max(t2));
            }
        }
        (lo <= hi).then_some((lo, hi))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn depth_and_deviation() {
        let path = PlannedPath::new(Point3::new(0.01, 0.02, 0.03), Point3::new(0.01, 0.02, 0.13)).unwrap();
        let p = Point3::new(0.013, 0.02, 0.08);
        assert!((path.depth_m(&p) - 0.05).abs() < 1e-12);
        assert!((path.deviation_m(&p) - 0.003).abs() < 1e-7);
        // Beyond B the deviation is the distance to B.
        let q = Point3::new(0.01, 0.02, 0.14);
        assert!((path.deviation_m(&q) - 0.01).abs() < 1e-7);
        assert!(PlannedPath::new(Point3::origin(), Point3::origin()).is_err());
        assert!(PlannedPath::new(Point3::new(f64::NAN, 0.0, 0.0), Point3::new(1.0, 0.0, 0.0)).is_err());
    }

    #[test]
    fn layer_runs_cover_the_path_in_order() {
        // A cube of 20 cortical voxels (0.5 mm, centres 2.0 to 11.5 mm) with 4 voxels of air around.
        let vol = crate::volume::test_support::uniform_block(28, 0.5e-3, Layer::Cortical, 1500.0, 4);
        let c = 7e-3;
        let path = PlannedPath::new(Point3::new(0.0, c, c), Point3::new(13.5e-3, c, c)).unwrap();
        let runs = path.layer_runs(&vol, 0.1e-3).unwrap();
        let names: Vec<Layer> = runs.iter().map(|r| r.layer).collect();
        assert_eq!(names, [Layer::Outside, Layer::Cortical, Layer::Outside]);
        // Runs tile the samples: each starts one step after the previous one ends.
        for w in runs.windows(2) {
            assert!((w[1].start_m - w[0].end_m - 0.1e-3).abs() < 1e-12);
        }
        // The cortex's voxels span 1.75 to 11.75 mm; its samples lie within 0.1 mm inside.
        assert!((runs[1].start_m - 1.8e-3).abs() < 0.06e-3, "{runs:?}");
        assert!((runs[1].end_m - 11.7e-3).abs() < 0.06e-3, "{runs:?}");
        assert!((runs[2].end_m - 13.5e-3).abs() < 0.06e-3, "{runs:?}");
        assert!(path.layer_runs(&vol, 0.0).is_err());
        assert!(path.layer_runs(&vol, f64::NAN).is_err());
        // The first cortex's exit, as a surgeon reads it off the runs: halfway to the next sample.
        let exit = path.first_cortex_exit_m(&vol, 0.1e-3).unwrap();
        assert!((exit - (runs[1].end_m + 0.05e-3)).abs() < 1e-12, "{exit} vs {runs:?}");
        let air = PlannedPath::new(Point3::new(0.0, 0.0, 0.5e-3), Point3::new(13.5e-3, 0.0, 0.5e-3)).unwrap();
        assert_eq!(air.first_cortex_exit_m(&vol, 0.1e-3), None);
    }

    /// Every sample looked up, the plain way the clipped sampling must agree with.
    fn every_sample(path: &PlannedPath, vol: &Volume, step_m: f64) -> Vec<(Layer, f64, f64)> {
        let n = ((path.length_m() + step_m / 2.0) / step_m).ceil() as usize;
        let mut runs: Vec<(Layer, f64, f64)> = Vec::new();
        for i in 0..n {
            let d = i as f64 * step_m;
            let layer = vol.layer_at(&(path.entry_m() + path.direction() * d)).unwrap();
            match runs.last_mut() {
                Some(r) if r.0 == layer => r.2 = d,
                _ => runs.push((layer, d, d)),
            }
        }
        runs
    }

    #[test]
    fn layer_runs_look_up_only_near_the_grid_and_agree_with_every_sample() {
        let vol = crate::volume::test_support::uniform_block(28, 0.5e-3, Layer::Cortical, 1500.0, 4);
        let c = 7e-3;
        // Oblique paths that start and end well outside the grid, one that misses it, one inside.
        let cases = [
            (Point3::new(-0.02, -0.01, c), Point3::new(0.03, 0.025, c + 0.004)),
            (Point3::new(0.03, c, -0.02), Point3::new(-0.01, c + 0.001, 0.04)),
            (Point3::new(-0.02, 0.05, c), Point3::new(0.03, 0.05, c)),
            (Point3::new(3e-3, 4e-3, 5e-3), Point3::new(9e-3, 10e-3, 11e-3)),
        ];
        for (a, b) in cases {
            let path = PlannedPath::new(a, b).unwrap();
            for step in [0.1e-3, 0.25e-3, 0.7e-3] {
                let got: Vec<(Layer, f64, f64)> =
                    path.layer_runs(&vol, step).unwrap().iter().map(|r| (r.layer, r.start_m, r.end_m)).collect();
                assert_eq!(got, every_sample(&path, &vol, step), "{a} -> {b} every {step} m");
            }
        }
        // A path a thousand kilometres long costs what the grid's size allows, not 4e9 lookups.
        let far = PlannedPath::new(Point3::new(-1e-3, c, c), Point3::new(1e6, c, c)).unwrap();
        let runs = far.layer_runs(&vol, 0.25e-3).unwrap();
        assert_eq!(runs.iter().map(|r| r.layer).collect::<Vec<_>>(), [Layer::Outside, Layer::Cortical, Layer::Outside]);
        assert!(runs[2].end_m >= 1e6 - 0.25e-3);
        assert!(PlannedPath::new(Point3::new(-1e300, 0.0, 0.0), Point3::new(1e300, 0.0, 0.0)).is_err());
    }
}
