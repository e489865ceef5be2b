//! `Volume` and `DrilledVolume`: thin wrappers over the core types.

use std::sync::Arc;

use numpy::ndarray::{Array1, Array2, Array3, Array4};
use numpy::{
    IntoPyArray, PyArray1, PyArray2, PyArray3, PyArray4, PyReadonlyArray2, PyReadonlyArray3, PyUntypedArrayMethods,
};
use pyo3::prelude::*;
use pyo3::types::PyDict;

use super::convert::{detached, from_python, image, points, to_python};
use super::errors::IntoPyResult;
use crate::error::SimError;
use crate::path::PlannedPath;
use crate::removal::{Burr, Cut};
use crate::volume::bricks::BRICK_EDGE;
use crate::volume::drilled::DrilledVolume;
use crate::volume::grid::Grid;
use crate::volume::material::HuMapping;
use crate::volume::Volume;
use crate::xray::{Projections, View};

/// A CT bone volume (immutable, shared by every drilling session). Build it with
/// `dhg.Volume.from_hu`; this is the native half.
#[pyclass(name = "Volume", module = "dhg._bone_sim", frozen)]
pub struct PyVolume {
    pub(crate) inner: Arc<Volume>,
}

fn mapping_from_dict(dict: Option<&Bound<'_, PyDict>>) -> PyResult<HuMapping> {
    dict.map_or_else(|| Ok(HuMapping::default()), |d| from_python(d.as_any(), "HU mapping"))
}

/// The layer ids a CT's HU values get by threshold alone (`HuMapping::threshold_layer`: cortical,
/// cancellous or outside), for the CT importer to add the anatomy thresholds cannot see.
#[pyfunction]
#[pyo3(signature = (hu, mapping=None))]
pub(crate) fn threshold_layers<'py>(
    py: Python<'py>,
    hu: PyReadonlyArray3<'py, f32>,
    mapping: Option<&Bound<'py, PyDict>>,
) -> PyResult<Bound<'py, PyArray3<u8>>> {
    let m = mapping_from_dict(mapping)?;
    m.validate().py()?;
    let hu = hu.as_array();
    if let Some(&v) = hu.iter().find(|v| !v.is_finite()) {
        return Err(SimError::NonFinite { what: "HU value", value: f64::from(v) }).py();
        // as Volume::from_hu
    }
    Ok(hu.mapv(|v| m.threshold_layer(f64::from(v)) as u8).into_pyarray(py))
}

/// A session's drilled bricks handed to Python: origins (n, 3) as voxel (i, j, k) and material
/// (n, 8, 8, 8) `u16` indexed [k][j][i] within the brick.
pub(crate) type Bricks<'py> = (Bound<'py, PyArray2<u32>>, Bound<'py, PyArray4<u16>>);

/// The drilled bricks of `bone` as numpy arrays (see [`Bricks`]).
pub(crate) fn bricks_arrays<'py>(py: Python<'py>, bone: &DrilledVolume) -> Bricks<'py> {
    let (mut origins, mut material) = (Vec::new(), Vec::new());
    for (o, b) in bone.bricks() {
        origins.extend(o.map(|v| u32::try_from(v).unwrap_or(u32::MAX)));
        material.extend_from_slice(b);
    }
    let n = origins.len() / 3;
    let e = BRICK_EDGE;
    let origins = Array2::from_shape_vec((n, 3), origins).expect("3 per brick");
    let material = Array4::from_shape_vec((n, e, e, e), material).expect("BRICK_VOXELS per brick");
    (origins.into_pyarray(py), material.into_pyarray(py))
}

/// The (top, front, side) images handed to Python.
pub(crate) type Views<'py> = (Bound<'py, PyArray2<f32>>, Bound<'py, PyArray2<f32>>, Bound<'py, PyArray2<f32>>);

pub(crate) fn xray_tuple<'py>(py: Python<'py>, p: &Projections) -> Views<'py> {
    let [top, front, side] = View::ALL.map(|v| {
        let (data, shape) = p.view(v);
        image(py, data, shape)
    });
    (top, front, side)
}

