"""Importing real CT: DICOM series (pydicom) and NIfTI (nibabel) → a prepared :class:`Volume`.

Steps: read (HU from RescaleSlope/Intercept, slices ordered along their normal, spacing from the
headers) → resample to isotropic voxels on an axis-aligned LPS grid → crop to a region →
segment layers (HU thresholds; marrow = low-HU voxels enclosed by bone in an axial slice) →
:class:`Volume`, which :meth:`Volume.save` writes as a prepared volume file.

Necrosis cannot be told from HU alone; pass ``labels`` from your own segmentation to mark it.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import numpy.typing as npt
from scipy import ndimage

from dhg.core.errors import CTImportError, InvalidInputError
from dhg.core.layers import Layer
from dhg.core.volume import HU_MIN, HuMapping, Volume

__all__ = ["CTImage", "crop", "load", "load_dicom", "load_nifti", "prepare", "resample_isotropic", "segment"]

AIR_HU = HU_MIN
"""Air (HU): the core's lowest stored value, given to voxels resampled from outside the scan."""


@dataclass
class CTImage:
    """A CT image in HU with its geometry (m, world frame LPS), arrays indexed [z, y, x]."""

    hu: npt.NDArray[np.float32]
    spacing_m: tuple[float, float, float]
    origin_m: npt.NDArray[np.float64]
    direction: npt.NDArray[np.float64]
    source: str = ""

    def index_to_world(self, ijk: npt.NDArray[np.float64]) -> npt.NDArray[np.float64]:
        """World positions (m) of (x, y, z) array indices (N, 3)."""
        return self.origin_m + (ijk * np.asarray(self.spacing_m)) @ self.direction.T


def _unit(v: npt.ArrayLike) -> npt.NDArray[np.float64]:
    a = np.asarray(v, dtype=np.float64)
    return a / np.linalg.norm(a)


def load_dicom(path: str | os.PathLike[str], series_uid: str | None = None) -> CTImage:
    """Reads a DICOM CT series from a folder (or a single-slice file).

    Slices are ordered by their position along the slice normal; the spacing between slices comes
    from those positions (or SliceThickness for a single slice). Raises :class:`CTImportError` for
    files that are not DICOM images, several series without ``series_uid``, or uneven spacing.
    """
    import pydicom
    from pydicom.errors import InvalidDicomError

    p = Path(path)
    files = sorted(f for f in p.rglob("*") if f.is_file()) if p.is_dir() else [p]
    if not files or not p.exists():
        raise CTImportError(f"{p}: no such file or folder, or it is empty")
    slices = []
    for f in files:
        try:
            ds = pydicom.dcmread(f, force=False)
        except (InvalidDicomError, OSError, EOFError, ValueError) as exc:
            if p.is_dir():
                continue  # folders often hold DICOMDIR, notes, thumbnails
            raise CTImportError(f"{f}: not a DICOM file ({exc})") from None
        if "PixelData" not in ds:
            continue
        slices.append(ds)
    if not slices:
        raise CTImportError(f"{p}: no DICOM image slices found")
    uids = sorted({str(getattr(ds, "SeriesInstanceUID", "")) for ds in slices})
    if series_uid is not None:
        slices = [ds for ds in slices if str(getattr(ds, "SeriesInstanceUID", "")) == series_uid]
        if not slices:
            raise CTImportError(f"{p}: no slice of series {series_uid}; series present: {uids}")
    elif len(uids) > 1:
        raise CTImportError(f"{p}: {len(uids)} series found, choose one with series_uid: {uids}")
    modality = str(getattr(slices[0], "Modality", "CT"))
    if modality != "CT":
        raise CTImportError(f"{p}: modality is {modality!r}, expected 'CT'")

    try:
        iop = np.asarray(slices[0].ImageOrientationPatient, dtype=np.float64)
        row_dir, col_dir = _unit(iop[:3]), _unit(iop[3:])
        normal = np.cross(row_dir, col_dir)
        positions = [np.asarray(ds.ImagePositionPatient, dtype=np.float64) for ds in slices]
        order = np.argsort([pos @ normal for pos in positions])
        slices = [slices[i] for i in order]
        positions = [positions[i] for i in order]
        ps = [float(v) for v in slices[0].PixelSpacing]  # (row spacing, column spacing) in mm
        images = []
        for ds in slices:
            arr = ds.pixel_array.astype(np.float32)
            arr = arr * float(getattr(ds, "RescaleSlope", 1.0)) + float(getattr(ds, "RescaleIntercept", 0.0))
            images.append(arr)
    except (AttributeError, KeyError, ValueError, TypeError) as exc:
        raise CTImportError(f"{p}: incomplete CT headers or pixel data ({exc})") from None
    if len({im.shape for im in images}) != 1:
        raise CTImportError(f"{p}: slices have different sizes {sorted({im.shape for im in images})}")
    if len(slices) > 1:
        gaps = np.diff([pos @ normal for pos in positions])
        if np.any(gaps <= 1e-6):
            raise CTImportError(f"{p}: two slices share a position; is this a multi-phase series?")
        dz = float(np.median(gaps))
        if np.max(np.abs(gaps - dz)) > 0.01 * dz + 1e-3:
            raise CTImportError(f"{p}: uneven slice spacing {gaps.min():.3f}–{gaps.max():.3f} mm")
    else:
        dz = float(getattr(slices[0], "SpacingBetweenSlices", 0) or getattr(slices[0], "SliceThickness", 0) or 1.0)
    hu = np.stack(images, axis=0)
    direction = np.stack([row_dir, col_dir, normal], axis=1)
    mm = 1e-3
    return CTImage(
        hu=np.ascontiguousarray(hu, dtype=np.float32),
        spacing_m=(ps[1] * mm, ps[0] * mm, dz * mm),
        origin_m=positions[0] * mm,
        direction=direction,
        source=str(p),
    )


