//! The crate's one error type. Every fallible public function returns [`SimError`]; its
//! [`kind`](SimError::kind) names the category that the Python layer (`python/errors.rs`) and
//! remote clients (the `kind` of an error reply) map to an exception class.

use thiserror::Error;

/// Everything that can go wrong in the bone simulation core.
#[derive(Debug, Error, Clone, PartialEq)]
pub enum SimError {
    /// A value that must be finite was NaN or infinite.
    #[error("{what} must be finite, got {value}")]
    NonFinite {
        /// What was being checked, with its unit (e.g. "burr centre x (m)").
        what: &'static str,
        /// The offending value.
        value: f64,
    },
    /// A scalar parameter outside its allowed range.
    #[error("{name} = {value} is invalid: {reason}")]
    InvalidParameter {
        /// Parameter name with its unit.
        name: &'static str,
        /// The offending value.
        value: f64,
        /// What the allowed range is.
        reason: &'static str,
    },
    /// Array or grid sizes that do not agree.
    #[error("{what}: expected {expected}, got {got}")]
    ShapeMismatch {
        /// What was being checked.
        what: &'static str,
        /// The expected size or shape, as text.
        expected: String,
        /// The size or shape that was given, as text.
        got: String,
    },
    /// An input that must not be empty was empty.
    #[error("{what} must not be empty")]
    Empty {
        /// What was empty.
        what: &'static str,
    },
    /// A label that is not one of the layer ids.
    #[error("unknown layer id {id} at voxel {voxel} (valid ids are 0..={max})")]
    UnknownLayer {
        /// The offending id.
        id: u8,
        /// Linear index of the first voxel carrying it.
        voxel: usize,
        /// The largest valid id.
        max: u8,
    },
    /// A wire payload that does not follow its layout (see `docs/protocol.md`).
    #[error("bad {message} payload: {reason}")]
    Payload {
        /// Which message (e.g. "pose").
        message: &'static str,
        /// What was wrong, with the sizes or values found.
        reason: String,
    },
    /// The Zenoh transport failed (open, declare, endpoint in use).
    #[error("zenoh: {0}")]
    Transport(String),
    /// The real-time engine refused a request (not running, no such session, full).
    #[error("engine: {0}")]
    Engine(String),
    /// A string option that is not one of the allowed values.
    #[error("{name} must be one of {allowed}, got {value:?}")]
    InvalidOption {
        /// Option name.
        name: &'static str,
        /// The value given.
        value: String,
        /// The allowed values, as text.
        allowed: &'static str,
    },
    /// A settings object that does not fit its definition: an unknown field, a value of the wrong
    /// type (Python dicts and JSON bodies are read through the core types' serde definitions).
    #[error("invalid {what}: {reason}")]
    InvalidConfig {
        /// What was being read (e.g. "session config").
        what: &'static str,
        /// What did not fit, as the reader says it.
        reason: String,
    },
    /// A grid whose geometry is unusable (orientation not a rotation, too many voxels...).
    #[error("invalid grid: {reason}")]
    InvalidGrid {
        /// What is wrong with it.
        reason: String,
    },
}

/// Result alias used throughout the crate.
pub type SimResult<T> = Result<T, SimError>;

impl SimError {
    /// Every error kind [`kind`](Self::kind) returns: the Python layer has one exception class
    /// for each (checked by a test on both sides).
    pub const KINDS: [&'static str; 4] = ["invalid_input", "shape", "transport", "engine"];

    /// The error's category, as written in the `kind` field of error replies on the wire
    /// (`docs/protocol.md`): `invalid_input`, `shape`, `transport` or `engine`. Python maps each to
    /// one exception class (`dhg.core.errors.ERROR_KINDS`).
    #[must_use]
    pub fn kind(&self) -> &'static str {
        match self {
            Self::ShapeMismatch { .. } | Self::Empty { .. } => "shape",
            Self::NonFinite { .. }
            | Self::InvalidParameter { .. }
            | Self::UnknownLayer { .. }
            | Self::InvalidOption { .. }
            | Self::InvalidGrid { .. }
            | Self::InvalidConfig { .. }
            | Self::Payload { .. } => "invalid_input",
            Self::Transport(_) => "transport",
            Self::Engine(_) => "engine",
        }
    }
}

/// Returns `Err(NonFinite)` unless `value` is finite.
pub(crate) fn finite(what: &'static str, value: f64) -> SimResult<f64> {
    if value.is_finite() {
        Ok(value)
    } else {
        Err(SimError::NonFinite { what, value })
    }
}

/// Returns `Err(InvalidParameter)` unless `value` is finite and strictly positive.
pub(crate) fn positive(name: &'static str, value: f64) -> SimResult<f64> {
    finite(name, value)?;
    if value > 0.0 {
        Ok(value)
    } else {
        Err(SimError::InvalidParameter { name, value, reason: "must be > 0" })
    }
}

/// Returns `Err(InvalidParameter)` unless `value` is finite and `>= 0`.
pub(crate) fn non_negative(name: &'static str, value: f64) -> SimResult<f64> {
    finite(name, value)?;
    if value >= 0.0 {
        Ok(value)
    } else {
        Err(SimError::InvalidParameter { name, value, reason: "must be >= 0" })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_error_kind_is_one_of_the_kinds_python_maps() {
        let one_of_each = [
            SimError::NonFinite { what: "x", value: f64::NAN },
            SimError::InvalidParameter { name: "x", value: 0.0, reason: "r" },
            SimError::ShapeMismatch { what: "x", expected: "a".into(), got: "b".into() },
            SimError::Empty { what: "x" },
            SimError::UnknownLayer { id: 9, voxel: 0, max: 4 },
            SimError::Payload { message: "pose", reason: "r".into() },
            SimError::Transport("t".into()),
            SimError::Engine("e".into()),
            SimError::InvalidOption { name: "x", value: "v".into(), allowed: "a" },
            SimError::InvalidConfig { what: "x", reason: "r".into() },
            SimError::InvalidGrid { reason: "r".into() },
        ];
        // A new variant must be added above (this match fails to compile until it is).
        for e in &one_of_each {
            match e {
                SimError::NonFinite { .. }
                | SimError::InvalidParameter { .. }
                | SimError::ShapeMismatch { .. }
                | SimError::Empty { .. }
                | SimError::UnknownLayer { .. }
                | SimError::Payload { .. }
                | SimError::Transport(_)
                | SimError::Engine(_)
                | SimError::InvalidOption { .. }
                | SimError::InvalidConfig { .. }
                | SimError::InvalidGrid { .. } => {}
            }
            assert!(SimError::KINDS.contains(&e.kind()), "{e:?}");
        }
        let used: std::collections::BTreeSet<_> = one_of_each.iter().map(SimError::kind).collect();
        assert_eq!(used.len(), SimError::KINDS.len(), "a kind no error has");
    }
}
