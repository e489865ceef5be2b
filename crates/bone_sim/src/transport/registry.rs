//! Which trainee holds which engine slot. Lives on the comm side behind one mutex that the
//! queryable and reply callbacks and the comm thread share; the tick thread never touches it, and
//! a pose reads only its [`Routes`], which the registry keeps beside its slot table (a pose takes
//! the mutex once, to open its session). The mutex also owns the single producer of the command
//! ring.

use std::collections::HashMap;
use std::sync::Arc;
use std::time::Instant;

use crate::engine::handoff::{Command, PoseSample};
use crate::engine::CommandSender;
use crate::error::{SimError, SimResult};
use crate::guidance::{Fading, GuidanceMode};
use crate::path::PlannedPath;
use crate::protocol::{GuidanceMsg, PoseMsg, StateMsg};

use super::metrics::SessionMetrics;
use super::routes::{Route, Routes};

/// Poses keep their session alive only while they are a stream: each within this long (s) of
/// the one before (4 Hz; a haptic device sends 1 kHz, and even a stalled client's poses come in
/// bursts). A session whose poses stop being a stream is freed after the idle timeout.
pub const STREAM_GAP_S: f64 = 0.25;

/// Longest session id.
pub const MAX_ID_LEN: usize = 64;

/// Checks a session id: 1–64 characters of `A–Z a–z 0–9 _ - .`, the first a letter or digit. It
/// is one key segment, and recorders name a folder after it: so never `.`, `..`, a hidden name
/// or one a command line would read as an option.
///
/// # Errors
/// Any other id.
pub fn check_id(id: &str) -> SimResult<&str> {
    let ok = id.len() <= MAX_ID_LEN
        && id.as_bytes().first().is_some_and(u8::is_ascii_alphanumeric)
        && id.bytes().all(|b| b.is_ascii_alphanumeric() || matches!(b, b'_' | b'-' | b'.'));
    if ok {
        Ok(id)
    } else {
        Err(SimError::InvalidOption { name: "session id", value: id.chars().take(80).collect(), allowed: ID_RULE })
    }
}

/// The session-id rule in words (the refusal's `allowed`).
pub const ID_RULE: &str = "1-64 characters of A-Z a-z 0-9 _ - ., the first a letter or digit";

#[cfg(test)]
mod id_tests {
    use super::{check_id, Owners};

    #[test]
    fn a_sessions_owner_is_the_longest_station_name_it_starts_with() {
        let o = Owners { names: vec!["st-1".into(), "st-1-b".into(), "st-2".into()], max_sessions: 2 };
        assert_eq!(o.of("st-1"), Some("st-1"));
        assert_eq!(o.of("st-1-x"), Some("st-1"));
        assert_eq!(o.of("st-1-b-3"), Some("st-1-b"));
        assert_eq!(o.of("st-10"), None, "st-10 is not st-1's");
        assert_eq!(o.of("other"), None);
    }

    #[test]
    fn ids_that_a_file_system_or_shell_treats_specially_are_refused() {
        for bad in ["", ".", "..", ".hidden", "-rf", "_x", "a/b", "a b", "é", &"x".repeat(65)] {
            assert!(check_id(bad).is_err(), "{bad:?} was accepted");
        }
        for good in ["a", "trainee-01", "alice.02", "S_3", "9", &"x".repeat(64)] {
            assert_eq!(check_id(good).ok(), Some(good));
        }
    }
}

/// A session's force publisher, shared with the threads its poses arrive on: a pose that ticks
/// its session there puts the force from there (`docs/decisions/0023-tick-on-the-pose-thread.md`).
#[derive(Debug)]
pub struct ForcePublisher {
    /// The slot generation (session) it publishes for.
    pub generation: u32,
    /// The publisher of `<prefix>/session/<id>/force`.
    pub publisher: zenoh::pubsub::Publisher<'static>,
}

/// One slot as the comm side knows it.
#[derive(Debug)]
pub struct SlotInfo {
    /// Trainee id holding the slot, if any.
    pub id: Option<String>,
    /// Bumped at every (re)assignment.
    pub generation: u32,
    /// Planned path in effect.
    pub path: PlannedPath,
    /// Guidance mode in effect.
    pub mode: GuidanceMode,
    /// Guidance gain in effect.
    pub gain: f64,
    /// Burr radius in effect (m).
    pub burr_radius_m: f64,
    /// Metrics so far.
    pub metrics: SessionMetrics,
    /// The gain schedule over attempts, if fading.
    pub fading: Option<Fading>,
    /// The engine's count of this slot's attempts (the `attempt` its states carry): counted up
    /// (wrapping) with each `Activate` and `Reset` this registry sends, which the engine applies
    /// in order and counts the same way, so the two agree. A state of another attempt is a
    /// straggler of one that ended.
    pub attempt: u32,
    /// The poses received ([`Routes::received`]) when the current attempt began (a reset or the
    /// session's start).
    pub attempt_first_pose: u64,
    /// The window sequence number of the newest model reply applied in this assignment: a reply
    /// to an older window (however late it comes) is ignored.
    pub applied_window_seq: Option<u32>,
    /// The number of the current attempt's first model window (`None`: the attempt has not
    /// recorded yet: a reset or the session's start). A reply to an earlier window is of the
    /// attempt before, and is not applied.
    pub attempt_first_window: Option<u32>,
}

