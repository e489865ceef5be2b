"""CT import: the real slice pydicom ships, synthetic series and NIfTI files, and bad files."""

from __future__ import annotations

import copy

import nibabel as nib
import numpy as np
import pydicom
import pytest
from pydicom.data import get_testdata_file

from dhg import CTImportError, InvalidInputError, Layer, ShapeError
from dhg.bone import ct
from dhg.core.volume import HuMapping

CT_SMALL = get_testdata_file("CT_small.dcm")


def test_ct_small_reads_real_hu():
    img = ct.load(CT_SMALL)
    assert img.hu.shape == (1, 128, 128)
    np.testing.assert_allclose(img.spacing_m[:2], (0.661468e-3, 0.661468e-3), rtol=1e-6)
    np.testing.assert_allclose(img.origin_m, np.array([-158.135803, -179.035797, -75.699997]) * 1e-3)
    # Air around the patient near -1000 HU, soft tissue near 0, and bone well above 700 HU.
    assert -1024 <= img.hu.min() < -800
    assert 1000 < img.hu.max() < 2000
    assert -100 < np.median(img.hu) < 100
    assert np.sum(img.hu > 700) > 50


def test_ct_small_prepares_into_a_volume_with_bone_layers():
    vol = ct.prepare(CT_SMALL, voxel_m=0.661468e-3)
    counts = np.bincount(vol.labels().ravel(), minlength=len(Layer))
    assert counts[Layer.CORTICAL] > 50 and counts[Layer.CANCELLOUS] > 500
    assert vol.hu().max() > 1000
    assert vol.meta["source"].endswith("CT_small.dcm")


def _write_series(folder, positions_mm, rng):
    """Copies of CT_small at the given z positions, in shuffled file order, each slice a
    distinct constant HU so order can be checked."""
    base = pydicom.dcmread(CT_SMALL)
    order = rng.permutation(len(positions_mm))
    for n, i in enumerate(order):
        ds = copy.deepcopy(base)
        ds.ImagePositionPatient = [-158.135803, -179.035797, float(positions_mm[i])]
        ds.InstanceNumber = int(i)
        arr = np.full(base.pixel_array.shape, 1024 + 100 * i, dtype=base.pixel_array.dtype)
        ds.PixelData = arr.tobytes()
        ds.save_as(folder / f"slice_{n:03d}.dcm")
    (folder / "README.txt").write_text("not DICOM: skipped when reading a folder")


def test_dicom_series_is_ordered_by_position_with_spacing_from_headers(tmp_path):
    _write_series(tmp_path, [10.0, 12.5, 15.0, 17.5], np.random.default_rng(1))
    img = ct.load_dicom(tmp_path)
    assert img.hu.shape == (4, 128, 128)
    assert img.spacing_m[2] == pytest.approx(2.5e-3)
    np.testing.assert_allclose(img.hu[:, 0, 0], [0.0, 100.0, 200.0, 300.0])
    assert img.origin_m[2] == pytest.approx(10e-3)


def test_uneven_or_duplicate_slices_are_refused(tmp_path):
    _write_series(tmp_path, [10.0, 12.5, 16.0], np.random.default_rng(2))
    with pytest.raises(CTImportError, match="uneven slice spacing"):
        ct.load_dicom(tmp_path)


def test_non_ct_inputs_are_refused(tmp_path):
    (tmp_path / "notes.txt").write_text("hello")
    with pytest.raises(CTImportError, match="not a DICOM file"):
        ct.load(tmp_path / "notes.txt")
    with pytest.raises(CTImportError, match="no DICOM image slices"):
        ct.load(tmp_path)
    with pytest.raises(CTImportError, match="no such file"):
        ct.load(tmp_path / "missing")
    (tmp_path / "bad.nii.gz").write_bytes(b"\x00" * 100)
    with pytest.raises(CTImportError, match="NIfTI"):
        ct.load(tmp_path / "bad.nii.gz")


