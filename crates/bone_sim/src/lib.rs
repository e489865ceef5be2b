//! # `bone_sim` — the Rust core of DHG (Deep Haptic Guidance)
//!
//! Voxel bone built from CT, layer lookup, material removal by a spherical burr and X-ray views.
//! Pure Rust: nothing here knows about Python; the optional `python` feature adds the thin pyo3
//! binding layer in [`python`] (built by maturin as `dhg._bone_sim`).
//!
//! Units are SI throughout (m, kg, s, N, Pa; temperature in °C); names carry the unit
//! (`radius_m`, `dt_s`). Frames and array layouts are documented once in `docs/frames.md`.

pub mod device;
pub mod error;
pub mod removal;
pub mod volume;
pub mod xray;

#[cfg(feature = "python")]
pub mod python;

pub use device::{DeviceProfile, ForceLimiter};
pub use error::{SimError, SimResult};
pub use removal::{Burr, Cut, RemovalReport};
pub use volume::drilled::DrilledVolume;
pub use volume::grid::Grid;
pub use volume::layer::Layer;
pub use volume::material::HuMapping;
pub use volume::sample::Interp;
pub use volume::Volume;
pub use xray::{Projections, View};
