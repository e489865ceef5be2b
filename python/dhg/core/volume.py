"""Bone volumes: the shared pristine CT volume and a session's drilled copy of it.

Units are SI: positions in metres in the world frame (LPS, see ``docs/frames.md``), densities in
kg/m³, durations in seconds. Arrays are indexed ``[k, j, i]`` = ``[z, y, x]`` (x fastest).
"""

from __future__ import annotations

import json
import os
import tempfile
import zipfile
from collections.abc import Sequence
from dataclasses import asdict, dataclass, fields
from pathlib import Path
from typing import Any, Literal

import numpy as np
import numpy.typing as npt

from dhg import _bone_sim
from dhg.core.errors import InvalidInputError, ShapeError, VolumeFileError

__all__ = [
    "BRICK_EDGE",
    "FULL_MATERIAL",
    "HU_MIN",
    "VIEW_NAMES",
    "DrilledVolume",
    "HuMapping",
    "RemovalReport",
    "Volume",
    "XRayViews",
]

VIEW_NAMES: tuple[str, ...] = tuple(_bone_sim.XRAY_VIEWS)
"""The three X-ray views, in the core's order (``bone_sim::xray::View``): top, front, side."""
HU_MIN: float = float(_bone_sim.HU_MIN)
"""The lowest HU the core stores (air)."""
BRICK_EDGE: int = _bone_sim.BRICK_EDGE
"""Voxels along a drilled brick's edge."""
FULL_MATERIAL: int = _bone_sim.FULL_MATERIAL
"""The core's material fraction 1 (``u16``)."""

VOLUME_FILE_FORMAT = "dhg-volume"
VOLUME_FILE_VERSION = 1

Interp = Literal["nearest", "linear"]


_MAPPING: dict[str, float] = _bone_sim.defaults()["hu_mapping"]
"""The core's ``HuMapping::default()``: the one place the defaults below are defined."""


@dataclass(frozen=True)
class HuMapping:
    """HU → density → stiffness/erodibility/attenuation mapping (see the Rust ``HuMapping``).

    Defaults: cortical > 700 HU, cancellous 150–700 HU; apparent density ρ = a + b·HU
    (a = 0 kg/m³, b = 1 kg/m³ per HU); modulus E = 6850·ρ^1.49 MPa with ρ in g/cm³
    (Morgan, Bayraktar & Keaveny 2003, femoral neck); erosion ∝ 1/E, 2.5 /s for
    ρ = 1850 kg/m³ at 1000 rpm; water attenuation 19.3 /m (NIST XCOM, 70 keV).
    """

    cortical_min_hu: float = _MAPPING["cortical_min_hu"]
    cancellous_min_hu: float = _MAPPING["cancellous_min_hu"]
    density_intercept_kg_m3: float = _MAPPING["density_intercept_kg_m3"]
    density_slope_kg_m3_per_hu: float = _MAPPING["density_slope_kg_m3_per_hu"]
    min_bone_density_kg_m3: float = _MAPPING["min_bone_density_kg_m3"]
    marrow_density_kg_m3: float = _MAPPING["marrow_density_kg_m3"]
    marrow_cutting_density_kg_m3: float = _MAPPING["marrow_cutting_density_kg_m3"]
    modulus_coeff_pa: float = _MAPPING["modulus_coeff_pa"]
    modulus_exponent: float = _MAPPING["modulus_exponent"]
    erosion_reference_density_kg_m3: float = _MAPPING["erosion_reference_density_kg_m3"]
    erosion_rate_ref_per_s: float = _MAPPING["erosion_rate_ref_per_s"]
    erosion_reference_rpm: float = _MAPPING["erosion_reference_rpm"]
    erosion_speed_exponent: float = _MAPPING["erosion_speed_exponent"]
    marrow_erosion_rate_per_s: float = _MAPPING["marrow_erosion_rate_per_s"]
    max_erosion_rate_per_s: float = _MAPPING["max_erosion_rate_per_s"]
    water_attenuation_per_m: float = _MAPPING["water_attenuation_per_m"]

    def to_dict(self) -> dict[str, float]:
        """The mapping as a plain dict (what the native core and volume files take)."""
        return {k: float(v) for k, v in asdict(self).items()}

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> HuMapping:
        """Builds a mapping from a dict; unknown keys are an :class:`InvalidInputError`."""
        known = {f.name for f in fields(cls)}
        unknown = sorted(set(d) - known)
        if unknown:
            raise InvalidInputError(f"unknown HU mapping keys {unknown}; known keys are {sorted(known)}")
        return cls(**{k: float(v) for k, v in d.items()})

    def threshold_layers(self, hu: npt.ArrayLike) -> npt.NDArray[np.uint8]:
        """Layer ids (nz, ny, nx) of HU values by threshold alone, as the core assigns them to a
        volume without labels: cortical above ``cortical_min_hu``, cancellous from
        ``cancellous_min_hu``, outside below (marrow and necrosis need anatomy)."""
        a = np.asarray(hu, dtype=np.float32)
        if a.ndim != 3:
            raise ShapeError(f"HU must be (nz, ny, nx), got shape {a.shape}")
        return _bone_sim.threshold_layers(np.ascontiguousarray(a), self.to_dict())


