//! Any bytes on a pose key: a refusal, or a pose the tick may use as it is.
#![no_main]

use bone_sim::protocol::{decode_pose, encode_pose};
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    if let Ok(msg) = decode_pose(data) {
        let p = &msg.pose;
        assert!(p.position_m.iter().all(|v| v.is_finite()), "a decoded position is finite");
        assert!(p.spindle_rpm.is_finite() && p.spindle_rpm >= 0.0, "a decoded spindle speed is finite, >= 0");
        let q = p.orientation.quaternion();
        assert!((q.norm() - 1.0).abs() < 1e-6, "a decoded orientation is a unit quaternion");
        // What decodes re-encodes to a payload that decodes to the same pose.
        assert_eq!(
            decode_pose(&encode_pose(&msg)).map(|m| (m.seq, m.client_time_ns)),
            Ok((msg.seq, msg.client_time_ns))
        );
    }
});
