//! Any bytes in a model reply: predictions that are finite and come from the payload, each taken
//! whole, then at most one refusal.
#![no_main]

use bone_sim::protocol::{decode_prediction, decode_predictions, MAX_QUERY_WINDOWS, PREDICTION};
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let mut taken = 0;
    let mut refused = false;
    for p in decode_predictions(data) {
        assert!(!refused, "nothing follows a refusal");
        match p {
            Ok(p) => {
                assert!(p.force_n.iter().all(|v| v.is_finite()), "a decoded prediction is finite");
                assert!(p.inference_s.is_finite());
                taken += PREDICTION.size + usize::from(u16::from_le_bytes([data[taken + 24], data[taken + 25]]));
                assert!(taken <= data.len(), "a prediction lies inside the payload");
                assert!(p.model_id.len() <= 3 * data.len(), "the model id comes from the payload");
            }
            Err(_) => refused = true,
        }
    }
    assert!(refused || taken == data.len(), "the whole payload is read or a refusal says why not");
    assert!(taken <= MAX_QUERY_WINDOWS * 4096);
    if let Ok(p) = decode_prediction(data) {
        assert_eq!(taken, data.len(), "one prediction alone is the whole payload");
        assert!(p.force_n.iter().all(|v| v.is_finite()));
    }
});
