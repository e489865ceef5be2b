//! The tick thread's alarm: when it next has to wake, moved later by the threads that tick slots.
//!
//! A slot whose client streams on time is ticked by its poses' thread, and its deadline moves one
//! period later with each pose: the tick thread only has to tick it if a pose is late. Sleeping
//! to the deadline it computed, the tick thread woke once a period to find the slot already
//! ticked (about 1,000 wake-ups a second at any session count, 24 µs of a core each on the 2-core
//! VM). Here every slot publishes its deadline ([`Alarm::publish`]); the tick thread arms the
//! alarm at the earliest ([`Alarm::set`]) and sleeps on it; a pose's thread that ticked a slot
//! moves the alarm to the new earliest ([`Alarm::postpone`], one `timerfd_settime`, about 1 µs),
//! so the alarm only goes off when a slot is due that no pose ticked. Anything the tick thread
//! must see at once (a command, a pose it has to tick) rings the bell ([`Alarm::ring`]).
//!
//! The alarm never goes off later than the earliest deadline: a slot's deadline only moves
//! earlier on the tick thread, or on a pose's thread that then rings the bell, and the tick
//! thread sets the alarm after every wake-up; a [`postpone`](Alarm::postpone) computed from
//! older deadlines is earlier than the truth (a wake-up that finds nothing due, never a late
//! one), and a postpone that loses a race with [`set`](Alarm::set) is undone by the loser
//! (see [`Alarm::arm`]).
//!
//! On Linux: a `timerfd` and an `eventfd`, waited on together with `ppoll`. Elsewhere the alarm
//! cannot be moved once its thread sleeps: the tick thread parks until the time it set and wakes
//! at each deadline, as before.
//!
//! Why: `docs/decisions/0024-the-tick-threads-alarm.md`.

use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::time::{Duration, Instant};

use crate::error::{SimError, SimResult};

/// A deadline that is never reached (an inactive slot, a disarmed alarm).
const NEVER: u64 = u64::MAX;

/// Why [`Alarm::wait`] returned.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Woke {
    /// The alarm went off.
    Alarm,
    /// The bell was rung.
    Bell,
    /// Neither within the wait's timeout.
    Timeout,
}

/// The tick thread's alarm (see the module docs).
#[derive(Debug)]
pub struct Alarm {
    epoch: Instant,
    /// Per slot: when it next ticks unless a pose ticks it first (ns since `epoch`; [`NEVER`]).
    dues: Box<[AtomicU64]>,
    /// When the alarm is set to go off (ns since `epoch`; [`NEVER`]: disarmed).
    armed: AtomicU64,
    /// Whether the tick thread sleeps on it (not while it spins: nothing to move then).
    enabled: AtomicBool,
    /// Times a pose's thread moved the alarm.
    postponed: AtomicU64,
    sys: sys::Timer,
}

impl Alarm {
    /// An alarm for `slots` slots, disarmed, every slot inactive.
    ///
    /// # Errors
    /// The system would not give the timer or the bell (out of file descriptors).
    pub fn new(slots: usize) -> SimResult<Self> {
        let sys =
            sys::Timer::new().map_err(|e| SimError::Engine(format!("cannot create the tick thread's alarm: {e}")))?;
        Ok(Self {
            epoch: Instant::now(),
            dues: (0..slots).map(|_| AtomicU64::new(NEVER)).collect(),
            armed: AtomicU64::new(NEVER),
            enabled: AtomicBool::new(true),
            postponed: AtomicU64::new(0),
            sys,
        })
    }

    fn ns(&self, at: Instant) -> u64 {
        u64::try_from(at.saturating_duration_since(self.epoch).as_nanos()).unwrap_or(NEVER - 1)
    }

    fn instant(&self, ns: u64) -> Option<Instant> {
        (ns != NEVER).then(|| self.epoch + Duration::from_nanos(ns))
    }

    /// Records when `slot` next ticks without a pose (`None`: inactive). Called by whoever
    /// ticked or looked at it, under its claim.
    pub fn publish(&self, slot: usize, due: Option<Instant>) {
        if let Some(d) = self.dues.get(slot) {
            d.store(due.map_or(NEVER, |t| self.ns(t)), Ordering::Release);
        }
    }

