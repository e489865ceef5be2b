//! numpy ↔ core conversions shared by the wrappers, and the one GIL-release helper.

use nalgebra::Point3;
use numpy::ndarray::Array2;
use numpy::{IntoPyArray, PyArray2, PyReadonlyArray2};
use pyo3::marker::Ungil;
use pyo3::prelude::*;
use serde::de::DeserializeOwned;
use serde::Serialize;

use super::errors::IntoPyResult;
use crate::error::SimError;
use crate::volume::sample::Interp;

/// Runs `f` with the GIL released: everything that can take long goes through here.
pub(crate) fn detached<T: Ungil>(py: Python<'_>, f: impl Ungil + FnOnce() -> T) -> T {
    py.detach(f)
}

/// Reads an `(N, 3)` array of world points (m).
pub(crate) fn points(array: &PyReadonlyArray2<'_, f64>, what: &'static str) -> Result<Vec<Point3<f64>>, SimError> {
    let view = array.as_array();
    if view.ncols() != 3 {
        return Err(SimError::ShapeMismatch {
            what,
            expected: "shape (N, 3)".into(),
            got: format!("{:?}", view.shape()),
        });
    }
    Ok(view.rows().into_iter().map(|r| Point3::new(r[0], r[1], r[2])).collect())
}

/// Parses the interpolation option.
pub(crate) fn interp(name: &str) -> Result<Interp, SimError> {
    match name {
        "nearest" => Ok(Interp::Nearest),
        "linear" => Ok(Interp::Linear),
        _ => Err(SimError::InvalidOption { name: "interp", value: name.to_owned(), allowed: "'nearest', 'linear'" }),
    }
}

/// A row-major image as a 2-D float32 array.
pub(crate) fn image<'py>(py: Python<'py>, data: &[f64], shape: [usize; 2]) -> Bound<'py, PyArray2<f32>> {
    let v: Vec<f32> = data.iter().map(|&x| x as f32).collect();
    // The core guarantees data.len() == rows · cols.
    Array2::from_shape_vec((shape[0], shape[1]), v)
        .unwrap_or_else(|_| Array2::zeros((shape[0], shape[1])))
        .into_pyarray(py)
}

/// A Python value (dicts, lists, numbers, strings) read as a core type through its serde
/// definition; what does not fit (an unknown field, a wrong type) is an `InvalidConfig` naming
/// `what`. The one way settings cross the boundary inwards: no field tables.
pub(crate) fn from_python<T: DeserializeOwned>(value: &Bound<'_, PyAny>, what: &'static str) -> PyResult<T> {
    let mut de = pythonize::Depythonizer::from_object(value);
    serde_path_to_error::deserialize(&mut de)
        .map_err(|e| {
            let path = e.path().to_string();
            let reason = if path == "." { e.inner().to_string() } else { format!("{path}: {}", e.inner()) };
            SimError::InvalidConfig { what, reason }
        })
        .py()
}

/// A Python request (dicts, lists, numbers, strings) as JSON, as a wire request would arrive:
/// JSON has no NaN or infinity, and `serde_json` would read a Python NaN as `null` ("not given"),
/// so a non-finite float anywhere in it is an `InvalidConfig` naming where.
pub(crate) fn json_from_python(value: &Bound<'_, PyAny>, what: &'static str) -> PyResult<serde_json::Value> {
    fn check(value: &Bound<'_, PyAny>, at: &str, what: &'static str) -> PyResult<()> {
        use pyo3::types::{PyDict, PyFloat, PyList, PyTuple};
        if let Ok(f) = value.cast::<PyFloat>() {
            let v = f.value();
            if !v.is_finite() {
                return Err(SimError::InvalidConfig { what, reason: format!("{at}: {v} is not a finite number") }).py();
            }
        } else if let Ok(d) = value.cast::<PyDict>() {
            for (k, v) in d.iter() {
                check(&v, &if at.is_empty() { k.to_string() } else { format!("{at}.{k}") }, what)?;
            }
        } else if let Ok(l) = value.cast::<PyList>() {
            for (i, v) in l.iter().enumerate() {
                check(&v, &format!("{at}[{i}]"), what)?;
            }
        } else if let Ok(t) = value.cast::<PyTuple>() {
            for (i, v) in t.iter().enumerate() {
                check(&v, &format!("{at}[{i}]"), what)?;
            }
        }
        Ok(())
    }
    check(value, "", what)?;
    from_python(value, what)
}

/// A core value as Python dicts, lists and numbers, through its serde definition.
pub(crate) fn to_python<'py, T: Serialize + ?Sized>(py: Python<'py>, value: &T) -> PyResult<Bound<'py, PyAny>> {
    pythonize::pythonize(py, value).map_err(|e| SimError::Engine(format!("cannot hand a value to Python: {e}"))).py()
}