def test_nifti_ras_affine_becomes_lps(tmp_path):
    data = np.full((6, 5, 4), -1000.0, np.float32)  # (i, j, k)
    data[3:6, 0:3, 1:4] = 1500.0  # a 3×3×3 marker centred on voxel (4, 1, 2)
    affine = np.diag([-0.8, 0.7, 1.5, 1.0])  # left-handed in RAS: i runs towards patient right
    affine[:3, 3] = [10.0, -20.0, 30.0]
    nib.save(nib.Nifti1Image(data, affine), tmp_path / "ct.nii.gz")
    img = ct.load(tmp_path / "ct.nii.gz")
    assert np.isclose(np.linalg.det(img.direction), 1.0)
    np.testing.assert_allclose(img.spacing_m, (0.8e-3, 0.7e-3, 1.5e-3))
    marker_ras = affine @ np.array([4, 1, 2, 1.0])
    marker_lps = np.array([-marker_ras[0], -marker_ras[1], marker_ras[2]]) * 1e-3
    k, j, i = np.argwhere(img.hu == 1500.0).mean(axis=0)
    np.testing.assert_allclose(img.index_to_world(np.array([[i, j, k]], float))[0], marker_lps, atol=1e-9)
    # After resampling and preparing, the marker is still where it was in the world.
    vol = ct.prepare(tmp_path / "ct.nii.gz", voxel_m=0.5e-3)
    assert vol.hu_at(marker_lps, interp="nearest")[0] > 1000
    assert vol.layer_at(marker_lps)[0] == Layer.CORTICAL


def test_resample_and_crop_keep_world_positions():
    hu = np.zeros((10, 10, 10), np.float32)
    hu[5, 5, 5] = 1000.0
    img = ct.CTImage(hu, (1e-3, 1e-3, 1e-3), np.zeros(3), np.eye(3))
    fine = ct.resample_isotropic(img, 0.5e-3)
    assert fine.hu.shape == (19, 19, 19) and fine.hu[10, 10, 10] == pytest.approx(1000.0)
    cropped = ct.crop(fine, [4e-3, 4e-3, 4e-3], [6e-3, 6e-3, 6e-3])
    assert cropped.hu.shape == (5, 5, 5) and cropped.hu[2, 2, 2] == pytest.approx(1000.0)
    np.testing.assert_allclose(cropped.origin_m, [4e-3, 4e-3, 4e-3])
    with pytest.raises(ValueError, match="does not overlap"):
        ct.crop(fine, [1.0, 1.0, 1.0], [2.0, 2.0, 2.0])
    with pytest.raises(ValueError, match="voxel_m"):
        ct.resample_isotropic(img, 0.0)


def test_segmentation_finds_marrow_inside_a_bone_ring():
    hu = np.full((3, 21, 21), 0.0, np.float32)
    yy, xx = np.mgrid[:21, :21]
    r = np.hypot(yy - 10, xx - 10)
    hu[:, (r > 5) & (r < 8)] = 1500.0
    labels = ct.segment(hu)
    assert labels[1, 10, 10] == Layer.MARROW
    assert labels[1, 10, 16] == Layer.CORTICAL
    assert labels[1, 0, 0] == Layer.OUTSIDE


def test_threshold_layers_are_the_cores_at_both_boundaries():
    m = HuMapping()
    hu = np.array([m.cancellous_min_hu - 1, m.cancellous_min_hu, m.cortical_min_hu, m.cortical_min_hu + 1])
    got = m.threshold_layers(hu.reshape(1, 1, 4))
    assert got.ravel().tolist() == [Layer.OUTSIDE, Layer.CANCELLOUS, Layer.CANCELLOUS, Layer.CORTICAL]
    moved = HuMapping(cortical_min_hu=m.cortical_min_hu + 10).threshold_layers(hu.reshape(1, 1, 4))
    assert moved.ravel().tolist()[-1] == Layer.CANCELLOUS, "the mapping given is the one used"
    with pytest.raises(ShapeError, match="nz, ny, nx"):
        m.threshold_layers(hu)
    with pytest.raises(InvalidInputError):
        HuMapping(cortical_min_hu=float("nan")).threshold_layers(hu.reshape(1, 1, 4))
    # A NaN voxel is refused, as Volume.from_hu refuses it, not labelled outside.
    with pytest.raises(InvalidInputError, match="HU value must be finite"):
        m.threshold_layers(np.array([[[0.0, float("nan")]]]))
