//! The one place where core errors become Python exceptions.
//!
//! The exception classes are defined in Python (`dhg/core/errors.py`) so they can subclass both
//! `DhgError` and the matching builtin (`ValueError`); this module looks them up by the error's
//! kind in `dhg.core.errors.ERROR_KINDS`.

use pyo3::exceptions::PyRuntimeError;
use pyo3::prelude::*;

use crate::error::SimError;

/// Converts a core error into the `dhg.core.errors` exception of its kind (`dhg.core.errors.ERROR_KINDS`,
/// the table remote clients use for error replies too).
#[allow(clippy::needless_pass_by_value)] // by value so it fits `map_err`
pub(crate) fn to_py(err: SimError) -> PyErr {
    let message = err.to_string();
    Python::attach(|py| {
        let class = py.import("dhg.core.errors").and_then(|m| m.getattr("ERROR_KINDS")?.get_item(err.kind()));
        // Every kind has its class (tests/test_one_source.py checks SimError::KINDS against the
        // table); a missing one is a bug, said as such rather than hidden behind a ValueError.
        match class.and_then(|c| c.cast_into().map_err(PyErr::from)) {
            Ok(cls) => PyErr::from_type(cls, message),
            Err(_) => PyRuntimeError::new_err(format!(
                "internal error: no Python class for error kind {:?} in dhg.core.errors.ERROR_KINDS: {message}",
                err.kind()
            )),
        }
    })
}

/// `Result` → `PyResult` with the mapping above.
pub(crate) trait IntoPyResult<T> {
    fn py(self) -> PyResult<T>;
}

impl<T> IntoPyResult<T> for Result<T, SimError> {
    fn py(self) -> PyResult<T> {
        self.map_err(to_py)
    }
}
