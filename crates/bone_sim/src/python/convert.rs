//! numpy ↔ core conversions shared by the wrappers, and the one GIL-release helper.

use nalgebra::Point3;
use numpy::ndarray::Array2;
use numpy::{IntoPyArray, PyArray2, PyReadonlyArray2};
use pyo3::marker::Ungil;
use pyo3::prelude::*;

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
