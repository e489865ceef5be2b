//! A `ZENOH_RUNTIME` Zenoh cannot read is an error naming it, not a panic (Zenoh parses the
//! variable once per process, so these checks share a binary of their own and one test).

use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;

use bone_sim::transport::check_zenoh_runtime;
use bone_sim::SimError;

#[test]
fn an_unreadable_zenoh_runtime_is_an_error_that_names_it_and_the_panic_hook_comes_back() {
    let printed = Arc::new(AtomicBool::new(false));
    let p = printed.clone();
    std::panic::set_hook(Box::new(move |_| p.store(true, Ordering::SeqCst)));
    std::env::set_var("ZENOH_RUNTIME", "(rx: (worker_threads: \"two\"))");
    // Several threads check at once: one parses, the others wait for its outcome.
    let errors: Vec<SimError> = (0..4)
        .map(|_| std::thread::spawn(check_zenoh_runtime))
        .collect::<Vec<_>>()
        .into_iter()
        .map(|t| t.join().expect("the check does not panic").expect_err("Zenoh cannot read this setting"))
        .collect();
    let message = errors[0].to_string();
    assert!(matches!(errors[0], SimError::InvalidConfig { .. }), "{message}");
    assert!(message.contains("ZENOH_RUNTIME") && message.contains("two"), "{message}");
    assert!(message.contains("ExpectedInteger at line 1, column 22"), "{message}");
    assert!(errors.iter().all(|e| e.to_string() == message));
    assert!(!printed.load(Ordering::SeqCst), "Zenoh's panic stays off the hook while it is caught");
    // The variable changed after Zenoh read it: said so, not the old reason under the new value.
    std::env::set_var("ZENOH_RUNTIME", "(rx: (worker_threads: 1))");
    let changed = check_zenoh_runtime().expect_err("Zenoh read it once already").to_string();
    assert!(changed.contains("when Zenoh read it") && changed.contains("restart"), "{changed}");
    std::env::remove_var("ZENOH_RUNTIME");
    assert!(check_zenoh_runtime().is_err(), "unset after a bad read: still refused, the process must restart");
    // The hook is this test's again.
    let _ = std::panic::catch_unwind(|| panic!("a panic after the check"));
    assert!(printed.load(Ordering::SeqCst), "the process's panic hook was put back");
}
