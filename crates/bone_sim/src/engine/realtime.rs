//! Best-effort scheduling of the server's latency-critical threads.
//!
//! With `SCHED_FIFO` the tick thread preempts the Zenoh, Python and model threads when its
//! deadline comes, which is what kept missed ticks at zero on a loaded machine while it ran every
//! tick (`--tick-on thread`, the only mode that asks for it since the poses' threads run the
//! ticks: `docs/decisions/0033-the-tick-thread-yields-to-the-poses.md`). It needs
//! `CAP_SYS_NICE` (or an `rtprio` limit); without it the thread keeps normal scheduling and the
//! health report says so.
//!
//! Without privilege, a thread can still ask Linux's EEVDF scheduler (6.12 and later) for a
//! short time slice: it keeps its normal policy and fair share, but when it wakes it preempts a
//! running thread with a longer slice instead of waiting out that thread's slice (up to a few
//! ms on a busy machine). The server asks for it for the tick thread (when it has no
//! `SCHED_FIFO`), the thread that publishes the forces, and Zenoh's I/O threads.

/// `SCHED_FIFO` priority: above ordinary real-time helpers, below the kernel's own (99).
///
/// Why this value: `docs/decisions/0007-realtime-priority.md`.
#[cfg(target_os = "linux")]
pub const FIFO_PRIORITY: i32 = 80;

/// The slice asked for (ns): 0.1 ms, the shortest the kernel grants (the default is 0.7 ms
/// times 1 + log2 of the core count, up to 2.8 ms).
///
/// Why this value: `docs/decisions/0004-short-time-slices.md`.
pub const LATENCY_SLICE_NS: u64 = 100_000;

/// Asks for `SCHED_FIFO` for the calling thread; returns whether it was granted.
#[cfg(target_os = "linux")]
#[allow(unsafe_code)] // libc has no safe wrapper for these calls
pub(crate) fn promote() -> bool {
    let param = libc::sched_param { sched_priority: FIFO_PRIORITY };
    // SAFETY: `param` is a valid sched_param; pid 0 names the calling thread.
    unsafe { libc::sched_setscheduler(0, libc::SCHED_FIFO, &raw const param) == 0 }
}

/// Asks for a [`LATENCY_SLICE_NS`] slice for thread `tid` of this process (0: the calling
/// thread), keeping its policy and nice value. A thread under a real-time policy (the whole
/// process started with `chrt`, say) is left alone: the request would move it to the fair
/// class. Returns whether the kernel now reports that slice: older kernels accept the request
/// and ignore it, so it is read back.
#[cfg(target_os = "linux")]
#[allow(unsafe_code)]
#[must_use]
pub fn short_slice(tid: i32) -> bool {
    let size = std::mem::size_of::<libc::sched_attr>() as u32;
    let get = |attr: &mut libc::sched_attr| {
        // SAFETY: `attr` is a sched_attr of `size` bytes; the kernel writes at most that many.
        unsafe { libc::syscall(libc::SYS_sched_getattr, tid, &raw mut *attr, size, 0) == 0 }
    };
    // SAFETY: sched_attr is plain data, and all zeros is a valid value.
    let mut attr: libc::sched_attr = unsafe { std::mem::zeroed() };
    let fair = [libc::SCHED_OTHER, libc::SCHED_BATCH].map(|p| p as u32);
    if !get(&mut attr) || !fair.contains(&attr.sched_policy) {
        return false;
    }
    attr.size = size;
    attr.sched_flags = 0;
    attr.sched_runtime = LATENCY_SLICE_NS;
    // SAFETY: `attr` is a fully initialised sched_attr of `size` bytes that outlives the call.
    if unsafe { libc::syscall(libc::SYS_sched_setattr, tid, &raw const attr, 0) } != 0 {
        return false;
    }
    get(&mut attr) && attr.sched_runtime == LATENCY_SLICE_NS
}

/// Asks for the short slice for every thread of this process whose name starts with one of
/// `prefixes`; returns how many have it. Reads `/proc/self/task`: not for a real-time path.
#[cfg(target_os = "linux")]
#[must_use]
pub fn short_slice_named(prefixes: &[&str]) -> usize {
    let Ok(tasks) = std::fs::read_dir("/proc/self/task") else { return 0 };
    tasks
        .flatten()
        .filter(|task| {
            let name = std::fs::read_to_string(task.path().join("comm")).unwrap_or_default();
            prefixes.iter().any(|p| name.starts_with(p))
        })
        .filter_map(|task| task.file_name().to_str()?.parse::<i32>().ok())
        .filter(|&tid| short_slice(tid))
        .count()
}

/// Other systems: normal scheduling.
#[cfg(not(target_os = "linux"))]
pub(crate) fn promote() -> bool {
    false
}

/// Other systems: nothing to ask for.
#[cfg(not(target_os = "linux"))]
#[must_use]
pub fn short_slice(_tid: i32) -> bool {
    false
}