    /// The earliest published deadline.
    #[must_use]
    pub fn earliest(&self) -> Option<Instant> {
        self.instant(self.earliest_ns())
    }

    fn earliest_ns(&self) -> u64 {
        self.dues.iter().map(|d| d.load(Ordering::Acquire)).min().unwrap_or(NEVER)
    }

    /// When the alarm goes off (`None`: disarmed).
    #[must_use]
    pub fn armed(&self) -> Option<Instant> {
        self.instant(self.armed.load(Ordering::SeqCst))
    }

    /// Times a pose's thread moved the alarm later.
    #[must_use]
    pub fn postponed(&self) -> u64 {
        self.postponed.load(Ordering::Relaxed)
    }

    /// Stops (or resumes) moving the alarm: a spinning tick thread does not sleep on it.
    pub fn enable(&self, on: bool) {
        self.enabled.store(on, Ordering::Relaxed);
    }

    /// Sets the alarm to go off at `at` (`None`: disarmed): the tick thread, after each wake-up.
    pub fn set(&self, at: Option<Instant>) {
        let v = at.map_or(NEVER, |t| self.ns(t));
        self.armed.store(v, Ordering::SeqCst);
        self.arm(v);
    }

    /// Moves the alarm to the earliest published deadline if that is later than it is set for:
    /// a pose's thread, after its tick (and its force's put). Never waits; one system call when
    /// it moves the alarm, none otherwise.
    pub fn postpone(&self) {
        if !self.enabled.load(Ordering::Relaxed) {
            return;
        }
        let armed = self.armed.load(Ordering::SeqCst);
        let earliest = self.earliest_ns();
        if earliest <= armed {
            return;
        }
        // Lost to another thread's move: theirs stands (the tick thread's is the truth; another
        // pose thread's is as good as this one's).
        if self.armed.compare_exchange(armed, earliest, Ordering::SeqCst, Ordering::SeqCst).is_ok() {
            self.postponed.fetch_add(1, Ordering::Relaxed);
            self.arm(earliest);
        }
    }

    /// Programs the timer for `v`, then makes sure it holds what `armed` holds: two threads'
    /// stores and timer calls can interleave, so each re-reads `armed` after its call and
    /// programs that until they agree. The last thread to program the timer thus programs the
    /// last value stored (any later store is followed by its own, later, call).
    fn arm(&self, mut v: u64) {
        loop {
            self.sys.arm(self.instant(v).map(|t| t.saturating_duration_since(Instant::now())));
            let now = self.armed.load(Ordering::SeqCst);
            if now == v {
                return;
            }
            v = now;
        }
    }

    /// Rings the bell: the sleeping tick thread wakes at once (or its next wait returns at once).
    pub fn ring(&self) {
        self.sys.ring();
    }

    /// Sleeps until the alarm goes off, the bell rings or `timeout` passes (the tick thread only).
    /// A ring or an alarm since the last wait ends it at once.
    pub fn wait(&self, timeout: Duration) -> Woke {
        self.sys.wait(timeout, self.armed())
    }
}

#[cfg(target_os = "linux")]
mod sys {
    use std::io;
    use std::os::fd::OwnedFd;
    use std::time::{Duration, Instant};

    use rustix::event::{eventfd, poll, EventfdFlags, PollFd, PollFlags};
    use rustix::time::Timespec;
    use rustix::time::{timerfd_create, timerfd_settime, Itimerspec, TimerfdClockId, TimerfdFlags, TimerfdTimerFlags};

    use super::Woke;

    /// A `timerfd` (the alarm) and an `eventfd` (the bell).
    #[derive(Debug)]
    pub(super) struct Timer {
        timer: OwnedFd,
        bell: OwnedFd,
    }

    fn timespec(d: Duration) -> Timespec {
        Timespec::try_from(d).unwrap_or(Timespec { tv_sec: i64::MAX, tv_nsec: 0 })
    }

