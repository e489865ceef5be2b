//! Any bytes in a batch of ticks: a refusal, or rows that are finite, as many as the header says,
//! and that encode back to the same bytes but for the reserved fields.
#![no_main]

use bone_sim::protocol::{decode_ticks, TickBatch};
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    if let Ok(rows) = decode_ticks(data) {
        assert_eq!(u32::from_le_bytes([data[4], data[5], data[6], data[7]]) as usize, rows.len());
        let mut again = TickBatch::with_capacity(rows.len());
        for r in &rows {
            assert!(r.position_m.iter().chain(&r.orientation_wxyz).all(|v| v.is_finite()));
            assert!(r.force_n.iter().chain(r.guidance_n.iter()).all(|v| v.is_finite()) && r.spindle_rpm.is_finite());
            again.push(r);
        }
        assert_eq!(decode_ticks(&again.take()).as_deref(), Ok(&rows[..]), "decoded rows round-trip");
    }
});