/// Other systems: nothing to ask for.
#[cfg(not(target_os = "linux"))]
#[must_use]
pub fn short_slice_named(_prefixes: &[&str]) -> usize {
    0
}

#[cfg(all(test, target_os = "linux"))]
mod tests {
    use super::*;

    /// The slice the kernel reports for the calling thread, where it reports one (6.6 and later).
    fn reported_slice_ns() -> Option<u64> {
        let sched = std::fs::read_to_string("/proc/thread-self/sched").ok()?;
        let line = sched.lines().find(|l| l.starts_with("se.slice"))?;
        line.split(':').nth(1)?.trim().parse().ok()
    }

    /// The calling thread's policy and `sched_runtime` as `sched_getattr` reports them, read here
    /// independently of the code under test.
    #[allow(unsafe_code)]
    fn getattr() -> (u32, u64) {
        let size = std::mem::size_of::<libc::sched_attr>() as u32;
        // SAFETY: sched_attr is plain data, and all zeros is a valid value.
        let mut attr: libc::sched_attr = unsafe { std::mem::zeroed() };
        // SAFETY: `attr` is a sched_attr of `size` bytes; the kernel writes at most that many.
        let rc = unsafe { libc::syscall(libc::SYS_sched_getattr, 0, &raw mut attr, size, 0) };
        assert_eq!(rc, 0, "sched_getattr failed: {}", std::io::Error::last_os_error());
        (attr.sched_policy, attr.sched_runtime)
    }

    #[test]
    fn short_slice_reports_honestly_what_the_kernel_now_has() {
        std::thread::spawn(|| {
            let (policy_before, runtime_before) = getattr();
            let before = reported_slice_ns();
            let granted = short_slice(0);
            let (policy, runtime) = getattr();
            let now = reported_slice_ns();
            eprintln!(
                "policy {policy_before}, sched_runtime {runtime_before} ns, se.slice {before:?} ns; \
                 granted: {granted}; now policy {policy}, sched_runtime {runtime} ns, se.slice {now:?} ns"
            );
            // True on any kernel: the answer is whether the kernel now reports the short slice.
            assert_eq!(
                granted,
                runtime == LATENCY_SLICE_NS,
                "short_slice said {granted}, the kernel reports {runtime} ns"
            );
            assert_eq!(policy, policy_before, "the request changed the thread's policy");
            if let Some(now) = now {
                // Where the scheduler shows its slice (6.6 and later), it agrees with the answer.
                assert_eq!(granted, now == LATENCY_SLICE_NS, "short_slice said {granted}, se.slice is {now} ns");
            }
            if !granted {
                // Refused (older kernel, or a kernel without custom slices): nothing was changed.
                assert_eq!(runtime, runtime_before, "a refused request changed sched_runtime");
                assert_eq!(now, before, "a refused request changed the slice");
            }
        })
        .join()
        .unwrap();
    }

    #[test]
    fn a_real_time_thread_keeps_its_policy_and_a_fair_one_its_nice_value() {
        std::thread::spawn(|| {
            // SAFETY: plain libc calls on the calling thread.
            #[allow(unsafe_code)]
            let (nice_set, policy) = unsafe {
                let tid = libc::gettid();
                let ok = libc::setpriority(libc::PRIO_PROCESS, tid as libc::id_t, 3) == 0;
                (ok, libc::sched_getscheduler(0))
            };
            assert_eq!(policy, libc::SCHED_OTHER);
            let granted = short_slice(0);
            // SAFETY: as above.
            #[allow(unsafe_code)]
            let nice = unsafe { libc::getpriority(libc::PRIO_PROCESS, libc::gettid() as libc::id_t) };
            if nice_set {
                assert_eq!(nice, 3, "the slice request reset the thread's nice value (granted: {granted})");
            }
            if promote() {
                assert!(!short_slice(0), "a SCHED_FIFO thread was offered a fair-class slice");
                // SAFETY: as above.
                #[allow(unsafe_code)]
                let policy = unsafe { libc::sched_getscheduler(0) };
                assert_eq!(policy, libc::SCHED_FIFO, "the slice request moved a SCHED_FIFO thread");
            }
        })
        .join()
        .unwrap();
    }

    #[test]
    fn threads_are_found_by_name() {
        let (tx, rx) = std::sync::mpsc::channel::<()>();
        let (started_tx, started) = std::sync::mpsc::channel::<()>();
        // The thread names itself as it starts: scan once it has.
        let t = std::thread::Builder::new()
            .name("dhg-slice-test".into())
            .spawn(move || {
                started_tx.send(()).unwrap();
                rx.recv()
            })
            .unwrap();
        started.recv().unwrap();
        let here = short_slice(0);
        let n = short_slice_named(&["dhg-slice-te"]);
        assert_eq!(n, usize::from(here), "the kernel grants it to one thread iff to all");
        assert_eq!(short_slice_named(&["no-such-thread-"]), 0);
        tx.send(()).unwrap();
        t.join().unwrap().unwrap();
    }
}
