//! The comm thread: drains the outputs of every tick and publishes them through each session's
//! [`Outlet`] (but the forces a pose's own thread already put), keeps each session's window of
//! records and the batches of its ticks, and sends the model queries, one for each burst of
//! sessions' windows ([`ModelQueries`]). It sleeps until a tick unparks it (at most
//! [`IDLE_WAKE`], or until the burst waiting is due), or spins ([`WaitMode::Spin`]).

use std::collections::VecDeque;
use std::sync::atomic::Ordering;
use std::sync::{Arc, TryLockError};
use std::thread::{self, JoinHandle};
use std::time::{Duration, Instant};

use zenoh::Wait;

use super::history::sample;
use super::model_query::ModelQueries;
use super::outlet::Outlet;
use super::registry::ForcePublisher;
use super::{lock, Shared, ZENOH_IO_THREADS};
use crate::engine::handoff::Output;
use crate::engine::realtime;
use crate::engine::{OutputQueue, WaitMode};
use crate::error::{SimError, SimResult};
use crate::protocol;
use crate::protocol::keys;

/// Longest the comm thread sleeps: forces a pose's thread already put are queued without waking
/// it, only to be added to the recorders' batches, so it takes them in this often.
pub(crate) const IDLE_WAKE: Duration = Duration::from_millis(20);

/// While the registry is held by another thread, how often the comm thread tries it again
/// (a force queued meanwhile wakes it sooner).
const REGISTRY_RETRY: Duration = Duration::from_micros(100);

struct Comm {
    session: zenoh::Session,
    shared: Arc<Shared>,
    outlets: Vec<Option<Outlet>>,
    model: ModelQueries,
    queue: ForcesFirst,
}

/// The ticks' outputs as the comm thread takes them: forces first. A state's model query or a
/// guidance message takes tens of µs (up to ms), and a force queued behind it would wait for it.
/// So every waiting force, including those that arrive meanwhile, goes out before each of the
/// other outputs, which keep their order. Why: `docs/decisions/0008-forces-first.md`.
struct ForcesFirst {
    outputs: Arc<OutputQueue>,
    /// Outputs other than forces, in order, waiting for every force to be out (kept across
    /// wake-ups, so its capacity is reused).
    later: VecDeque<Output>,
}

impl ForcesFirst {
    /// The next waiting force; the other outputs taken on the way wait behind those already
    /// waiting.
    fn next_force(&mut self) -> Option<Output> {
        while let Some(out) = self.outputs.pop() {
            if matches!(out, Output::Force { .. }) {
                return Some(out);
            }
            self.later.push_back(out);
        }
        None
    }

    /// The oldest waiting output that is not a force (take it once no force waits).
    fn next_other(&mut self) -> Option<Output> {
        self.later.pop_front()
    }

    /// Whether no output waits.
    fn is_empty(&self) -> bool {
        self.later.is_empty() && self.outputs.is_empty()
    }
}

/// Gives every waiting force to `handle`, those that arrive meanwhile too ([`ForcesFirst`] of
/// `ctx`, which `queue` picks out of it).
fn put_waiting_forces<C>(ctx: &mut C, queue: fn(&mut C) -> &mut ForcesFirst, handle: fn(&mut C, Output)) {
    while let Some(force) = queue(ctx).next_force() {
        handle(ctx, force);
    }
}

/// The comm thread's loop over the waiting outputs: every force first, then the oldest other
/// output, and again, until none waits ([`ForcesFirst`]).
fn drain_forces_first<C>(ctx: &mut C, queue: fn(&mut C) -> &mut ForcesFirst, handle: fn(&mut C, Output)) {
    loop {
        put_waiting_forces(ctx, queue, handle);
        let Some(out) = queue(ctx).next_other() else { return };
        handle(ctx, out);
    }
}

impl Comm {
    /// The outlet of the session in `slot` as of `generation`, declared on its first output;
    /// `None` if the slot has moved on, holds no session, or Zenoh refused a publisher.
    fn outlet(&mut self, slot: u16, generation: u32) -> Option<&mut Outlet> {
        let i = slot as usize;
        let stale = self.outlets[i].as_ref().is_none_or(|o| o.generation() != generation);
        if stale {
            if let Some(mut old) = self.outlets[i].take() {
                old.publish_ticks();
            }
            // The session's id from the routes, not the registry, so that the first outputs of a
            // session do not wait for a query holding the registry (decision 0039). None: the
            // slot has moved on; what is left of the old session is dropped.
            let id = self.shared.routes.id_of(slot, generation)?;
            let key = |leaf: &str| keys::session_leaf(&self.shared.prefix, &id, leaf);
            let force = Outlet::declare_force(&self.session, key("force"), generation)?;
            // From now on the session's poses put their own forces (if they tick it).
            if !self.shared.routes.set_force(slot, generation, force.clone()) {
                return None;
            }
            self.outlets[i] = Some(Outlet::declare(&self.session, key, generation, force)?);
        }
        self.outlets[i].as_mut()
    }

