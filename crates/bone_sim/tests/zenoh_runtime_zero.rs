//! A `ZENOH_RUNTIME` Zenoh parses but tokio cannot build (zero threads) is refused too, before a
//! session would panic on it (a binary of its own: Zenoh reads the variable once per process).

use bone_sim::transport::check_zenoh_runtime;

#[test]
fn a_zenoh_runtime_of_zero_threads_is_refused() {
    std::env::set_var("ZENOH_RUNTIME", "(net: (worker_threads: 0))");
    let message = check_zenoh_runtime().expect_err("zero worker threads").to_string();
    assert!(
        message.contains("ZENOH_RUNTIME") && message.contains("the net runtime needs at least one thread"),
        "{message}"
    );
}
