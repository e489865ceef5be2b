//! A `ZENOH_RUNTIME` Zenoh cannot read is an error naming it, not a panic (Zenoh parses the
//! variable once per process, so this test has a binary of its own).

use bone_sim::transport::check_zenoh_runtime;
use bone_sim::SimError;

#[test]
fn an_unreadable_zenoh_runtime_is_an_error_that_names_it() {
    std::env::set_var("ZENOH_RUNTIME", "(rx: (worker_threads: \"two\"))");
    let err = check_zenoh_runtime().expect_err("Zenoh cannot read this runtime setting");
    assert!(matches!(err, SimError::InvalidConfig { .. }), "{err:?}");
    let message = err.to_string();
    assert!(
        message.contains("ZENOH_RUNTIME") && message.contains("two") && message.contains("ExpectedInteger"),
        "{message}"
    );
    // Asked again (Zenoh's parse is spent), still an error, still no panic.
    assert!(check_zenoh_runtime().is_err());
}