    #[allow(clippy::large_types_passed_by_value)] // moved into the ring / consumed: by value is the point
    fn handle(&mut self, out: Output) {
        match out {
            Output::Force { slot, generation, msg, pose, received, order, published } => {
                let shared = self.shared.clone();
                if let Some(o) = self.outlet(slot, generation) {
                    if !published {
                        put_force(&shared, o.force(), slot, &msg, received, order);
                    }
                    o.add_force(msg, pose);
                } else {
                    // Of a session that ended: let go, so that the slot's next forces may leave
                    // from their poses' threads.
                    for n in [&shared.put_begun, &shared.put_done].into_iter().filter_map(|a| a.get(usize::from(slot)))
                    {
                        n.fetch_max(order, Ordering::AcqRel);
                    }
                }
            }
            Output::State { slot, generation, attempt, record, msg } => {
                let Some(o) = self.outlet(slot, generation) else { return };
                let (asked, pose_time_ns) = o.add_state(&msg, attempt, record.features.map(|x| x as f32));
                // A record of the session's current attempt is counted, and the model asked about
                // its window; a straggler of an attempt a reset ended is neither (a reply to it
                // would not be applied).
                let current = self.with_registry(|reg| {
                    reg.slots
                        .get_mut(slot as usize)
                        .filter(|info| info.generation == generation)
                        .is_some_and(|info| info.add_record(&msg, attempt, asked.seq))
                });
                if current {
                    self.model.ask(slot, generation, asked.seq, pose_time_ns, &asked.window);
                }
            }
            Output::Guidance { slot, generation, msg } => {
                if let Some(o) = self.outlet(slot, generation) {
                    o.publish_guidance(&msg);
                }
                self.with_registry(|reg| {
                    if let Some(info) = reg.slots.get_mut(slot as usize).filter(|info| info.generation == generation) {
                        info.add_guidance(&msg);
                    }
                });
            }
            Output::Snapshot { .. } => {
                self.shared.snapshot_seq.fetch_add(1, Ordering::AcqRel);
            }
        }
    }

    /// Runs `f` on the registry for a state's or a guidance message's bookkeeping. While another
    /// thread holds the registry (a control, metrics or health query, a model reply), this thread
    /// goes on putting the forces that arrive meanwhile, so that no force, and no later force of
    /// its session (which must follow it out), waits for the registry
    /// (`docs/decisions/0039-poses-route-without-the-registry.md`).
    fn with_registry<R>(&mut self, f: impl FnOnce(&mut super::registry::Registry) -> R) -> R {
        let shared = self.shared.clone();
        loop {
            match shared.registry.try_lock() {
                Ok(mut reg) => return f(&mut reg),
                Err(TryLockError::Poisoned(p)) => return f(&mut p.into_inner()),
                Err(TryLockError::WouldBlock) => {
                    self.put_waiting_forces();
                    // Woken at once by the next output a tick queues; else it looks again soon.
                    thread::park_timeout(REGISTRY_RETRY);
                }
            }
        }
    }

    /// Puts every waiting force ([`ForcesFirst`]).
    fn put_waiting_forces(&mut self) {
        put_waiting_forces(self, |c| &mut c.queue, Self::handle);
    }

    /// Handles every waiting output, forces first ([`ForcesFirst`]).
    fn drain_forces_first(&mut self) {
        drain_forces_first(self, |c| &mut c.queue, Self::handle);
    }

    /// Once a second: the health history, idle sessions, and (when the number of sessions has
    /// changed) the short slice for Zenoh's I/O threads, which it starts as links come up.
    fn housekeeping(&mut self, io_sessions: &mut Option<u64>) {
        let sessions = self.shared.stats.sessions.load(Ordering::Relaxed);
        if *io_sessions != Some(sessions) {
            *io_sessions = Some(sessions);
            let n = realtime::short_slice_named(&ZENOH_IO_THREADS);
            self.shared.counters.io_short_slices.store(n as u64, Ordering::Relaxed);
        }
        let s = sample(&self.shared);
        lock(&self.shared.history).push(s);
        let idle = self.shared.config.idle_timeout_s;
        self.with_registry(|reg| reg.sweep_idle(idle));
    }

    fn run(&mut self, wait: WaitMode) {
        // A force waits for this thread's wake-up: preempt longer-sliced threads (no privilege).
        let slice = realtime::short_slice(0);
        self.shared.counters.comm_short_slice.store(u64::from(slice), Ordering::Relaxed);
        let mut io_sessions = None;
        let mut next_housekeeping = Instant::now();
        while !self.shared.stopping.load(Ordering::Acquire) {
            if wait == WaitMode::Spin && self.shared.stats.sessions.load(Ordering::Relaxed) > 0 {
                std::hint::spin_loop();
            } else {
                // A tick unparks this thread when it queued output to publish; a burst's query
                // leaves at most `model_query::BURST_WAIT` after its first window. Not when
                // output waits already: a wait for the registry (`with_registry`) may have taken
                // the unpark that came with it.
                let nap = self.model.deadline().map_or(IDLE_WAKE, |due| due.saturating_duration_since(Instant::now()));
                if self.queue.is_empty() {
                    thread::park_timeout(nap);
                }
            }
            self.drain_forces_first();
            let now = Instant::now();
            self.model.send_if_due(now);
            for o in self.outlets.iter_mut().flatten() {
                o.publish_view(now);
                o.publish_stale_ticks(now);
            }
            if now >= next_housekeeping {
                self.housekeeping(&mut io_sessions);
                next_housekeeping += Duration::from_secs(1);
            }
        }
        for o in self.outlets.iter_mut().flatten() {
            o.publish_ticks();
        }
        self.outlets.clear();
        self.model.drop_burst(); // the windows of a stopping server go unasked
    }
}

