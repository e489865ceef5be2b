//! Wire payloads of the real-time server: compact, versioned, little-endian binary layouts.
//!
//! Every layout is declared once here as a [`Layout`] table (field, type, byte offset, count,
//! unit). The encoders and decoders below follow those tables (a test checks each one), Python
//! builds its `struct` formats from the same tables (`dhg.core.protocol`), and `docs/protocol.md`
//! documents them (a test checks the document against the tables).
//!
//! Every payload starts with the same 4-byte header: `kind: u8`, `version: u8`, `flags: u16`.
//! Positions are in the world (LPS) frame in m, forces in N, times in s unless a name says `_ns`.

mod codec;
pub mod keys;
mod layout;
#[cfg(test)]
mod tests;

pub use codec::*;
pub use layout::*;

/// The protocol version every layout here carries in its header.
pub const VERSION: u8 = 1;
/// Records in one model window (the paper's window of 20 records at 10 Hz).
pub const WINDOW_RECORDS: usize = 20;
/// The longest payload the server reads (in a model reply, the longest prediction); anything
/// longer is refused unread.
pub const MAX_PAYLOAD_BYTES: usize = 4096;
/// The most windows one model query holds (`predict` messages back to back): the engine asks for
/// a burst of sessions' windows in one query (decision 0032), and a reply may hold as many
/// `prediction`s, each at most [`MAX_PAYLOAD_BYTES`].
pub const MAX_QUERY_WINDOWS: usize = 32;

/// Flag bits of the force and state headers.
pub mod flags {
    /// The drill is running.
    pub const DRILL_ON: u16 = 1 << 0;
    /// The burr touches bone.
    pub const IN_CONTACT: u16 = 1 << 1;
    /// The burr is cutting.
    pub const CUTTING: u16 = 1 << 2;
    /// A plunge after a breakthrough is under way.
    pub const PLUNGING: u16 = 1 << 3;
    /// No fresh pose for the device's stale time: the force is ramping to zero.
    pub const STALE: u16 = 1 << 4;
    /// The model answered recently (guidance is live).
    pub const MODEL_AVAILABLE: u16 = 1 << 5;
    /// Guidance is mixed into the rendered force (gain > 0 and non-zero guidance).
    pub const GUIDANCE_ACTIVE: u16 = 1 << 6;

    /// Every flag by its name in `docs/protocol.md` (Python's `dhg.core.protocol.FLAGS` is this).
    pub const ALL: [(&str, u16); 7] = [
        ("drill_on", DRILL_ON),
        ("in_contact", IN_CONTACT),
        ("cutting", CUTTING),
        ("plunging", PLUNGING),
        ("stale", STALE),
        ("model_available", MODEL_AVAILABLE),
        ("guidance_active", GUIDANCE_ACTIVE),
    ];
}