impl SlotInfo {
    /// The engine was sent `Activate` or `Reset` for this slot, which has received
    /// `poses_received` poses: a new attempt, with no metrics and no record yet.
    pub fn new_attempt(&mut self, poses_received: u64) {
        self.attempt = self.attempt.wrapping_add(1);
        self.metrics = SessionMetrics::default();
        self.attempt_first_pose = poses_received;
        // Until the attempt's first record, any model reply is to a window of the one before.
        self.attempt_first_window = None;
    }

    /// A 10 Hz record of `attempt` reached the comm thread and was asked about as model window
    /// `window_seq`. A record of the current attempt is counted in its metrics, and the first to
    /// come starts its windows (replies to earlier ones are not applied). A record of another
    /// attempt is a straggler of one that ended, still in the output queue at the reset: it is
    /// left out (counted, a second reset would finish a fading attempt on it). Returns whether
    /// the record was counted.
    pub fn add_record(&mut self, msg: &StateMsg, attempt: u32, window_seq: u32) -> bool {
        if attempt != self.attempt {
            return false;
        }
        self.attempt_first_window.get_or_insert(window_seq);
        self.metrics.add_state(msg, &self.path);
        true
    }

    /// Guidance the engine applied: counted in the attempt's metrics once the attempt has
    /// recorded (before, after a reset, it was applied in the attempt that ended).
    pub fn add_guidance(&mut self, msg: &GuidanceMsg) {
        if self.attempt_first_window.is_some() {
            self.metrics.add_guidance(msg);
        }
    }
}

/// The slot table plus the command producer.
#[derive(Debug)]
pub struct Registry {
    /// Commands into the tick thread.
    pub commands: CommandSender,
    /// Session id → slot.
    pub by_id: HashMap<String, u16>,
    /// The slots.
    pub slots: Vec<SlotInfo>,
    /// What the poses' threads read of the slots, without this registry's lock.
    routes: Arc<Routes>,
    default_path: PlannedPath,
    default_mode: GuidanceMode,
    default_gain: f64,
    default_burr_m: f64,
    owners: Owners,
}

/// Who owns which session ids, and how many one owner may hold at once: in the secure lab mode a
/// station `S` names its sessions `S` or `S-<anything>` (its access-control list allows no other),
/// and without a cap one station could take every slot.
#[derive(Debug, Clone, Default)]
pub struct Owners {
    /// Owner names (stations).
    pub names: Vec<String>,
    /// Most sessions one owner may hold (0: no cap).
    pub max_sessions: usize,
}

impl Owners {
    /// The owner of session `id`: the longest name `S` with `id == S` or `id` starting `S-`.
    #[must_use]
    pub fn of<'a>(&'a self, id: &str) -> Option<&'a str> {
        self.names
            .iter()
            .filter(|s| id == s.as_str() || (id.starts_with(s.as_str()) && id.as_bytes().get(s.len()) == Some(&b'-')))
            .max_by_key(|s| s.len())
            .map(String::as_str)
    }
}

impl Registry {
    /// A registry over the engine's pose writers.
    #[must_use]
    pub fn new(
        commands: CommandSender,
        poses: Vec<triple_buffer::Input<PoseSample>>,
        default_path: PlannedPath,
        (default_mode, default_gain): (GuidanceMode, f64),
        default_burr_m: f64,
        owners: Owners,
    ) -> Self {
        let slots = (0..poses.len())
            .map(|_| SlotInfo {
                id: None,
                generation: 0,
                path: default_path.clone(),
                mode: default_mode,
                gain: default_gain,
                burr_radius_m: default_burr_m,
                metrics: SessionMetrics::default(),
                fading: None,
                attempt: 0,
                attempt_first_pose: 0,
                applied_window_seq: None,
                attempt_first_window: None,
            })
            .collect();
        Self {
            commands,
            by_id: HashMap::new(),
            slots,
            routes: Arc::new(Routes::new(poses)),
            default_path,
            default_mode,
            default_gain,
            default_burr_m,
            owners,
        }
    }

    /// The routes of the open sessions' poses (shared with the threads that receive them).
    #[must_use]
    pub fn routes(&self) -> &Arc<Routes> {
        &self.routes
    }