/// A k-major voxel array as a numpy array of shape (nz, ny, nx).
fn grid_array<T: numpy::Element>(
    py: Python<'_>,
    shape: (usize, usize, usize),
    data: Vec<T>,
) -> PyResult<Bound<'_, PyArray3<T>>> {
    Array3::from_shape_vec(shape, data)
        .map(|a| a.into_pyarray(py))
        .map_err(|e| pyo3::exceptions::PyRuntimeError::new_err(format!("internal: voxel array shape: {e}")))
}

fn per_point<T: numpy::Element + Copy>(
    pts: &PyReadonlyArray2<'_, f64>,
    f: impl Fn(&nalgebra::Point3<f64>) -> Result<T, SimError>,
) -> PyResult<Array1<T>> {
    let pts = points(pts, "points (m)").py()?;
    let out: Result<Vec<T>, SimError> = pts.iter().map(f).collect();
    Ok(Array1::from(out.py()?))
}

#[pymethods]
impl PyVolume {
    /// Builds a volume from HU (float32, shape (nz, ny, nx)), geometry in metres, optional layer
    /// labels (uint8, same shape) and an optional HU mapping dict.
    #[new]
    #[pyo3(signature = (hu, spacing_m, origin_m, direction, labels=None, mapping=None))]
    fn new(
        py: Python<'_>,
        hu: PyReadonlyArray3<'_, f32>,
        spacing_m: [f64; 3],
        origin_m: [f64; 3],
        direction: PyReadonlyArray2<'_, f64>,
        labels: Option<PyReadonlyArray3<'_, u8>>,
        mapping: Option<&Bound<'_, PyDict>>,
    ) -> PyResult<Self> {
        let mapping = mapping_from_dict(mapping)?;
        let shape = hu.shape().to_vec();
        let dir = direction.as_array();
        if dir.shape() != [3, 3] {
            return Err(SimError::ShapeMismatch {
                what: "direction",
                expected: "shape (3, 3)".into(),
                got: format!("{:?}", dir.shape()),
            })
            .py();
        }
        let direction = nalgebra::Matrix3::from_fn(|r, c| dir[[r, c]]);
        if let Some(labels) = &labels {
            if labels.shape() != shape.as_slice() {
                return Err(SimError::ShapeMismatch {
                    what: "labels shape",
                    expected: format!("{shape:?} (the HU array's shape)"),
                    got: format!("{:?}", labels.shape()),
                })
                .py();
            }
        }
        let hu: Vec<f32> = hu.as_array().iter().copied().collect();
        let labels: Option<Vec<u8>> = labels.map(|l| l.as_array().iter().copied().collect());
        let dims = [shape[2], shape[1], shape[0]];
        let volume = detached(py, move || {
            let grid = Grid::new(dims, spacing_m, origin_m, direction)?;
            Volume::from_hu(grid, &hu, labels.as_deref(), mapping)
        })
        .py()?;
        Ok(Self { inner: Arc::new(volume) })
    }

    /// Array shape (nz, ny, nx).
    #[getter]
    fn shape(&self) -> (usize, usize, usize) {
        let [nx, ny, nz] = self.inner.grid().dims();
        (nz, ny, nx)
    }

    /// Voxel spacing along x, y, z (m).
    #[getter]
    fn spacing_m(&self) -> [f64; 3] {
        self.inner.grid().spacing_m()
    }

    /// World position of voxel (0, 0, 0)'s centre (m).
    #[getter]
    fn origin_m(&self) -> [f64; 3] {
        let o = self.inner.grid().origin_m();
        [o.x, o.y, o.z]
    }