def load_nifti(path: str | os.PathLike[str]) -> CTImage:
    """Reads a NIfTI CT (values taken as HU after the file's scaling). The RAS affine is converted
    to LPS; a left-handed voxel order is flipped so the orientation is a proper rotation."""
    import nibabel as nib
    from nibabel.spatialimages import SpatialImage

    p = Path(path)
    try:
        img = nib.load(str(p))
        if not isinstance(img, SpatialImage):
            raise TypeError(f"a {type(img).__name__} has no voxel grid")
        data = np.asarray(img.get_fdata(dtype=np.float32))
        affine = np.asarray(img.affine, dtype=np.float64)
    except FileNotFoundError:
        raise CTImportError(f"{p}: no such file") from None
    except Exception as exc:  # nibabel raises many types for damaged files
        raise CTImportError(f"{p}: not a readable NIfTI image ({exc})") from None
    if data.ndim == 4 and data.shape[3] == 1:
        data = data[..., 0]
    if data.ndim != 3:
        raise CTImportError(f"{p}: expected a 3-D image, got shape {data.shape}")
    lps = np.diag([-1.0, -1.0, 1.0]) @ affine[:3, :3]
    origin = np.diag([-1.0, -1.0, 1.0]) @ affine[:3, 3]
    spacing = np.linalg.norm(lps, axis=0)
    if np.any(spacing <= 0) or not np.all(np.isfinite(lps)):
        raise CTImportError(f"{p}: degenerate affine {affine.tolist()}")
    direction = lps / spacing
    if np.linalg.det(direction) < 0:
        # Flip the first voxel axis: reverse the data along it and move the origin to its far end.
        origin = origin + direction[:, 0] * spacing[0] * (data.shape[0] - 1)
        direction[:, 0] *= -1
        data = data[::-1]
    hu = np.ascontiguousarray(np.transpose(data, (2, 1, 0)), dtype=np.float32)  # (i,j,k) → [z,y,x]
    mm_to_m = 1e-3
    sx, sy, sz = (float(s) * mm_to_m for s in spacing)
    return CTImage(hu, (sx, sy, sz), origin * mm_to_m, direction, str(p))


def load(path: str | os.PathLike[str]) -> CTImage:
    """Reads a CT: NIfTI for ``.nii``/``.nii.gz``, otherwise DICOM (a folder or a file)."""
    name = str(path).lower()
    if name.endswith((".nii", ".nii.gz")):
        return load_nifti(path)
    return load_dicom(path)


