//! Best-effort real-time scheduling of the tick thread.
//!
//! With `SCHED_FIFO` the tick thread preempts the Zenoh, Python and model threads when its
//! deadline comes, which is what keeps missed ticks at zero on a loaded machine. It needs
//! `CAP_SYS_NICE` (or an `rtprio` limit); without it the thread keeps normal scheduling and the
//! health report says so.

/// `SCHED_FIFO` priority: above ordinary real-time helpers, below the kernel's own (99).
#[cfg(target_os = "linux")]
const FIFO_PRIORITY: i32 = 80;

/// Asks for `SCHED_FIFO` for the calling thread; returns whether it was granted.
#[cfg(target_os = "linux")]
#[allow(unsafe_code)] // the one FFI call of the core: libc has no safe wrapper for it
pub(crate) fn promote() -> bool {
    let param = libc::sched_param { sched_priority: FIFO_PRIORITY };
    // SAFETY: `param` is a valid sched_param; pid 0 names the calling thread.
    unsafe { libc::sched_setscheduler(0, libc::SCHED_FIFO, &raw const param) == 0 }
}

/// Other systems: normal scheduling.
#[cfg(not(target_os = "linux"))]
pub(crate) fn promote() -> bool {
    false
}
