//! # `bone_sim` — the Rust core of DHG (Deep Haptic Guidance)
//!
//! Voxel bone built from CT, layer lookup, material removal by a spherical burr, X-ray views,
//! 1 kHz haptic sessions, and the real-time server: the tick [`engine`] and its Zenoh
//! [`transport`] speaking the [`protocol`].
//! Pure Rust: nothing here knows about Python; the optional `python` feature adds the thin pyo3
//! binding layer in `python` (built by maturin as `dhg._bone_sim`).
//!
//! Units are SI throughout (m, kg, s, N, Pa; temperature in °C); names carry the unit
//! (`radius_m`, `dt_s`). Frames and array layouts are documented once in `docs/frames.md`.

pub mod contact;
pub mod cutting;
pub mod device;
pub mod engine;
pub mod error;
pub mod guidance;
pub mod path;
pub mod protocol;
pub mod record;
pub mod removal;
pub mod session;
pub mod skill;
pub mod surgeon;
pub mod thermal;
pub mod transport;
pub mod volume;
pub mod xray;

#[cfg(feature = "python")]
pub mod python;

pub use device::{DeviceProfile, ForceLimiter};
pub use error::{SimError, SimResult};
pub use path::PlannedPath;
pub use record::{Record, FEATURES, FEATURE_COUNT};
pub use removal::{Burr, Cut, RemovalReport};
pub use session::{DrillingSession, Pose, SessionConfig, SessionState, TickOutput};
pub use volume::drilled::DrilledVolume;
pub use volume::grid::Grid;
pub use volume::layer::Layer;
pub use volume::material::HuMapping;
pub use volume::sample::Interp;
pub use volume::Volume;
pub use xray::{Projections, View};
