//! The device limits, property-tested over random pose sequences (docs/frames.md, "Device
//! limits"): whatever poses arrive and whatever guidance is asked for (any mode, gain, model
//! reply), the force a session sends is finite, never above the peak,
//! never changes faster than the rate limit, and never uses more than the continuous budget of
//! the motors' thermal model.

mod common;

use bone_sim::guidance::GuidanceMode;
use bone_sim::{DeviceProfile, DrillingSession, Layer, PlannedPath, Pose, SessionConfig};
use common::{slab, H};
use nalgebra::{Point3, UnitQuaternion, Vector3};
use proptest::prelude::*;

const NXY: usize = 24;
const CENTRE: f64 = 12.0 * H;

/// One step of a random stylus: a move (m), a rotation (rad), the drill, its speed, and now and
/// then a pose that is lost or broken.
#[derive(Debug, Clone)]
struct Step {
    move_m: [f64; 3],
    tilt_rad: f64,
    drill_on: bool,
    rpm: f64,
    /// 0: a good pose; 1: none arrives; 2: NaN position; 3: absurd speed; 4: absurd position.
    fault: u8,
    /// Ticks this step is held.
    hold: u16,
}

fn step() -> impl Strategy<Value = Step> {
    (
        prop::array::uniform3(-0.4e-3..0.6e-3_f64),
        -0.05..0.05_f64,
        any::<bool>(),
        0.0..2000.0_f64,
        prop_oneof![8 => Just(0u8), 1 => Just(1u8), 1 => Just(2u8), 1 => Just(3u8), 1 => Just(4u8)],
        1u16..60,
    )
        .prop_map(|(move_m, tilt_rad, drill_on, rpm, fault, hold)| Step {
            move_m,
            tilt_rad,
            drill_on,
            rpm,
            fault,
            hold,
        })
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 48, ..ProptestConfig::default() })]

    #[test]
    fn forces_stay_within_the_device_limits(
        steps in prop::collection::vec(step(), 20..120),
        mode in prop::sample::select(GuidanceMode::ALL.to_vec()),
        gain in 0.0..4.0_f64,
        predicted in prop::array::uniform3(-5.0..5.0_f64),
    ) {
        let layers = [(Layer::Cortical, 1800.0, 3e-3), (Layer::Cancellous, 350.0, 6e-3)];
        let (vol, surface) = slab(NXY, &layers);
        let path = PlannedPath::new(Point3::new(CENTRE, CENTRE, surface), Point3::new(CENTRE, CENTRE, surface + 9e-3))
            .unwrap();
        let mut s = DrillingSession::new(vol, path, SessionConfig::default()).unwrap();
        // Guidance in any mode and gain, a model replying with anything every 100 ms.
        s.set_guidance(mode, gain).unwrap();
        let dev = DeviceProfile::geomagic_touch();
        let max_step = dev.max_force_rate_n_per_s * 1e-3;
        let mut p = Point3::new(CENTRE, CENTRE, surface - 2e-3);
        let mut tilt = UnitQuaternion::identity();
        let mut prev = Vector3::zeros();
        for st in &steps {
            p += Vector3::from(st.move_m);
            // Keep the stylus near the slab, as a hand would be.
            p.z = p.z.clamp(surface - 4e-3, surface + 10e-3);
            tilt = UnitQuaternion::from_axis_angle(&Vector3::x_axis(), st.tilt_rad) * tilt;
            let good = Pose { position_m: p, orientation: tilt, drill_on: st.drill_on, spindle_rpm: st.rpm };
            let pose = match st.fault {
                0 => Some(good),
                1 => None,
                2 => Some(Pose { position_m: Point3::new(f64::NAN, p.y, p.z), ..good }),
                3 => Some(Pose { spindle_rpm: 3.4e38, ..good }),
                _ => Some(Pose { position_m: Point3::new(1e30, p.y, p.z), ..good }),
            };
            for _ in 0..st.hold {
                if s.state().ticks % 100 == 0 {
                    s.set_prediction(Vector3::from(predicted));
                }
                let f = s.tick(pose.as_ref()).force_n;
                prop_assert!(f.iter().all(|v| v.is_finite()), "NaN force {f}");
                prop_assert!(f.norm() <= dev.peak_force_n + 1e-12, "|F| = {} above the peak", f.norm());
                prop_assert!((f - prev).norm() <= max_step + 1e-12, "a jump of {} N", (f - prev).norm());
                prop_assert!(s.state().device_thermal_load <= 1.0 + 1e-12, "load {}", s.state().device_thermal_load);
                prop_assert!(s.state().temperature_c.is_finite() && s.state().temperature_c < 150.0);
                prev = f;
            }
        }
    }
}

proptest! {
    /// On the wire the force and its guidance share are float32: rounding never makes them
    /// longer than what the limiter gave (a client's guard refuses a force over the peak).
    #[test]
    fn a_force_at_the_peak_is_not_over_it_on_the_wire(
        dir in prop::array::uniform3(-1.0..1.0_f64),
        peak in 0.1..50.0_f64,
    ) {
        let d = Vector3::from(dir);
        prop_assume!(d.norm() > 1e-3);
        let f = d.normalize() * peak;
        let bytes = bone_sim::protocol::encode_force(&bone_sim::protocol::ForceMsg {
            force_n: f,
            guidance_n: -f,
            ..Default::default()
        });
        let read = |at: usize| -> Vector3<f64> {
            Vector3::from_fn(|i, _| f64::from(f32::from_le_bytes(bytes[at + 4 * i..at + 4 * i + 4].try_into().unwrap())))
        };
        let (wire_f, wire_g) = (read(24), read(36));
        prop_assert!(wire_f.norm() <= f.norm(), "|F| on the wire {} over {}", wire_f.norm(), f.norm());
        prop_assert!(wire_g.norm() <= f.norm(), "|G| on the wire {} over {}", wire_g.norm(), f.norm());
        prop_assert!((wire_f - f).norm() < 1e-5 * peak);
    }
}