    /// Orientation (3×3; columns are the world directions of the x, y, z array axes).
    #[getter]
    fn direction<'py>(&self, py: Python<'py>) -> Bound<'py, PyArray2<f64>> {
        let d = self.inner.grid().direction();
        Array2::from_shape_fn((3, 3), |(r, c)| d[(r, c)]).into_pyarray(py)
    }

    /// The HU mapping in use, as a dict.
    #[getter]
    fn mapping<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyAny>> {
        to_python(py, self.inner.table().mapping())
    }

    /// Bytes held by the volume (shared by all sessions).
    #[getter]
    fn memory_bytes(&self) -> usize {
        self.inner.memory_bytes()
    }

    /// Copy of the layer labels, uint8 (nz, ny, nx).
    fn labels<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyArray3<u8>>> {
        grid_array(py, self.shape(), self.inner.labels().to_vec())
    }

    /// Copy of the stored HU, int16 (nz, ny, nx).
    fn hu<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyArray3<i16>>> {
        grid_array(py, self.shape(), self.inner.hu().to_vec())
    }

    /// Pristine layer id at each world point (N, 3) in metres.
    fn layer_at<'py>(
        &self,
        py: Python<'py>,
        points_m: PyReadonlyArray2<'_, f64>,
    ) -> PyResult<Bound<'py, PyArray1<u8>>> {
        Ok(per_point(&points_m, |p| self.inner.layer_at(p).map(crate::Layer::id))?.into_pyarray(py))
    }

    /// The pristine layers along the path A → B (m) sampled every `step_m` (m), as runs
    /// (layer id, first sample's depth (m), last sample's depth (m)).
    fn layer_runs(
        &self,
        py: Python<'_>,
        entry_m: [f64; 3],
        target_m: [f64; 3],
        step_m: f64,
    ) -> PyResult<Vec<(u8, f64, f64)>> {
        let path = PlannedPath::new(entry_m.into(), target_m.into()).py()?;
        let runs = detached(py, || path.layer_runs(&self.inner, step_m)).py()?;
        Ok(runs.iter().map(|r| (r.layer.id(), r.start_m, r.end_m)).collect())
    }

    /// HU at each world point (N, 3) in metres.
    #[pyo3(signature = (points_m, interp="linear"))]
    fn hu_at<'py>(
        &self,
        py: Python<'py>,
        points_m: PyReadonlyArray2<'_, f64>,
        interp: &str,
    ) -> PyResult<Bound<'py, PyArray1<f64>>> {
        let mode = super::convert::interp(interp).py()?;
        Ok(per_point(&points_m, |p| self.inner.hu_at(p, mode))?.into_pyarray(py))
    }

    /// Apparent density (kg/m³) at each world point (N, 3) in metres.
    #[pyo3(signature = (points_m, interp="linear"))]
    fn density_at<'py>(
        &self,
        py: Python<'py>,
        points_m: PyReadonlyArray2<'_, f64>,
        interp: &str,
    ) -> PyResult<Bound<'py, PyArray1<f64>>> {
        let mode = super::convert::interp(interp).py()?;
        Ok(per_point(&points_m, |p| self.inner.density_at(p, mode))?.into_pyarray(py))
    }

    /// Continuous (x, y, z) array indices of world points (N, 3) in metres.
    fn world_to_index<'py>(
        &self,
        py: Python<'py>,
        points_m: PyReadonlyArray2<'_, f64>,
    ) -> PyResult<Bound<'py, PyArray2<f64>>> {
        let pts = points(&points_m, "points (m)").py()?;
        let grid = self.inner.grid();
        Ok(Array2::from_shape_fn((pts.len(), 3), |(r, c)| grid.world_to_index(&pts[r])[c]).into_pyarray(py))
    }

    /// X-ray line integrals of the undrilled volume: (top, front, side) float32 images.
    fn xray<'py>(&self, py: Python<'py>) -> Views<'py> {
        xray_tuple(py, self.inner.pristine_xray())
    }
}

/// One session's drilled copy of a shared `Volume` (copy-on-write bricks).
#[pyclass(name = "DrilledVolume", module = "dhg._bone_sim")]
pub struct PyDrilledVolume {
    inner: DrilledVolume,
    volume: Py<PyVolume>,
}

#[pymethods]
impl PyDrilledVolume {
    /// A fresh, undrilled session view of `volume`.
    #[new]
    // 512 = DEFAULT_RESERVED_BRICKS, written out so the Python signature shows it.
    #[pyo3(signature = (volume, reserve_bricks=512))]
    fn new(volume: Bound<'_, PyVolume>, reserve_bricks: usize) -> Self {
        let inner = DrilledVolume::with_reserve(Arc::clone(&volume.get().inner), reserve_bricks.min(1 << 20));
        Self { inner, volume: volume.unbind() }
    }

    /// The shared pristine volume.
    #[getter]
    fn volume(&self, py: Python<'_>) -> Py<PyVolume> {
        self.volume.clone_ref(py)
    }

