//! What a pose needs of its session, kept outside the registry's mutex: the slot and generation of
//! a session id, the slot's newest-pose writer and force publisher, and the stream bookkeeping that
//! the idle sweep reads. The registry writes them as sessions open and close; a pose's thread only
//! reads them and writes its slot's pose. So a pose of an open session never waits on the
//! registry, which the control, metrics and health queries, the model's replies and the comm
//! thread take, and the pose's own path takes no lock (the comm thread, for its part, puts forces
//! while it waits for the registry; `docs/decisions/0039-poses-route-without-the-registry.md`).

use std::collections::HashMap;
use std::sync::atomic::{AtomicBool, AtomicU32, AtomicU64, Ordering};
use std::sync::{Arc, Mutex, TryLockError};
use std::time::{Duration, Instant};

use arc_swap::{ArcSwap, ArcSwapOption};

use super::registry::{ForcePublisher, STREAM_GAP_S};
use crate::engine::handoff::PoseSample;
use crate::protocol::PoseMsg;

/// Where a session's poses go: its slot, as of the generation it was opened with.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Route {
    /// Engine slot.
    pub slot: u16,
    /// The slot's generation when the session opened (a pose for another is of a session that
    /// has ended).
    pub generation: u32,
}

/// Why a pose was not handed on.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Missed {
    /// The session closed (and its slot may hold another) since the route was looked up.
    Ended,
    /// Another thread held the session's pose writer at that instant: a second client publishing
    /// under the same session id, or the server opening or closing a session in that slot or
    /// declaring its force publisher. The pose is dropped rather than waited for.
    Busy,
}

/// One slot's half of the routes.
#[derive(Debug)]
struct SlotRoute {
    generation: AtomicU32,
    /// Whether the slot holds a session (set by `assign`, cleared by `retire`).
    open: AtomicBool,
    /// The newest-pose writer (single producer). Only ever `try_lock`ed: a second writer at the
    /// same instant drops its pose instead of waiting.
    writer: Mutex<triple_buffer::Input<PoseSample>>,
    /// The id of the session the slot was last given to, with that session's generation (one
    /// pointer, so a reader never pairs one session's id with another's generation).
    id: ArcSwapOption<SlotId>,
    force: ArcSwapOption<ForcePublisher>,
    /// When the last pose arrived, in ns since [`Routes::epoch`] plus 1 (0: none yet).
    last_pose_ns: AtomicU64,
    /// When the session last showed it is alive (a pose of a stream, a control request), the same.
    last_seen_ns: AtomicU64,
    /// Poses received in the current assignment.
    received: AtomicU64,
}

/// A slot's session: its id, as of its generation.
#[derive(Debug)]
struct SlotId {
    generation: u32,
    id: Box<str>,
}

/// Every slot's route, and the session ids' map to them.
#[derive(Debug)]
pub struct Routes {
    /// Session id → route, replaced whole (a new map) when a session opens or closes.
    ids: ArcSwap<HashMap<Box<str>, Route>>,
    slots: Box<[SlotRoute]>,
    epoch: Instant,
}

/// [`STREAM_GAP_S`] in ns.
const STREAM_GAP_NS: u64 = (STREAM_GAP_S * 1e9) as u64;

impl Routes {
    /// The routes over the engine's pose writers, one a slot; no session open.
    #[must_use]
    pub fn new(writers: Vec<triple_buffer::Input<PoseSample>>) -> Self {
        let epoch = Instant::now();
        let slots = writers
            .into_iter()
            .map(|w| SlotRoute {
                generation: AtomicU32::new(0),
                open: AtomicBool::new(false),
                writer: Mutex::new(w),
                id: ArcSwapOption::empty(),
                force: ArcSwapOption::empty(),
                last_pose_ns: AtomicU64::new(0),
                last_seen_ns: AtomicU64::new(1),
                received: AtomicU64::new(0),
            })
            .collect();
        Self { ids: ArcSwap::from_pointee(HashMap::new()), slots, epoch }
    }