    /// The route of the session in `slot` (open or not).
    #[must_use]
    pub fn route(&self, slot: u16) -> Route {
        Route { slot, generation: self.slots[usize::from(slot)].generation }
    }

    /// Poses the session in `slot` has received.
    #[must_use]
    pub fn poses_received(&self, slot: u16) -> u64 {
        self.routes.received(slot)
    }

    fn publish_routes(&self) {
        self.routes.publish(self.by_id.iter().map(|(id, &slot)| (id.as_str(), self.route(slot))));
    }

    /// Sends a command to the tick thread.
    ///
    /// # Errors
    /// The ring is full (the tick thread is stalled).
    pub fn send(&mut self, cmd: Command) -> SimResult<()> {
        self.commands.push(cmd)
    }

    /// Checks that the command ring can take `n` commands, so that a request that sends several
    /// is refused whole, before it changes anything, rather than half applied.
    ///
    /// # Errors
    /// The ring has fewer free places (the tick thread is stalled).
    pub fn room_for(&self, n: usize) -> SimResult<()> {
        if self.commands.free() < n {
            return Err(SimError::Engine("the engine's command ring is full: try again".into()));
        }
        Ok(())
    }

    /// The slot of `id`, if it has one.
    #[must_use]
    pub fn slot_of(&self, id: &str) -> Option<u16> {
        self.by_id.get(id).copied()
    }

    /// The slot of `id`, creating the session if needed. Returns (slot, created).
    ///
    /// # Errors
    /// A bad id, every slot taken, or a full command ring.
    pub fn open(&mut self, id: &str, path: Option<PlannedPath>) -> SimResult<(u16, bool)> {
        if let Some(slot) = self.slot_of(id) {
            return Ok((slot, false));
        }
        check_id(id)?;
        if let Some(owner) = self.owners.of(id).filter(|_| self.owners.max_sessions > 0) {
            let held = self.by_id.keys().filter(|k| self.owners.of(k) == Some(owner)).count();
            if held >= self.owners.max_sessions {
                return Err(SimError::Engine(format!(
                    "{owner} already holds {held} sessions, the most one station may (close one first)"
                )));
            }
        }
        let Some(slot) = self.slots.iter().position(|s| s.id.is_none()) else {
            return Err(SimError::Engine(format!("all {} session slots are taken", self.slots.len())));
        };
        let info = &mut self.slots[slot];
        let generation = info.generation.wrapping_add(1);
        let path = path.unwrap_or_else(|| self.default_path.clone());
        let (mode, gain) = (self.default_mode, self.default_gain);
        // Named in the routes before the engine can tick it, so that the comm thread finds the
        // id of the session's first outputs there.
        self.routes.assign(slot as u16, generation, id, Instant::now());
        let activate = Command::Activate { slot: slot as u16, generation, path: Some(path.clone()), mode, gain };
        if let Err(e) = self.commands.push(activate) {
            self.routes.retire(slot as u16);
            return Err(e);
        }
        let info = &mut self.slots[slot];
        info.id = Some(id.to_owned());
        info.generation = generation;
        info.path = path;
        info.mode = mode;
        info.gain = gain;
        info.burr_radius_m = self.default_burr_m;
        info.fading = None;
        info.new_attempt(0);
        info.applied_window_seq = None;
        self.by_id.insert(id.to_owned(), slot as u16);
        self.publish_routes();
        Ok((slot as u16, true))
    }

    /// Hands a decoded pose, `received` when its sample arrived, to the tick thread, as a pose's
    /// thread does through the [`Routes`] (tests drive a session with it).
    pub fn pose(&self, slot: u16, msg: &PoseMsg, received: Instant) {
        let _ = self.routes.pose(self.route(slot), msg, received);
    }

    /// A control request keeps the session in `slot` alive.
    pub fn seen(&self, slot: u16) {
        self.routes.seen(slot, Instant::now());
    }

    /// Frees the session `id`.
    ///
    /// # Errors
    /// Unknown id, or a full command ring.
    pub fn close(&mut self, id: &str) -> SimResult<()> {
        let slot = self.slot_of(id).ok_or_else(|| SimError::Engine(format!("no session {id:?}")))?;
        self.send(Command::Release { slot })?;
        self.by_id.remove(id);
        self.slots[slot as usize].id = None;
        self.routes.retire(slot);
        self.publish_routes();
        Ok(())
    }

    /// Frees every session silent for longer than `timeout_s`; returns their ids.
    pub fn sweep_idle(&mut self, timeout_s: f64) -> Vec<String> {
        let now = Instant::now();
        let idle: Vec<String> = self
            .by_id
            .iter()
            .filter(|(_, &slot)| self.routes.silent_for(slot, now).as_secs_f64() > timeout_s)
            .map(|(id, _)| id.clone())
            .collect();
        for id in &idle {
            let _ = self.close(id);
        }
        idle
    }
}