    /// Reads a descriptor's 8-byte counter, if it is set (both are non-blocking).
    fn drain(fd: &OwnedFd) -> bool {
        let mut n = [0u8; 8];
        matches!(rustix::io::read(fd, &mut n), Ok(8))
    }

    impl Timer {
        pub(super) fn new() -> io::Result<Self> {
            let timer = timerfd_create(TimerfdClockId::Monotonic, TimerfdFlags::NONBLOCK | TimerfdFlags::CLOEXEC)?;
            let bell = eventfd(0, EventfdFlags::NONBLOCK | EventfdFlags::CLOEXEC)?;
            Ok(Self { timer, bell })
        }

        /// Arms the timer `after` from now, or disarms it (`None`).
        pub(super) fn arm(&self, after: Option<Duration>) {
            // A zero it_value disarms: a due time already past goes off in 1 ns.
            let value = after.map_or(Duration::ZERO, |d| d.max(Duration::from_nanos(1)));
            let spec = Itimerspec { it_interval: timespec(Duration::ZERO), it_value: timespec(value) };
            // Cannot fail with a timerfd and a valid value.
            let _ = timerfd_settime(&self.timer, TimerfdTimerFlags::empty(), &spec);
        }

        /// Time left before the timer goes off (zero: disarmed).
        #[cfg(test)]
        pub(super) fn remaining(&self) -> Duration {
            let cur = rustix::time::timerfd_gettime(&self.timer).expect("timerfd_gettime");
            Duration::new(cur.it_value.tv_sec as u64, cur.it_value.tv_nsec as u32)
        }

        pub(super) fn ring(&self) {
            // Fails only when the counter would overflow, that is, when the bell already rings.
            let _ = rustix::io::write(&self.bell, &1u64.to_ne_bytes());
        }

        pub(super) fn wait(&self, timeout: Duration, _armed: Option<Instant>) -> Woke {
            let mut fds = [PollFd::new(&self.timer, PollFlags::IN), PollFd::new(&self.bell, PollFlags::IN)];
            // An interrupted wait returns early, which the caller's loop tolerates.
            let _ = poll(&mut fds, Some(&timespec(timeout)));
            let bell = drain(&self.bell);
            let alarm = drain(&self.timer);
            if bell {
                Woke::Bell
            } else if alarm {
                Woke::Alarm
            } else {
                Woke::Timeout
            }
        }
    }
}

#[cfg(not(target_os = "linux"))]
mod sys {
    use std::io;
    use std::sync::atomic::{AtomicBool, Ordering};
    use std::sync::OnceLock;
    use std::thread::Thread;
    use std::time::{Duration, Instant};

    use super::Woke;

    /// Parking: the alarm cannot move once its thread sleeps (see the module docs).
    #[derive(Debug, Default)]
    pub(super) struct Timer {
        sleeper: OnceLock<Thread>,
        rung: AtomicBool,
    }

    impl Timer {
        pub(super) fn new() -> io::Result<Self> {
            Ok(Self::default())
        }

        pub(super) fn arm(&self, _after: Option<Duration>) {}

        pub(super) fn ring(&self) {
            self.rung.store(true, Ordering::SeqCst);
            if let Some(t) = self.sleeper.get() {
                t.unpark();
            }
        }

