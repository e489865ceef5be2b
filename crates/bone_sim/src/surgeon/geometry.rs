//! The geometry of the surgeon's reach: a minimum-jerk profile, a frame across the drill axis, and
//! the stylus orientation that points the drill along the path.

use nalgebra::Vector3;

/// Minimum-jerk position profile from 0 to 1 (Flash & Hogan 1985).
pub(super) fn min_jerk(t: f64, duration: f64) -> f64 {
    let x = (t / duration).clamp(0.0, 1.0);
    x.powi(3) * (10.0 - 15.0 * x + 6.0 * x * x)
}

/// Two unit vectors across the unit direction `d`, with `d` a right-handed frame.
pub(super) fn basis(d: &Vector3<f64>) -> (Vector3<f64>, Vector3<f64>) {
    let helper = if d.x.abs() < 0.9 { Vector3::x() } else { Vector3::y() };
    let e1 = d.cross(&helper).normalize();
    (e1, d.cross(&e1))
}

/// The stylus orientation (w, x, y, z) that points the drill's +z along the unit direction `d`.
#[must_use]
pub fn axis_quaternion(d: &Vector3<f64>) -> [f64; 4] {
    let c = Vector3::z().cross(d);
    let q = nalgebra::Vector4::new(1.0 + d.z, c.x, c.y, c.z);
    let n = q.norm();
    if n > 1e-9 {
        [q.x / n, q.y / n, q.z / n, q.w / n]
    } else {
        [0.0, 1.0, 0.0, 0.0]
    }
}
