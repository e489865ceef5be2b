//! X-ray views: the incremental views equal a full re-integration, and drilling shows.

// Exact float comparisons are intended: untouched values must be bit-identical.
#![allow(clippy::float_cmp, clippy::cast_lossless)]

mod common;

use bone_sim::{Burr, Cut, DrilledVolume, Layer, View};
use common::{block, H};
use nalgebra::Point3;

#[test]
fn incremental_views_match_full_integration_after_drilling() {
    let v = block(30, Layer::Cortical, 1500.0);
    let mut d = DrilledVolume::new(v.clone());
    let cut = Cut { spindle_rpm: 1500.0, dt_s: 0.05, contact: 1.0 };
    for step in 0..20 {
        let c = Point3::new((5.0 + step as f64) * H, 14.2 * H, 15.6 * H);
        d.remove(&Burr { center_m: c, radius_m: 1.25e-3 }, &cut).unwrap();
    }
    let (fast, full) = (d.xray(), d.xray_full());
    for view in View::ALL {
        let (a, shape_a) = fast.view(view);
        let (b, shape_b) = full.view(view);
        assert_eq!(shape_a, shape_b);
        let worst = a.iter().zip(b).map(|(x, y)| (x - y).abs()).fold(0.0, f64::max);
        assert!(worst < 1e-9, "{} view differs by {worst}", view.name());
    }
}

#[test]
fn drilling_darkens_the_views_where_bone_was_removed() {
    let v = block(30, Layer::Cortical, 1500.0);
    let mut d = DrilledVolume::new(v.clone());
    let before = d.xray();
    assert_eq!(&before, v.pristine_xray());
    let c = Point3::new(14.0 * H, 14.0 * H, 14.0 * H);
    d.remove(&Burr { center_m: c, radius_m: 2e-3 }, &Cut { spindle_rpm: 1500.0, dt_s: 2.0, contact: 1.0 }).unwrap();
    let after = d.xray();
    for view in View::ALL {
        let (a, [_, cols]) = after.view(view);
        let (b, _) = before.view(view);
        let centre_px = 14 * cols + 14;
        assert!(a[centre_px] < b[centre_px] - 0.01, "{} view unchanged at the hole", view.name());
        assert_eq!(a[0], b[0], "{} view changed far from the hole", view.name());
    }
}