@dataclass(frozen=True)
class RemovalReport:
    """What a removal call did."""

    voxels_eroded: int
    """Voxels inside the burr that held material and were eroded."""
    voxels_removed: int
    """Voxels whose material reached zero."""
    mass_removed_kg: float
    """Mass removed (kg)."""
    volume_removed_m3: float
    """Material volume removed (m³)."""


@dataclass(frozen=True)
class XRayViews:
    """X-ray line integrals ∫μ dl (dimensionless) along the volume's three axes.

    ``top`` is along z (rows y, columns x), ``front`` along y (rows z, columns x), ``side`` along x
    (rows z, columns y); row and column 0 are the lowest index. See ``docs/frames.md``.
    """

    top: npt.NDArray[np.float32]
    front: npt.NDArray[np.float32]
    side: npt.NDArray[np.float32]

    def as_dict(self) -> dict[str, npt.NDArray[np.float32]]:
        """``{"top": ..., "front": ..., "side": ...}``."""
        return {"top": self.top, "front": self.front, "side": self.side}


def _triple(value: npt.ArrayLike, what: str) -> tuple[float, float, float]:
    arr = np.asarray(value, dtype=np.float64)
    if arr.shape != (3,):
        raise ShapeError(f"{what} must have 3 components, got shape {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise InvalidInputError(f"{what} must be finite, got {arr.tolist()}")
    return (float(arr[0]), float(arr[1]), float(arr[2]))


def as_points(points_m: npt.ArrayLike, what: str = "points_m") -> npt.NDArray[np.float64]:
    """Coerces one point (3,) or many (N, 3) to a C-contiguous float64 (N, 3) array (m)."""
    try:
        arr = np.asarray(points_m, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise TypeError(f"{what} must be numeric coordinates in metres: {exc}") from None
    if arr.ndim == 1:
        arr = arr.reshape(1, -1)
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise ShapeError(f"{what} must have shape (3,) or (N, 3), got {np.shape(points_m)}")
    return np.ascontiguousarray(arr)


def _one_point(point_m: npt.ArrayLike, what: str) -> tuple[float, float, float]:
    """Coerces one world point (3,) in metres to a tuple."""
    arr = as_points(point_m, what)
    if len(arr) != 1:
        raise ShapeError(f"{what} must be one point of shape (3,), got {np.shape(point_m)}")
    return (float(arr[0, 0]), float(arr[0, 1]), float(arr[0, 2]))


def _numeric_3d(array: npt.ArrayLike, what: str) -> np.ndarray:
    arr = np.asarray(array)
    if arr.dtype == object or not (np.issubdtype(arr.dtype, np.number) or arr.dtype == bool):
        raise TypeError(f"{what} must be a numeric array, got dtype {arr.dtype}")
    if arr.ndim != 3:
        raise ShapeError(f"{what} must be 3-D (nz, ny, nx), got shape {arr.shape}")
    if arr.size == 0:
        raise ShapeError(f"{what} must not be empty, got shape {arr.shape}")
    return arr


class Volume:
    """A CT bone volume: geometry, per-voxel layer labels and HU, shared by all drilling sessions.

    Build one with :meth:`from_hu`, :func:`dhg.bone.phantom.femur`, :func:`dhg.bone.ct.prepare` or
    :meth:`load`. Immutable; :meth:`drill` gives a session's private, drillable copy.
    """

    def __init__(self, native: _bone_sim.Volume, meta: dict[str, Any] | None = None) -> None:
        if not isinstance(native, _bone_sim.Volume):
            raise InvalidInputError(
                f"Volume(...) wraps the core's volume; build one from HU with Volume.from_hu(hu, spacing_m), "
                f"got {type(native).__name__}"
            )
        self._vol = native
        self.meta: dict[str, Any] = dict(meta or {})
        """Free-form provenance (source file, phantom seed, ...); saved with the volume."""

    @classmethod
    def from_hu(
        cls,
        hu: npt.ArrayLike,
        spacing_m: npt.ArrayLike,
        origin_m: npt.ArrayLike = (0.0, 0.0, 0.0),
        direction: npt.ArrayLike | None = None,
        labels: npt.ArrayLike | None = None,
        mapping: HuMapping | None = None,
        meta: dict[str, Any] | None = None,
    ) -> Volume:
        """Builds a volume from an HU array of shape (nz, ny, nx).

        Args:
            hu: Hounsfield units, any numeric dtype; NaN/inf is an error. Stored as int16, clamped
                to [-1024, 3071].
            spacing_m: voxel size along x, y, z (m), each > 0.
            origin_m: world position (m) of voxel [0, 0, 0]'s centre.
            direction: 3×3 rotation whose columns are the world directions of the x, y, z array
                axes (identity if omitted).
            labels: optional layer ids (see :class:`dhg.Layer`), same shape; without them layers
                come from the mapping's HU thresholds.
            mapping: the HU mapping (defaults: :class:`HuMapping`).
            meta: provenance to keep with the volume.
        """
        hu_arr = _numeric_3d(hu, "hu")
        hu32 = np.ascontiguousarray(hu_arr, dtype=np.float32)
        spacing = _triple(spacing_m, "spacing_m")
        if min(spacing) <= 0:
            raise InvalidInputError(f"spacing_m must be > 0 along every axis, got {spacing}")
        origin = _triple(origin_m, "origin_m")
        dir_arr = np.eye(3) if direction is None else np.asarray(direction, dtype=np.float64)
        if dir_arr.shape != (3, 3):
            raise ShapeError(f"direction must be 3×3, got shape {dir_arr.shape}")
        lab = None
        if labels is not None:
            lab_arr = _numeric_3d(labels, "labels")
            if lab_arr.shape != hu_arr.shape:
                raise ShapeError(f"labels shape {lab_arr.shape} differs from hu shape {hu_arr.shape}")
            if not np.issubdtype(lab_arr.dtype, np.integer):
                raise TypeError(f"labels must be an integer array of layer ids, got dtype {lab_arr.dtype}")
            lo, hi = int(lab_arr.min()), int(lab_arr.max())
            if lo < 0 or hi >= len(_bone_sim.LAYER_NAMES):
                bad = lo if lo < 0 else hi
                raise InvalidInputError(
                    f"labels hold layer id {bad}; valid ids are 0..{len(_bone_sim.LAYER_NAMES) - 1} "
                    f"({', '.join(_bone_sim.LAYER_NAMES)})"
                )
            lab = np.ascontiguousarray(lab_arr, dtype=np.uint8)
        mapping = mapping or HuMapping()
        native = _bone_sim.Volume(
            hu32, spacing, origin, np.ascontiguousarray(dir_arr), labels=lab, mapping=mapping.to_dict()
        )
        return cls(native, meta)

    # -- geometry -------------------------------------------------------------------------------
    @property
    def shape(self) -> tuple[int, int, int]:
        """Array shape (nz, ny, nx)."""
        return self._vol.shape

    @property
    def spacing_m(self) -> tuple[float, float, float]:
        """Voxel size along x, y, z (m)."""
        return tuple(self._vol.spacing_m)  # type: ignore[return-value]

    @property
    def origin_m(self) -> npt.NDArray[np.float64]:
        """World position (m) of voxel [0, 0, 0]'s centre."""
        return np.array(self._vol.origin_m)

    @property
    def direction(self) -> npt.NDArray[np.float64]:
        """3×3 rotation: columns are the world directions of the x, y, z array axes."""
        return self._vol.direction

    @property
    def mapping(self) -> HuMapping:
        """The HU mapping in use."""
        return HuMapping.from_dict(self._vol.mapping)

    @property
    def memory_bytes(self) -> int:
        """Bytes the native volume holds (shared by every session)."""
        return self._vol.memory_bytes

    def world_to_index(self, points_m: npt.ArrayLike) -> npt.NDArray[np.float64]:
        """Continuous (x, y, z) array indices of world points (m), shape (N, 3)."""
        return self._vol.world_to_index(as_points(points_m))

    def index_to_world(self, ijk: npt.ArrayLike) -> npt.NDArray[np.float64]:
        """World positions (m) of continuous (x, y, z) array indices, shape (N, 3)."""
        idx = as_points(ijk, "ijk")
        return self.origin_m + (idx * np.asarray(self.spacing_m)) @ self.direction.T

    def bounds_m(self) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.float64]]:
        """World-frame (min, max) corners (m) of the voxel centres."""
        nz, ny, nx = self.shape
        corners = np.array([[i, j, k] for i in (0, nx - 1) for j in (0, ny - 1) for k in (0, nz - 1)], float)
        w = self.index_to_world(corners)
        return w.min(axis=0), w.max(axis=0)

    # -- contents -------------------------------------------------------------------------------
    def hu(self) -> npt.NDArray[np.int16]:
        """Copy of the stored HU, int16 (nz, ny, nx)."""
        return self._vol.hu()

    def labels(self) -> npt.NDArray[np.uint8]:
        """Copy of the layer ids, uint8 (nz, ny, nx)."""
        return self._vol.labels()

    def layer_at(self, points_m: npt.ArrayLike) -> npt.NDArray[np.uint8]:
        """Layer id at world points (m), nearest voxel; 0 outside the volume."""
        return self._vol.layer_at(as_points(points_m))

    def layer_runs(
        self, entry_m: npt.ArrayLike, target_m: npt.ArrayLike, step_m: float = _bone_sim.PLAN_STEP_M
    ) -> list[tuple[int, float, float]]:
        """The layers along the straight path entry → target (world points, m), sampled every
        ``step_m`` (m) from the entry and merged into runs: (layer id, depth of the run's first
        sample (m), depth of its last (m)). The server's session info reports the same runs."""
        a, b = _one_point(entry_m, "entry_m"), _one_point(target_m, "target_m")
        return self._vol.layer_runs(a, b, float(step_m))

    def hu_at(self, points_m: npt.ArrayLike, interp: Interp = "linear") -> npt.NDArray[np.float64]:
        """HU at world points (m); air (-1024) outside the volume."""
        return self._vol.hu_at(as_points(points_m), interp)

    def density_at(self, points_m: npt.ArrayLike, interp: Interp = "linear") -> npt.NDArray[np.float64]:
        """Apparent density (kg/m³) at world points (m); 0 outside bone."""
        return self._vol.density_at(as_points(points_m), interp)

    def xray(self) -> XRayViews:
        """X-ray line integrals of the undrilled volume."""
        return XRayViews(*self._vol.xray())

    def drill(self, reserve_bricks: int = _bone_sim.DEFAULT_RESERVED_BRICKS) -> DrilledVolume:
        """A new, undrilled session copy of this volume (copy-on-write; costs only what it drills)."""
        return DrilledVolume(self, reserve_bricks)

    # -- files ----------------------------------------------------------------------------------
    def save(self, path: str | os.PathLike[str]) -> Path:
        """Writes the volume to a prepared-volume file (``.npz``), atomically. Returns the path."""
        path = Path(path)
        header = {
            "format": VOLUME_FILE_FORMAT,
            "version": VOLUME_FILE_VERSION,
            "units": {"spacing": "m", "origin": "m", "hu": "HU"},
            "layout": "arrays indexed [z, y, x]; world frame LPS",
            "spacing_m": list(self.spacing_m),
            "origin_m": self.origin_m.tolist(),
            "direction": self.direction.tolist(),
            "mapping": self.mapping.to_dict(),
            "meta": self.meta,
        }
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
        try:
            with os.fdopen(fd, "wb") as fh:
                np.savez_compressed(fh, header=np.array(json.dumps(header)), hu=self.hu(), labels=self.labels())
            os.replace(tmp, path)
        except BaseException:
            Path(tmp).unlink(missing_ok=True)
            raise
        return path

    @classmethod
    def load(cls, path: str | os.PathLike[str]) -> Volume:
        """Reads a prepared-volume file written by :meth:`save`.

        Raises:
            VolumeFileError: missing, truncated or corrupt file, or another format/version.
        """
        path = Path(path)
        if not path.is_file():
            raise VolumeFileError(f"{path}: no such volume file")
        try:
            # Open the file ourselves: np.load leaks its handle when the zip is truncated.
            with open(path, "rb") as fh, np.load(fh, allow_pickle=False) as z:
                missing = {"header", "hu", "labels"} - set(z.files)
                if missing:
                    raise VolumeFileError(f"{path}: not a DHG volume file (missing {sorted(missing)})")
                header = json.loads(str(z["header"]))
                hu, labels = z["hu"], z["labels"]
        except VolumeFileError:
            raise
        except (OSError, ValueError, zipfile.BadZipFile, EOFError, KeyError) as exc:
            raise VolumeFileError(f"{path}: unreadable or corrupt volume file ({exc})") from None
        if header.get("format") != VOLUME_FILE_FORMAT:
            raise VolumeFileError(f"{path}: format {header.get('format')!r}, expected {VOLUME_FILE_FORMAT!r}")
        if header.get("version") != VOLUME_FILE_VERSION:
            raise VolumeFileError(
                f"{path}: volume file version {header.get('version')} is not supported "
                f"(this DHG reads version {VOLUME_FILE_VERSION})"
            )
        try:
            return cls.from_hu(
                hu,
                header["spacing_m"],
                header["origin_m"],
                header["direction"],
                labels=labels,
                mapping=HuMapping.from_dict(header["mapping"]),
                meta=header.get("meta", {}),
            )
        except (KeyError, InvalidInputError, TypeError) as exc:
            raise VolumeFileError(f"{path}: inconsistent volume file ({exc})") from None

    def __repr__(self) -> str:
        nz, ny, nx = self.shape
        mm = ", ".join(f"{s * 1e3:g}" for s in self.spacing_m)
        return f"Volume({nx}×{ny}×{nz} voxels of {mm} mm)"


