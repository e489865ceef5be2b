//! The planned path A → B and where the drill is relative to it.

use nalgebra::{Point3, Vector3};
use parry3d::query::PointQuery;
use parry3d::shape::Segment;

use crate::error::{finite, SimError, SimResult};

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
        if length_m < 1e-4 {
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
}