    fn ns(&self, t: Instant) -> u64 {
        u64::try_from(t.saturating_duration_since(self.epoch).as_nanos()).unwrap_or(u64::MAX - 1) + 1
    }

    /// The route of session `id`, if it is open (no lock: a load of the current map).
    #[must_use]
    pub fn find(&self, id: &str) -> Option<Route> {
        self.ids.load().get(id).copied()
    }

    /// Hands a decoded pose, `received` when its sample arrived, to the tick thread, and counts it;
    /// returns the session's force publisher once the comm thread has declared it.
    ///
    /// # Errors
    /// [`Missed`]: the session has ended, or another thread is writing a pose of it now.
    pub fn pose(&self, route: Route, msg: &PoseMsg, received: Instant) -> Result<Option<Arc<ForcePublisher>>, Missed> {
        let s = &self.slots[usize::from(route.slot)];
        let mut writer = match s.writer.try_lock() {
            Ok(w) => w,
            Err(TryLockError::WouldBlock) => return Err(Missed::Busy),
            Err(TryLockError::Poisoned(p)) => p.into_inner(),
        };
        // Checked while holding the writer: `retire` (the session closed) and `assign` (the slot
        // given to a new session, before its id is published) take it, so a pose of a session
        // that has ended is refused here, whenever its route was looked up.
        if !s.open.load(Ordering::Acquire) || s.generation.load(Ordering::Acquire) != route.generation {
            return Err(Missed::Ended);
        }
        writer.write(PoseSample {
            pose: Some(msg.pose),
            seq: msg.seq,
            client_time_ns: msg.client_time_ns,
            generation: route.generation,
            received: Some(received),
        });
        // Counted while still holding the writer, which `assign` and `retire` take: so a pose of
        // a session that ends now is counted (and keeps it seen) before that, never for the next.
        // Only a stream keeps a session: a pose within STREAM_GAP_S of the one before. Isolated
        // poses (one every few seconds to many ids) would otherwise hold every slot.
        let now = self.ns(received);
        let last = s.last_pose_ns.swap(now, Ordering::Relaxed);
        if last != 0 && now.saturating_sub(last) <= STREAM_GAP_NS {
            s.last_seen_ns.fetch_max(now, Ordering::Relaxed);
        }
        s.received.fetch_add(1, Ordering::Relaxed);
        drop(writer);
        Ok(s.force.load_full().filter(|f| f.generation == route.generation))
    }

    /// Gives `slot` to the new session `id` of `generation` (the registry, holding its lock,
    /// before the engine activates the slot and before the id's route is published): no pose, no
    /// force publisher, seen `now`.
    pub fn assign(&self, slot: u16, generation: u32, id: &str, now: Instant) {
        let s = &self.slots[usize::from(slot)];
        // Under the writer, so that a pose of the slot's previous session being written now ends
        // (counted) before the counts restart, and any later one sees the new generation.
        let writer = s.writer.lock().unwrap_or_else(std::sync::PoisonError::into_inner);
        s.id.store(Some(Arc::new(SlotId { generation, id: Box::from(id) })));
        s.generation.store(generation, Ordering::Release);
        s.open.store(true, Ordering::Release);
        s.force.store(None);
        s.last_pose_ns.store(0, Ordering::Relaxed);
        s.last_seen_ns.store(self.ns(now), Ordering::Relaxed);
        s.received.store(0, Ordering::Relaxed);
        drop(writer);
    }

    /// The session in `slot` has closed (the registry, holding its lock): its poses are refused
    /// from now on, also those whose route was looked up before the id left the map.
    pub fn retire(&self, slot: u16) {
        let s = &self.slots[usize::from(slot)];
        let writer = s.writer.lock().unwrap_or_else(std::sync::PoisonError::into_inner);
        s.open.store(false, Ordering::Release);
        drop(writer);
    }