class DrilledVolume:
    """One session's drilled copy of a shared :class:`Volume` (copy-on-write 8³ bricks)."""

    def __init__(self, volume: Volume, reserve_bricks: int = _bone_sim.DEFAULT_RESERVED_BRICKS) -> None:
        if int(reserve_bricks) < 0:
            raise InvalidInputError(f"reserve_bricks must be >= 0, got {reserve_bricks}")
        self.volume = volume
        """The shared pristine volume."""
        self._bone = _bone_sim.DrilledVolume(volume._vol, int(reserve_bricks))

    def remove(
        self,
        center_m: Sequence[float] | npt.ArrayLike,
        radius_m: float,
        spindle_rpm: float,
        dt_s: float,
        contact: float = 1.0,
    ) -> RemovalReport:
        """Erodes the material inside a spherical burr.

        Args:
            center_m: burr centre (m, world frame).
            radius_m: burr radius (m), in (0, 0.02].
            spindle_rpm: spindle speed (rpm); <= 0 cuts nothing.
            dt_s: duration of contact (s), >= 0.
            contact: fraction of full cutting engagement, 0..1.
        """
        c = as_points(center_m, "center_m")
        if c.shape[0] != 1:
            raise ShapeError(f"center_m must be one point (3,), got shape {np.shape(center_m)}")
        r = self._bone.remove(tuple(c[0]), float(radius_m), float(spindle_rpm), float(dt_s), float(contact))
        return RemovalReport(**r)

    def remove_along(
        self,
        centers_m: npt.ArrayLike,
        radius_m: float,
        spindle_rpm: float,
        dt_s: float,
        contact: float = 1.0,
    ) -> RemovalReport:
        """Runs :meth:`remove` at each of the (N, 3) centres (m) in order, ``dt_s`` each (the GIL is
        released). All centres are checked first: on a bad one nothing is removed."""
        r = self._bone.remove_along(
            as_points(centers_m, "centers_m"), float(radius_m), float(spindle_rpm), float(dt_s), float(contact)
        )
        return RemovalReport(**r)

    def material_at(self, points_m: npt.ArrayLike, interp: Interp = "nearest") -> npt.NDArray[np.float64]:
        """Material fraction left (0..1) at world points (m); 0 outside the volume."""
        return self._bone.material_at(as_points(points_m), interp)

    def layer_at(self, points_m: npt.ArrayLike) -> npt.NDArray[np.uint8]:
        """Current layer id at world points (m): 0 (outside) where the bone is drilled away."""
        return self._bone.layer_at(as_points(points_m))

    def material_grid(self) -> npt.NDArray[np.float32]:
        """Material fraction of every voxel, float32 (nz, ny, nx)."""
        return self._bone.material_grid()

    def xray(self) -> XRayViews:
        """X-ray line integrals of the bone as drilled (cost grows with what was drilled)."""
        return XRayViews(*self._bone.xray())

    def bricks(self) -> tuple[npt.NDArray[np.uint32], npt.NDArray[np.uint16]]:
        """The drilled bricks: origins (n, 3) voxel (i, j, k) and material (n, 8, 8, 8)
        [k][j][i], uint16 (65535 = full); every other voxel is pristine."""
        return self._bone.bricks()

    def reset(self) -> None:
        """Restores the undrilled bone (cost grows with what was drilled)."""
        self._bone.reset()

    @property
    def removed_mass_kg(self) -> float:
        """Total mass removed (kg)."""
        return self._bone.removed_mass_kg

    @property
    def removed_voxels(self) -> int:
        """Voxels fully removed."""
        return self._bone.removed_voxels

    @property
    def drilled_bricks(self) -> int:
        """8³ bricks this session has copied."""
        return self._bone.drilled_bricks

    @property
    def memory_bytes(self) -> int:
        """Bytes this session holds beyond the shared volume."""
        return self._bone.memory_bytes