/// Puts a session's force (from the comm thread, or from the thread its pose arrived on), unless
/// a newer force of the slot is already out (`order`: the slot's tick count), and records the
/// pose → put time.
pub(crate) fn put_force(
    shared: &Shared,
    force: &ForcePublisher,
    slot: u16,
    msg: &protocol::ForceMsg,
    received: Option<Instant>,
    order: u64,
) {
    let i = usize::from(slot);
    let newest = shared.put_begun.get(i).map_or(0, |n| n.fetch_max(order, Ordering::AcqRel));
    if newest >= order {
        return; // superseded: a newer force left first; the recorders' batch still has it
    }
    let _ = force.publisher.put(protocol::encode_force(msg).to_vec()).wait();
    if let Some(n) = shared.put_done.get(i) {
        n.fetch_max(order, Ordering::AcqRel);
    }
    if let Some(t) = received {
        shared.stats.pose_to_put.record(t.elapsed().as_nanos() as u64);
    }
}

/// Starts the comm thread.
pub(crate) fn spawn(
    session: zenoh::Session,
    shared: Arc<Shared>,
    outputs: Arc<OutputQueue>,
    wait: WaitMode,
) -> SimResult<JoinHandle<()>> {
    let model = ModelQueries::declare(&session, &shared)?;
    let slots = lock(&shared.registry).slots.len();
    let mut comm = Comm {
        session,
        shared,
        outlets: (0..slots).map(|_| None).collect(),
        model,
        queue: ForcesFirst { outputs, later: VecDeque::with_capacity(4 * slots) },
    };
    thread::Builder::new()
        .name("dhg-comm".into())
        .spawn(move || comm.run(wait))
        .map_err(|e| SimError::Engine(format!("cannot start the comm thread: {e}")))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::protocol::ForceMsg;

    fn force(slot: u16) -> Output {
        Output::Force {
            slot,
            generation: 1,
            msg: ForceMsg::default(),
            pose: None,
            received: None,
            order: 1,
            published: false,
        }
    }

    fn other(slot: u16) -> Output {
        Output::Snapshot { slot, generation: 1 }
    }

    fn name(out: &Output) -> String {
        match out {
            Output::Force { slot, .. } => format!("F{slot}"),
            Output::Snapshot { slot, .. } => format!("S{slot}"),
            _ => "?".into(),
        }
    }

    /// What the comm thread's loop is given in the test: the queue, the order outputs were
    /// handled in, and what handling the first slow output (`S0`) does meanwhile.
    struct Probe {
        queue: ForcesFirst,
        order: Vec<String>,
        slow: fn(&mut Probe),
    }

    #[allow(clippy::large_types_passed_by_value)] // the signature of `Comm::handle`
    fn handle(p: &mut Probe, out: Output) {
        if matches!(out, Output::Snapshot { slot: 0, .. }) {
            (p.slow)(p);
        }
        p.order.push(name(&out));
    }

    /// The comm thread's loop (`drain_forces_first`, as `Comm` runs it) over the probe's queue;
    /// the order the outputs were handled in.
    fn drain(p: &mut Probe) -> Vec<String> {
        p.order.clear();
        drain_forces_first(p, |p| &mut p.queue, handle);
        std::mem::take(&mut p.order)
    }

    #[test]
    fn forces_go_out_before_other_outputs_even_those_that_arrive_meanwhile() {
        let outputs = Arc::new(OutputQueue::new(16));
        let fill = || {
            for out in [other(0), force(1), other(2), force(3)] {
                outputs.push(out).unwrap();
            }
        };
        let queue = ForcesFirst { outputs: outputs.clone(), later: VecDeque::new() };
        // A force that comes while a slow output is handled leaves after it, before the next.
        let mut p = Probe { queue, order: Vec::new(), slow: |p| p.queue.outputs.push(force(4)).unwrap() };
        fill();
        assert_eq!(drain(&mut p), ["F1", "F3", "S0", "F4", "S2"]);
        // A slow output waiting for the registry puts the forces that come meanwhile
        // (`Comm::with_registry`); another output that came too waits behind the older ones.
        p.slow = |p| {
            p.queue.outputs.push(force(4)).unwrap();
            p.queue.outputs.push(other(5)).unwrap();
            put_waiting_forces(p, |p| &mut p.queue, handle);
        };
        fill();
        assert_eq!(drain(&mut p), ["F1", "F3", "F4", "S0", "S2", "S5"]);
        assert!(p.queue.is_empty());
    }
}