    /// Publishes the open sessions' routes (the registry, after a session opened or closed).
    pub fn publish<'a>(&self, open: impl Iterator<Item = (&'a str, Route)>) {
        self.ids.store(Arc::new(open.map(|(id, r)| (Box::from(id), r)).collect()));
    }

    /// The session of `generation` in `slot` now puts its forces with `publisher` (the comm thread,
    /// once it has declared it); `false`, and nothing set, if that session has ended.
    pub(crate) fn set_force(&self, slot: u16, generation: u32, publisher: Arc<ForcePublisher>) -> bool {
        let s = &self.slots[usize::from(slot)];
        // Under the writer, as `assign` and `retire` change the slot: a publisher is never set
        // for a session after its slot was given to the next.
        let writer = s.writer.lock().unwrap_or_else(std::sync::PoisonError::into_inner);
        let current = s.open.load(Ordering::Acquire) && s.generation.load(Ordering::Acquire) == generation;
        if current {
            s.force.store(Some(publisher));
        }
        drop(writer);
        current
    }

    /// The id of the session of `generation` in `slot` while it is open (a copy; `None` once that
    /// session has ended or its slot was given to another). The comm thread names a session's
    /// outputs with it: set by `assign`, before the engine can tick the session, so it never
    /// waits for the registry (decision 0039).
    #[must_use]
    pub fn id_of(&self, slot: u16, generation: u32) -> Option<String> {
        let s = &self.slots[usize::from(slot)];
        let named = s.id.load();
        let named = named.as_ref().filter(|n| n.generation == generation)?;
        // Checked after the id: `retire` clears `open` without touching the id, and the next
        // `assign` replaces the id first, so a slot seen open here still holds `named`'s session
        // or has just moved on (its outputs are then dropped by `set_force`, as for any session
        // that ends while its publisher is declared).
        self.is_current(slot, generation).then(|| named.id.to_string())
    }

    /// Whether `slot` holds the session of `generation` (open, its id published or about to be).
    #[must_use]
    pub fn is_current(&self, slot: u16, generation: u32) -> bool {
        let s = &self.slots[usize::from(slot)];
        s.open.load(Ordering::Acquire) && s.generation.load(Ordering::Acquire) == generation
    }

    /// A control request keeps the session in `slot` alive, as of `now`.
    pub(crate) fn seen(&self, slot: u16, now: Instant) {
        self.slots[usize::from(slot)].last_seen_ns.fetch_max(self.ns(now), Ordering::Relaxed);
    }

    /// Poses the session in `slot` has received since it opened.
    #[must_use]
    pub fn received(&self, slot: u16) -> u64 {
        self.slots[usize::from(slot)].received.load(Ordering::Relaxed)
    }

    /// How long before `now` the session in `slot` last showed it is alive.
    #[must_use]
    pub fn silent_for(&self, slot: u16, now: Instant) -> Duration {
        let seen = self.slots[usize::from(slot)].last_seen_ns.load(Ordering::Relaxed);
        Duration::from_nanos(self.ns(now).saturating_sub(seen))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::session::Pose;
    use nalgebra::{Point3, UnitQuaternion};

    fn msg(seq: u32) -> PoseMsg {
        let pose = Pose {
            position_m: Point3::new(1e-3, 2e-3, 3e-3),
            orientation: UnitQuaternion::identity(),
            drill_on: true,
            spindle_rpm: 1000.0,
        };
        PoseMsg { seq, client_time_ns: u64::from(seq) * 1_000_000, pose }
    }

    fn routes() -> (Routes, triple_buffer::Output<PoseSample>) {
        let (input, output) = triple_buffer::triple_buffer(&PoseSample::default());
        (Routes::new(vec![input]), output)
    }

    #[test]
    fn a_pose_reaches_its_slot_through_the_published_route() {
        let (r, mut out) = routes();
        assert_eq!(r.find("a"), None);
        r.assign(0, 7, "a", Instant::now());
        r.publish([("a", Route { slot: 0, generation: 7 })].into_iter());
        let route = r.find("a").unwrap();
        assert_eq!(route, Route { slot: 0, generation: 7 });
        assert_eq!(r.pose(route, &msg(3), Instant::now()).unwrap().map(|_| ()), None, "no publisher yet");
        let got = out.read();
        assert_eq!((got.seq, got.generation, got.client_time_ns), (3, 7, 3_000_000));
        assert_eq!(r.received(0), 1);
    }

    #[test]
    fn a_pose_of_an_ended_session_is_refused_after_its_slot_is_reassigned() {
        let (r, mut out) = routes();
        r.assign(0, 1, "a", Instant::now());
        r.publish([("a", Route { slot: 0, generation: 1 })].into_iter());
        let old = r.find("a").unwrap(); // a pose's thread looked the route up...
        r.assign(0, 2, "b", Instant::now()); // ...then "a" closed and "b" took the slot
        r.publish([("b", Route { slot: 0, generation: 2 })].into_iter());
        assert_eq!(r.pose(old, &msg(1), Instant::now()).unwrap_err(), Missed::Ended);
        assert_eq!(r.received(0), 0, "counted for the new session");
        assert_eq!(out.read().generation, 0, "written for the new session");
        assert_eq!(r.find("a"), None);
    }

    #[test]
    fn a_sessions_id_is_known_from_its_assignment_until_it_ends() {
        let (r, _out) = routes();
        assert_eq!(r.id_of(0, 1), None, "never assigned");
        r.assign(0, 1, "a", Instant::now());
        // Before its route is published: the comm thread names the first outputs without the
        // registry.
        assert_eq!(r.find("a"), None);
        assert_eq!(r.id_of(0, 1).as_deref(), Some("a"));
        assert_eq!(r.id_of(0, 2), None, "another generation");
        r.retire(0);
        assert_eq!(r.id_of(0, 1), None, "ended");
        r.assign(0, 2, "b", Instant::now());
        assert_eq!((r.id_of(0, 1), r.id_of(0, 2).as_deref()), (None, Some("b")));
    }

    #[test]
    fn a_pose_routed_just_before_its_session_closed_is_refused() {
        let (r, mut out) = routes();
        r.assign(0, 1, "a", Instant::now());
        r.publish([("a", Route { slot: 0, generation: 1 })].into_iter());
        let route = r.find("a").unwrap(); // looked up, then "a" closed: the slot holds nobody
        r.retire(0);
        r.publish(std::iter::empty());
        assert_eq!(r.pose(route, &msg(1), Instant::now()).unwrap_err(), Missed::Ended);
        assert_eq!((r.received(0), out.read().seq), (0, 0), "counted or written for a closed session");
    }

    #[test]
    fn a_second_writer_at_the_same_instant_drops_its_pose_instead_of_waiting() {
        let (r, _out) = routes();
        r.assign(0, 1, "a", Instant::now());
        let route = Route { slot: 0, generation: 1 };
        let held = r.slots[0].writer.lock().unwrap(); // another thread in the middle of a write
        assert_eq!(r.pose(route, &msg(1), Instant::now()).unwrap_err(), Missed::Busy);
        drop(held);
        assert!(r.pose(route, &msg(2), Instant::now()).is_ok());
        assert_eq!(r.received(0), 1);
    }

    #[test]
    fn only_a_stream_of_poses_keeps_a_session_seen() {
        let (r, _out) = routes();
        let t0 = Instant::now();
        r.assign(0, 1, "a", t0);
        let route = Route { slot: 0, generation: 1 };
        let at = |s: f64| t0 + Duration::from_secs_f64(s);
        // An isolated pose, 3 s in: not a stream, the session was last seen at its start.
        r.pose(route, &msg(1), at(3.0)).unwrap();
        assert!((r.silent_for(0, at(3.0)).as_secs_f64() - 3.0).abs() < 1e-6);
        // The next pose 0.1 s later makes a stream: seen then.
        r.pose(route, &msg(2), at(3.1)).unwrap();
        assert!(r.silent_for(0, at(3.1)) < Duration::from_micros(1));
        // A control request counts too, and time never runs backwards.
        r.seen(0, at(5.0));
        r.seen(0, at(4.0));
        assert!(r.silent_for(0, at(5.0)) < Duration::from_micros(1));
    }
}