        pub(super) fn wait(&self, timeout: Duration, armed: Option<Instant>) -> Woke {
            let _ = self.sleeper.set(std::thread::current());
            let now = Instant::now();
            let until = armed.map_or(timeout, |t| t.saturating_duration_since(now).min(timeout));
            if !self.rung.load(Ordering::SeqCst) && !until.is_zero() {
                std::thread::park_timeout(until);
            }
            if self.rung.swap(false, Ordering::SeqCst) {
                Woke::Bell
            } else if armed.is_some_and(|t| Instant::now() >= t) {
                Woke::Alarm
            } else {
                Woke::Timeout
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::{Alarm, Woke};
    use std::time::{Duration, Instant};

    const LONG: Duration = Duration::from_secs(3600);

    #[test]
    fn an_alarm_goes_off_at_its_time_and_the_bell_at_once() {
        let a = Alarm::new(2).unwrap();
        a.set(Some(Instant::now() + Duration::from_millis(2)));
        assert_eq!(a.wait(LONG), Woke::Alarm);
        a.set(None);
        a.ring();
        assert_eq!(a.wait(LONG), Woke::Bell, "a ring before the wait is not lost");
        a.set(Some(Instant::now())); // already due: goes off at once
        assert_eq!(a.wait(LONG), Woke::Alarm);
    }

    #[cfg(target_os = "linux")]
    #[test]
    fn a_pose_thread_moves_the_alarm_to_the_earliest_deadline_and_never_earlier() {
        let a = Alarm::new(2).unwrap();
        let t0 = Instant::now();
        a.publish(0, Some(t0 + Duration::from_millis(1)));
        a.publish(1, None);
        a.set(a.earliest());
        assert_eq!(a.armed(), a.earliest());
        // Slot 0 ticked by its pose: its deadline an hour on. The alarm follows it, so a wait
        // that would have ended at 1 ms only ends at its own timeout.
        a.publish(0, Some(t0 + LONG));
        a.postpone();
        assert_eq!(a.postponed(), 1);
        assert!(a.armed().is_some_and(|t| t >= t0 + LONG));
        assert_eq!(a.wait(Duration::from_millis(50)), Woke::Timeout, "the alarm went off at its old time");
        // An earlier deadline is not a postpone: only the tick thread sets the alarm earlier.
        a.publish(1, Some(t0 + Duration::from_millis(5)));
        a.postpone();
        assert_eq!(a.postponed(), 1);
        assert!(a.armed().is_some_and(|t| t >= t0 + LONG));
        a.set(a.earliest());
        assert_eq!(a.wait(LONG), Woke::Alarm);
        // Disabled (a spinning tick thread): a postpone does nothing.
        a.enable(false);
        a.publish(1, None);
        a.postpone();
        assert_eq!(a.postponed(), 1);
    }

    #[cfg(target_os = "linux")]
    #[test]
    fn racing_postpones_and_sets_leave_the_timer_where_the_alarm_says() {
        use std::sync::atomic::{AtomicBool, Ordering};
        use std::sync::Arc;
        // A pose thread's postpone and the tick thread's set, started together, many times: in
        // some rounds the postpone's timer call lands after the set's, and without the re-check
        // in `arm` the timer would then hold the postpone's stale time, not the alarm's.
        let a = Arc::new(Alarm::new(2).unwrap());
        let spin_until = |t: Instant| while Instant::now() < t {};
        let mut wrong = Vec::new();
        for round in 0..3000u32 {
            let t0 = Instant::now();
            a.publish(0, Some(t0 + LONG));
            a.publish(1, Some(t0 + 2 * LONG));
            a.set(a.earliest());
            let ready = Arc::new(AtomicBool::new(false));
            let poser = {
                let (a, ready) = (a.clone(), ready.clone());
                std::thread::spawn(move || {
                    a.publish(0, Some(t0 + 3 * LONG));
                    ready.store(true, Ordering::SeqCst);
                    a.postpone(); // to slot 1's deadline, 2 h
                })
            };
            while !ready.load(Ordering::SeqCst) {
                std::hint::spin_loop();
            }
            // The set starts somewhere within the postpone's 1–2 µs.
            spin_until(Instant::now() + Duration::from_nanos(u64::from(round % 16) * 100));
            a.publish(1, Some(t0 + LONG + Duration::from_secs(u64::from(round % 60) + 1)));
            a.set(a.earliest()); // the tick thread: slot 1's new deadline, just over 1 h
            poser.join().unwrap();
            let want = a.armed().unwrap().saturating_duration_since(Instant::now());
            let left = a.sys.remaining();
            let off = left.abs_diff(want);
            if off > Duration::from_millis(100) {
                wrong.push((round, left, want));
            }
        }
        assert!(
            wrong.is_empty(),
            "{} rounds left the timer elsewhere: {:?}",
            wrong.len(),
            &wrong[..wrong.len().min(3)]
        );
    }
}
