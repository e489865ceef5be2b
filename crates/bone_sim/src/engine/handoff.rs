//! What crosses between the communication side and the tick thread. Everything here is plain
//! data moved through lock-free structures: an SPSC ring of [`Command`]s into the tick thread, a
//! bounded multi-producer queue of [`Output`]s out of every tick, and one triple buffer per
//! session slot for the newest pose.

use std::time::Instant;

use crate::guidance::GuidanceMode;
use crate::path::PlannedPath;
use crate::protocol::{ForceMsg, GuidanceMsg, StateMsg};
use crate::record::Record;
use crate::session::Pose;

/// The newest stylus pose of a slot, as the subscriber decoded it.
#[derive(Debug, Clone, Copy, Default)]
pub struct PoseSample {
    /// The pose (`None` until the first one arrives).
    pub pose: Option<Pose>,
    /// The client's sequence number.
    pub seq: u32,
    /// The client's send time (ns), echoed in the force.
    pub client_time_ns: u64,
    /// The slot generation it was written for (poses of an earlier owner are ignored).
    pub generation: u32,
    /// When the server received it (for the server's own pose → force latency).
    pub received: Option<Instant>,
}

/// A request to the tick thread.
#[derive(Debug, Clone)]
pub enum Command {
    /// Start a session in `slot` (reset bone and state), optionally with its own path.
    Activate {
        /// Slot index.
        slot: u16,
        /// New generation of the slot.
        generation: u32,
        /// Planned path; the engine's default when `None`.
        path: Option<PlannedPath>,
        /// Initial guidance mode.
        mode: GuidanceMode,
        /// Initial guidance gain.
        gain: f64,
    },
    /// Stop the session in `slot`.
    Release {
        /// Slot index.
        slot: u16,
    },
    /// Restore the undrilled bone and a fresh state.
    Reset {
        /// Slot index.
        slot: u16,
    },
    /// Replace the planned path.
    SetPath {
        /// Slot index.
        slot: u16,
        /// The new path.
        path: PlannedPath,
    },
    /// Swap the burr: a new radius (m), checked by the sender; the drilled bone stays.
    SetBurr {
        /// Slot index.
        slot: u16,
        /// Burr radius (m).
        radius_m: f64,
    },
    /// Change the guidance mode and gain (gain 0 renders no guidance; the paper's guidance is
    /// still computed and published).
    SetGuidance {
        /// Slot index.
        slot: u16,
        /// Mode.
        mode: GuidanceMode,
        /// Gain, 0..=`MAX_GAIN`, checked by the sender.
        gain: f64,
    },
    /// A model reply for a slot's window.
    Prediction {
        /// Slot index.
        slot: u16,
        /// Generation the window was taken from.
        generation: u32,
        /// Window sequence number.
        window_seq: u32,
        /// Predicted expert force (N).
        predicted_n: [f64; 3],
        /// Query round trip (s).
        latency_s: f64,
        /// Client time of the newest pose in the window (ns).
        pose_client_time_ns: u64,
    },
    /// Copy the slot's bone into the snapshot buffer (for X-ray views).
    Snapshot {
        /// Slot index.
        slot: u16,
    },
}

impl Command {
    /// The slot it is for.
    #[must_use]
    pub fn slot(&self) -> u16 {
        match self {
            Self::Activate { slot, .. }
            | Self::Release { slot }
            | Self::Reset { slot }
            | Self::SetPath { slot, .. }
            | Self::SetBurr { slot, .. }
            | Self::SetGuidance { slot, .. }
            | Self::Prediction { slot, .. }
            | Self::Snapshot { slot } => *slot,
        }
    }
}

/// What a tick (on the tick thread or a pose's thread) hands out.
#[derive(Debug, Clone, Copy)]
pub enum Output {
    /// The force rendered this tick.
    Force {
        /// Slot index.
        slot: u16,
        /// Slot generation.
        generation: u32,
        /// The message.
        msg: ForceMsg,
        /// The pose the tick used (for the recorders' stream), none before the first.
        pose: Option<Pose>,
        /// When the server received the pose this force was computed from; `None` when the
        /// tick had no fresh pose.
        received: Option<Instant>,
        /// The slot's ticks since the engine started (never reset): which of two forces is newer.
        order: u64,
        /// Whether the thread its pose arrived on puts it (the comm side only records it).
        published: bool,
    },
    /// The 10 Hz record and state.
    State {
        /// Slot index.
        slot: u16,
        /// Slot generation.
        generation: u32,
        /// The session's attempt, counted up at its start and each reset (wrapping): which
        /// records belong together, even where some were lost on the way.
        attempt: u32,
        /// The record (model features).
        record: Record,
        /// The state message.
        msg: StateMsg,
    },
    /// Guidance took effect.
    Guidance {
        /// Slot index.
        slot: u16,
        /// Slot generation.
        generation: u32,
        /// The message.
        msg: GuidanceMsg,
    },
    /// The snapshot buffer holds this slot's bone.
    Snapshot {
        /// Slot index.
        slot: u16,
        /// Slot generation.
        generation: u32,
    },
}