    /// Erodes the material inside a burr at `center_m` (m) of `radius_m` (m) for `dt_s` (s).
    #[pyo3(signature = (center_m, radius_m, spindle_rpm, dt_s, contact=1.0))]
    fn remove<'py>(
        &mut self,
        py: Python<'py>,
        center_m: [f64; 3],
        radius_m: f64,
        spindle_rpm: f64,
        dt_s: f64,
        contact: f64,
    ) -> PyResult<Bound<'py, PyAny>> {
        let burr = Burr { center_m: center_m.into(), radius_m };
        let report = self.inner.remove(&burr, &Cut { spindle_rpm, dt_s, contact }).py()?;
        to_python(py, &report)
    }

    /// Erodes along a path of burr centres (N, 3) in metres, `dt_s` at each; returns the summed
    /// report. All centres are checked before anything is removed.
    #[pyo3(signature = (centers_m, radius_m, spindle_rpm, dt_s, contact=1.0))]
    fn remove_along<'py>(
        &mut self,
        py: Python<'py>,
        centers_m: PyReadonlyArray2<'_, f64>,
        radius_m: f64,
        spindle_rpm: f64,
        dt_s: f64,
        contact: f64,
    ) -> PyResult<Bound<'py, PyAny>> {
        let centers = points(&centers_m, "centers_m").py()?;
        let cut = Cut { spindle_rpm, dt_s, contact };
        for c in &centers {
            Burr { center_m: *c, radius_m }.validate().py()?;
        }
        cut.validate().py()?;
        let inner = &mut self.inner;
        let report = detached(py, move || inner.remove_along(&centers, radius_m, &cut)).py()?;
        to_python(py, &report)
    }

    /// Material fraction left (0..1) at each world point (N, 3) in metres.
    #[pyo3(signature = (points_m, interp="nearest"))]
    fn material_at<'py>(
        &self,
        py: Python<'py>,
        points_m: PyReadonlyArray2<'_, f64>,
        interp: &str,
    ) -> PyResult<Bound<'py, PyArray1<f64>>> {
        let mode = super::convert::interp(interp).py()?;
        Ok(per_point(&points_m, |p| self.inner.material_at(p, mode))?.into_pyarray(py))
    }

    /// Current layer id at each world point (N, 3) in metres (0 where drilled away).
    fn layer_at<'py>(
        &self,
        py: Python<'py>,
        points_m: PyReadonlyArray2<'_, f64>,
    ) -> PyResult<Bound<'py, PyArray1<u8>>> {
        Ok(per_point(&points_m, |p| self.inner.layer_at(p).map(crate::Layer::id))?.into_pyarray(py))
    }

    /// Material fraction of every voxel, float32 (nz, ny, nx).
    fn material_grid<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyArray3<f32>>> {
        let [nx, ny, nz] = self.inner.volume().grid().dims();
        let inner = &self.inner;
        let data = detached(py, || {
            let mut v = Vec::with_capacity(nx * ny * nz);
            for k in 0..nz {
                for j in 0..ny {
                    for i in 0..nx {
                        v.push(inner.material_fraction(i, j, k) as f32);
                    }
                }
            }
            v
        });
        grid_array(py, (nz, ny, nx), data)
    }

    /// X-ray line integrals of the drilled bone: (top, front, side) float32 images.
    fn xray<'py>(&self, py: Python<'py>) -> Views<'py> {
        let inner = &self.inner;
        let p = detached(py, || inner.xray());
        xray_tuple(py, &p)
    }

    /// Restores the pristine bone.
    fn reset(&mut self) {
        self.inner.reset();
    }

    /// Total mass removed (kg).
    #[getter]
    fn removed_mass_kg(&self) -> f64 {
        self.inner.removed_mass_kg()
    }

    /// Voxels fully removed.
    #[getter]
    fn removed_voxels(&self) -> u64 {
        self.inner.removed_voxels()
    }

    /// Bricks this session has copied.
    #[getter]
    fn drilled_bricks(&self) -> usize {
        self.inner.overlay().owned_count()
    }

    /// The drilled bricks: origins (n, 3) voxel (i, j, k), material (n, 8, 8, 8) u16 [k][j][i].
    fn bricks<'py>(&self, py: Python<'py>) -> Bricks<'py> {
        bricks_arrays(py, &self.inner)
    }

    /// Bytes this session holds beyond the shared volume.
    #[getter]
    fn memory_bytes(&self) -> usize {
        self.inner.memory_bytes()
    }
}