def resample_isotropic(ct: CTImage, voxel_m: float = 0.5e-3, order: int = 1) -> CTImage:
    """Resamples onto an axis-aligned (identity orientation, LPS) grid of ``voxel_m`` (m) voxels
    covering the image's extent. Outside the source reads as air."""
    if not (np.isfinite(voxel_m) and voxel_m > 0):
        raise InvalidInputError(f"voxel_m must be > 0, got {voxel_m}")
    nz, ny, nx = ct.hu.shape
    corners = np.array([[i, j, k] for i in (0, nx - 1) for j in (0, ny - 1) for k in (0, nz - 1)], float)
    world = ct.index_to_world(corners)
    lo, hi = world.min(axis=0), world.max(axis=0)
    n_out = np.maximum(1, np.floor((hi - lo) / voxel_m + 1e-6).astype(int) + 1)
    if np.prod(n_out) > 400_000_000:
        raise InvalidInputError(f"resampling to {voxel_m * 1e3} mm gives {n_out.tolist()} voxels; crop first")
    if np.allclose(ct.direction, np.eye(3)) and np.allclose(ct.spacing_m, voxel_m, rtol=1e-6):
        return ct
    # Output voxel (x, y, z) index → source continuous index, as an affine map per axis.
    to_src = np.linalg.inv(ct.direction * np.asarray(ct.spacing_m))  # world offset → source ijk
    m = to_src * voxel_m  # output ijk → source ijk (linear part)
    offset = to_src @ (lo - ct.origin_m)
    # ndimage works in array order [z, y, x]: permute the matrix accordingly.
    perm = [2, 1, 0]
    matrix = m[np.ix_(perm, perm)]
    hu = ndimage.affine_transform(
        ct.hu, matrix, offset=offset[perm], output_shape=tuple(n_out[perm]), order=order, mode="constant", cval=AIR_HU
    )
    return CTImage(hu.astype(np.float32), (voxel_m,) * 3, lo, np.eye(3), ct.source)


def crop(ct: CTImage, lo_m: npt.ArrayLike, hi_m: npt.ArrayLike) -> CTImage:
    """Keeps the voxels whose centres lie in the world box [lo_m, hi_m] (m). Axis-aligned images
    only (resample first)."""
    if not np.allclose(ct.direction, np.eye(3)):
        raise InvalidInputError("crop needs an axis-aligned image; call resample_isotropic first")
    lo, hi = np.asarray(lo_m, float), np.asarray(hi_m, float)
    if lo.shape != (3,) or hi.shape != (3,) or np.any(hi <= lo) or not np.all(np.isfinite([lo, hi])):
        raise InvalidInputError(
            f"crop box must be two finite 3-D corners with lo < hi, got {lo.tolist()} and {hi.tolist()}"
        )
    sp = np.asarray(ct.spacing_m)
    start = np.maximum(0, np.ceil((lo - ct.origin_m) / sp - 1e-9)).astype(int)
    stop = np.minimum(np.array(ct.hu.shape[::-1]), np.floor((hi - ct.origin_m) / sp + 1e-9).astype(int) + 1)
    if np.any(stop <= start):
        raise InvalidInputError(f"crop box {lo.tolist()}–{hi.tolist()} m does not overlap the image")
    hu = ct.hu[start[2] : stop[2], start[1] : stop[1], start[0] : stop[0]]
    return CTImage(np.ascontiguousarray(hu), ct.spacing_m, ct.origin_m + start * sp, ct.direction, ct.source)


def segment(hu: npt.NDArray[np.floating], mapping: HuMapping | None = None) -> npt.NDArray[np.uint8]:
    """Layer ids from HU: cortical above ``cortical_min_hu``, cancellous from ``cancellous_min_hu``;
    marrow where softer tissue is enclosed by bone within an axial slice; the rest outside."""
    m = mapping or HuMapping()
    labels = m.threshold_layers(hu)
    bone = labels != Layer.OUTSIDE
    for k in range(hu.shape[0]):
        enclosed = ndimage.binary_fill_holes(bone[k]) & ~bone[k]
        labels[k][enclosed] = Layer.MARROW
    return labels


def prepare(
    path: str | os.PathLike[str],
    voxel_m: float = 0.5e-3,
    crop_m: tuple[npt.ArrayLike, npt.ArrayLike] | None = None,
    mapping: HuMapping | None = None,
    labels: npt.ArrayLike | None = None,
) -> Volume:
    """Reads a CT (:func:`load`), resamples to ``voxel_m`` (m) isotropic voxels, crops to
    ``crop_m = (lo, hi)`` (m, world) if given, segments (or uses ``labels``, which must match the
    final shape) and returns the :class:`Volume`."""
    ct = resample_isotropic(load(path), voxel_m)
    if crop_m is not None:
        ct = crop(ct, crop_m[0], crop_m[1])
    lab = segment(ct.hu, mapping) if labels is None else labels
    meta = {"source": ct.source, "voxel_m": float(voxel_m)}
    return Volume.from_hu(ct.hu, ct.spacing_m, ct.origin_m, ct.direction, labels=lab, mapping=mapping, meta=meta)
