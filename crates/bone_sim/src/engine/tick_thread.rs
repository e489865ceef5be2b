//! The tick thread: runs a [`TickCore`] on its own thread, sleeping (or spinning) until the
//! next slot is due, or a pose or a command wakes it (when a slot is due: `engine/schedule.rs`).

use std::panic::{catch_unwind, AssertUnwindSafe};
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::Arc;
use std::thread::{self, JoinHandle, Thread};
use std::time::Instant;

use super::{realtime, TickCore, TickWaker, WaitMode};
use crate::error::{SimError, SimResult};

/// Runs a thread's `body`; a panic in it (a bug) is caught and recorded in `failed` (1), which the
/// health report shows, instead of ending the thread unseen. The panic's message still goes to
/// standard error (the default hook).
pub(crate) fn guarded(failed: &AtomicU64, body: impl FnOnce()) {
    if catch_unwind(AssertUnwindSafe(body)).is_err() {
        failed.store(1, Ordering::Relaxed);
    }
}

/// The running tick thread.
#[derive(Debug)]
pub struct TickThread {
    stop: Arc<AtomicBool>,
    waker: Arc<TickWaker>,
    handle: Option<JoinHandle<()>>,
}

impl TickThread {
    /// Starts ticking `core` (see `engine/schedule.rs` for when a slot is due); `notify` is unparked after
    /// every wake-up that ticked a slot or applied a command (the comm thread, so outputs leave
    /// without polling delay). The core's [`TickWaker`] wakes it: every command pushed does, and a
    /// pose its own thread could not tick should (`PoseTicker::wake_tick_thread`). With
    /// [`WaitMode::Spin`] the thread does not sleep while a session is open: it checks for due
    /// slots, fresh poses and commands continuously.
    ///
    /// With `realtime` (and [`WaitMode::Sleep`]) the thread asks for `SCHED_FIFO`: for a thread
    /// that runs every tick (`TickOn::Thread`). Where the poses' threads run the ticks
    /// (`TickOn::Pose`, the default) it keeps normal scheduling with the short slice: at that
    /// priority each of its wake-ups (the sessions' deadlines, early poses) preempted the threads
    /// that carry the other sessions' poses, on a host whose cores they share. Why:
    /// `docs/decisions/0033-the-tick-thread-yields-to-the-poses.md`.
    ///
    /// # Errors
    /// The thread could not be spawned.
    pub fn spawn(core: TickCore, notify: Option<Thread>, wait: WaitMode, realtime: bool) -> SimResult<Self> {
        let stop = Arc::new(AtomicBool::new(false));
        let flag = stop.clone();
        let waker = core.waker().clone();
        // Returns once the thread knows its scheduling, so the health report is right at once.
        let (ready_tx, ready_rx) = std::sync::mpsc::sync_channel::<()>(1);
        let handle = thread::Builder::new()
            .name("dhg-tick".into())
            .spawn(move || {
                let stats = core.stats.clone();
                guarded(&stats.tick_thread_failed, move || {
                    Self::run(core, notify.as_ref(), wait, realtime, &flag, &ready_tx);
                });
            })
            .map_err(|e| SimError::Engine(format!("cannot start the tick thread: {e}")))?;
        let _ = ready_rx.recv(); // an error means the thread ended first: nothing to wait for
        Ok(Self { stop, waker, handle: Some(handle) })
    }

    fn run(
        mut core: TickCore,
        notify: Option<&Thread>,
        wait: WaitMode,
        realtime: bool,
        flag: &AtomicBool,
        ready_tx: &std::sync::mpsc::SyncSender<()>,
    ) {
        core.waker().register();
        // Never both: the kernel's real-time throttling (sched_rt_runtime_us, 95 % by
        // default) would stop a spinning SCHED_FIFO thread for 50 ms every second.
        let rt = realtime && wait == WaitMode::Sleep && realtime::promote();
        core.stats.realtime.store(u64::from(rt), Ordering::Relaxed);
        // Without it, at least preempt a longer-sliced thread on waking (no privilege).
        let slice = !rt && realtime::short_slice(0);
        core.stats.short_slice.store(u64::from(slice), Ordering::Relaxed);
        let _ = ready_tx.send(());
        let mut wake = Instant::now();
        while !flag.load(Ordering::Relaxed) {
            let now = Instant::now();
            if now < wake {
                // With no session there is nothing to be fast for: sleep, even when
                // spinning (a first pose or command unparks the thread).
                if wait == WaitMode::Spin && core.stats.sessions.load(Ordering::Relaxed) > 0 {
                    // `tick_due` is cheap when nothing is due (a few ns per slot) and
                    // sees a fresh pose or command the moment it lands.
                    std::hint::spin_loop();
                } else {
                    // Woken early by a pose or a command (or spuriously: the loop checks).
                    thread::park_timeout(wake - now);
                    core.stats.wakes.fetch_add(1, Ordering::Relaxed);
                }
            }
            let woke = Instant::now();
            let (ticked, next) = core.tick_due(woke);
            if ticked > 0 {
                core.stats.busy.record(woke.elapsed().as_nanos() as u64);
            }
            if ticked > 0 || core.applied > 0 {
                if let Some(t) = notify {
                    t.unpark();
                }
            }
            wake = next;
        }
    }

    /// Stops the thread and waits for it (at most one tick).
    pub fn stop(&mut self) {
        self.stop.store(true, Ordering::Relaxed);
        self.waker.wake();
        if let Some(h) = self.handle.take() {
            let _ = h.join();
        }
    }
}

impl Drop for TickThread {
    fn drop(&mut self) {
        self.stop();
    }
}

#[cfg(test)]
mod tests {
    use std::sync::atomic::{AtomicU64, Ordering};

    use super::guarded;

    #[test]
    fn a_panic_in_a_guarded_thread_is_recorded_not_lost() {
        let failed = AtomicU64::new(0);
        guarded(&failed, || {});
        assert_eq!(failed.load(Ordering::Relaxed), 0);
        let t = std::thread::spawn(move || {
            guarded(&failed, || panic!("a bug on the tick thread (this test's)"));
            failed.load(Ordering::Relaxed)
        });
        assert_eq!(t.join().unwrap(), 1, "the thread ended normally, with the panic recorded");
    }
}
