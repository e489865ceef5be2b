//! Any bytes in a model reply: a refusal, or a finite prediction.
#![no_main]

use bone_sim::protocol::decode_prediction;
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    if let Ok(p) = decode_prediction(data) {
        assert!(p.force_n.iter().all(|v| v.is_finite()), "a decoded prediction is finite");
        assert!(p.inference_s.is_finite());
        assert!(p.model_id.len() <= 3 * data.len(), "the model id comes from the payload");
    }
});
