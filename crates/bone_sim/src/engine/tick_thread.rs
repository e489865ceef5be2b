//! The tick thread: runs a [`TickCore`] on its own thread, sleeping on its alarm (or spinning)
//! until a slot is due that no pose ticked, or a pose or a command rings (see the schedule in the module docs of
//! [`crate::engine`]).

use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::thread::{self, JoinHandle, Thread};
use std::time::Instant;

use super::{realtime, Alarm, TickCore, WaitMode, CLAIM_RETRY, IDLE_WAKE};
use crate::error::{SimError, SimResult};

/// The running tick thread.
#[derive(Debug)]
pub struct TickThread {
    stop: Arc<AtomicBool>,
    alarm: Arc<Alarm>,
    handle: Option<JoinHandle<()>>,
}

impl TickThread {
    /// Starts ticking `core` (see the schedule in the module docs of [`crate::engine`]); `notify`
    /// is unparked after every wake-up that ticked a slot or applied a command (the comm thread,
    /// so outputs leave without polling delay). With [`WaitMode::Sleep`] the thread sleeps on the
    /// core's [`Alarm`](super::Alarm): until the earliest slot deadline no pose has pushed out, or
    /// until its bell rings (a command, a pose it must tick). With [`WaitMode::Spin`] it does not
    /// sleep while a session is open: it checks for due slots, fresh poses and commands
    /// continuously.
    ///
    /// # Errors
    /// The thread could not be spawned.
    pub fn spawn(mut core: TickCore, notify: Option<Thread>, wait: WaitMode) -> SimResult<Self> {
        let stop = Arc::new(AtomicBool::new(false));
        let flag = stop.clone();
        let alarm = core.alarm().clone();
        alarm.enable(wait == WaitMode::Sleep);
        let sleeper = alarm.clone();
        // Returns once the thread knows its scheduling, so the health report is right at once.
        let (ready_tx, ready_rx) = std::sync::mpsc::sync_channel::<()>(1);
        let handle = thread::Builder::new()
            .name("dhg-tick".into())
            .spawn(move || {
                let alarm = sleeper;
                // Never both: the kernel's real-time throttling (sched_rt_runtime_us, 95 % by
                // default) would stop a spinning SCHED_FIFO thread for 50 ms every second.
                let rt = wait == WaitMode::Sleep && realtime::promote();
                core.stats.realtime.store(u64::from(rt), Ordering::Relaxed);
                // Without it, at least preempt a longer-sliced thread on waking (no privilege).
                let slice = !rt && realtime::short_slice(0);
                core.stats.short_slice.store(u64::from(slice), Ordering::Relaxed);
                let _ = ready_tx.send(());
                let mut wake = Instant::now();
                while !flag.load(Ordering::Relaxed) {
                    let now = Instant::now();
                    if wait == WaitMode::Spin && now < wake {
                        if core.stats.sessions.load(Ordering::Relaxed) > 0 {
                            // `tick_due` is cheap when nothing is due (a few ns per slot) and
                            // sees a fresh pose or command the moment it lands.
                            std::hint::spin_loop();
                            continue;
                        }
                        // With no session there is nothing to be fast for: sleep (a first pose
                        // or command rings the bell).
                        alarm.wait(wake - now);
                    }
                    let woke = Instant::now();
                    let (ticked, next) = core.tick_due(woke);
                    if ticked > 0 {
                        core.stats.busy.record(woke.elapsed().as_nanos() as u64);
                    }
                    if ticked > 0 || core.commands_applied() > 0 {
                        if let Some(t) = &notify {
                            t.unpark();
                        }
                    }
                    wake = next;
                    if wait == WaitMode::Sleep {
                        // Set after the deadlines are published; a pose's thread moves it later.
                        alarm.set(alarm.earliest());
                        let timeout = if core.retry() { CLAIM_RETRY } else { IDLE_WAKE };
                        alarm.wait(timeout);
                        core.stats.wakes.fetch_add(1, Ordering::Relaxed);
                    }
                }
            })
            .map_err(|e| SimError::Engine(format!("cannot start the tick thread: {e}")))?;
        let _ = ready_rx.recv(); // an error means the thread ended first: nothing to wait for
        Ok(Self { stop, alarm, handle: Some(handle) })
    }

    /// Stops the thread and waits for it (at most one tick).
    pub fn stop(&mut self) {
        self.stop.store(true, Ordering::Relaxed);
        self.alarm.ring();
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
