"""The embedded default: a procedural CT of a right proximal femur, in Hounsfield units.

Anatomy (world frame LPS, mm in this file's constants, metres everywhere in the API):
- shaft along z with a medullary (marrow) canal that tapers out in the metaphysis;
- neck at a 129° neck–shaft angle with 12° anteversion, femoral head of radius 23.5 mm
  (adult femoral heads are 22–25 mm in radius);
- greater and lesser trochanters;
- a cortical shell that is thick along the shaft (4.5 mm) and thin at the head (1 mm);
- cancellous bone whose density rises towards the head, with a trabecular-like texture;
- a necrotic lesion in the head: a sclerotic rim (~900 HU) around a lucent core (~60 HU);
- soft tissue (30 HU) filling the rest of the field of view.

The default task is hip pinning: a straight path from an entry point A on the lateral cortex
below the greater trochanter, along the neck axis, to a target B 6 mm below the head's surface,
crossing cortical → cancellous → marrow → cancellous → necrosis → cancellous bone.

The anatomy is fixed; the seed changes the trabecular texture and the CT noise.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import lru_cache
from typing import Any

import numpy as np
import numpy.typing as npt

from dhg.core.errors import InvalidInputError
from dhg.core.layers import Layer
from dhg.core.path import PlannedPath
from dhg.core.volume import HuMapping, Volume

__all__ = ["Phantom", "default_phantom", "femur", "femur_arrays"]

# Anatomy, in mm (LPS: +x patient left = medial for a right femur, +y posterior, +z superior).
# Where a value has a published counterpart it is cited; the rest are the phantom's own choices,
# said so (docs/fidelity.md, "The phantom's anatomy").
NECK_SHAFT_ANGLE_DEG = 129.0
"""The mean angle of inclination, 129.2°, of Toogood, Skalak & Cooperman 2009's normal femora."""
ANTEVERSION_DEG = 12.0
"""The phantom's choice, a little above the mean version of 9.7° of the same femora (Toogood et al.
2009); reported means run to 14.5° in other CT series."""
NECK_BASE_MM = np.array([0.0, 0.0, 60.0])  # where the neck axis meets the shaft axis
NECK_LENGTH_MM = 50.0
"""Neck base to head centre: the phantom's choice (published neck lengths depend on how they are
measured)."""
HEAD_RADIUS_MM = 23.5
"""Between the mean head radii of female and male adolescents' CT, 21.9 and 24.5 mm (Jamali et al.,
Clin Orthop Relat Res, "What is normal femoral head/neck anatomy?")."""
SHAFT_RADIUS_MM = 13.5
"""27 mm across: a little above the mean mid-shaft widths of 25.6 (women) and 26.5 mm (men)
(Karakaş & Harma 2008)."""
CANAL_RADIUS_MM = 7.0
"""The phantom's choice, wider than the isthmus' mean diameter in CT (about 10.5 mm); with the 4.5 mm
cortex it leaves a ring of cancellous bone around the canal, which real diaphyses lack."""
LESION_CORE_MM = 6.0
LESION_RIM_MM = 1.8
"""The necrotic lesion's core radius and sclerotic rim: illustrative, the phantom's choice."""
TARGET_DEPTH_BELOW_SURFACE_MM = 6.0
FIELD_OF_VIEW_MM = ((-31.0, 68.0), (-38.0, 24.0), (-2.0, 121.0))
SOFT_TISSUE_HU = 30.0
"""The phantom's choice for the tissue around the bone (no source found)."""


def neck_axis() -> npt.NDArray[np.float64]:
    """Unit vector of the neck axis, from the shaft towards the head."""
    tilt = np.radians(180.0 - NECK_SHAFT_ANGLE_DEG)
    av = np.radians(ANTEVERSION_DEG)
    # Medial (+x), anterior (−y) and superior (+z).
    return np.array([np.sin(tilt) * np.cos(av), -np.sin(tilt) * np.sin(av), np.cos(tilt)])


def head_center_mm() -> npt.NDArray[np.float64]:
    """Centre of the femoral head (mm)."""
    return NECK_BASE_MM + NECK_LENGTH_MM * neck_axis()


def lesion_center_mm() -> npt.NDArray[np.float64]:
    """Centre of the necrotic lesion (mm): anterosuperior head, on the pinning path."""
    return head_center_mm() + 6.0 * neck_axis() + np.array([0.0, -1.5, 1.5])


def _smin(a: np.ndarray, b: np.ndarray, k: float) -> np.ndarray:
    """Polynomial smooth minimum (a smooth union of two signed distance fields), blend k mm."""
    h = np.clip(0.5 + 0.5 * (b - a) / k, 0.0, 1.0)
    return b * (1 - h) + a * h - k * h * (1 - h)


def _ellipsoid(x, y, z, c, r) -> np.ndarray:
    """Approximate signed distance (mm) to an axis-aligned ellipsoid."""
    q = np.sqrt(((x - c[0]) / r[0]) ** 2 + ((y - c[1]) / r[1]) ** 2 + ((z - c[2]) / r[2]) ** 2)
    return (q - 1.0) * min(r)


def _bone_sdf(x, y, z) -> np.ndarray:
    """Signed distance (mm, negative inside) of the femur surface; x, y, z broadcastable."""
    f32 = np.float32
    # Shaft: a cylinder that flares into the metaphysis and stops at the neck.
    r_shaft = SHAFT_RADIUS_MM + np.maximum(0.0, z - 45.0) * 0.15
    shaft = np.maximum(np.sqrt(x**2 + y**2) - r_shaft, z - 74.0).astype(f32)
    # Neck: a round cone from the shaft axis to the head centre, radius 15 → 13 mm.
    a, d = NECK_BASE_MM, neck_axis()
    t = np.clip((x - a[0]) * d[0] + (y - a[1]) * d[1] + (z - a[2]) * d[2], 0.0, NECK_LENGTH_MM)
    px, py, pz = x - (a[0] + t * d[0]), y - (a[1] + t * d[1]), z - (a[2] + t * d[2])
    neck = (np.sqrt(px**2 + py**2 + pz**2) - (15.0 - 2.0 * t / NECK_LENGTH_MM)).astype(f32)
    h = head_center_mm()
    head = (np.sqrt((x - h[0]) ** 2 + (y - h[1]) ** 2 + (z - h[2]) ** 2) - HEAD_RADIUS_MM).astype(f32)
    greater = _ellipsoid(x, y, z, (-11.0, 4.0, 79.0), (12.0, 13.0, 16.0)).astype(f32)
    lesser = _ellipsoid(x, y, z, (8.0, 10.0, 42.0), (7.0, 6.0, 8.0)).astype(f32)
    sdf = _smin(shaft, neck, 5.0)
    sdf = _smin(sdf, greater, 4.0)
    sdf = _smin(sdf, lesser, 3.0)
    return np.minimum(sdf, _smin(head, neck, 3.0))


def _cortical_thickness_mm(x, y, z) -> np.ndarray:
    """Cortical thickness (mm): 4.5 along the shaft, thinning to 1.8 in the metaphysis, 1.0 at the
    head. The phantom's choice: the trend is anatomy's, the millimetres have no source here."""
    t = np.interp(z, [35.0, 70.0], [4.5, 1.8])
    h = head_center_mm()
    near_head = np.sqrt((x - h[0]) ** 2 + (y - h[1]) ** 2 + (z - h[2]) ** 2) < HEAD_RADIUS_MM - 3.0
    return np.where(near_head, 1.0, t)


def _canal_radius_mm(z) -> np.ndarray:
    """Medullary canal radius (mm): full along the shaft, tapering out between z = 48 and 74 mm."""
    return CANAL_RADIUS_MM * np.clip((74.0 - z) / 26.0, 0.0, 1.0)


def _trabecular_texture(x, y, z, rng: np.random.Generator) -> np.ndarray:
    """Plate-like trabecular texture in [-1, 1]: a sum of plane waves of random orientation with
    wavelengths of 1.2–1.8 mm (trabecular spacing is ~0.5–2 mm)."""
    acc = np.zeros(np.broadcast(x, y, z).shape, dtype=np.float32)
    n_waves = 8
    for _ in range(n_waves):
        v = rng.normal(size=3)
        v /= np.linalg.norm(v)
        k = 2.0 * np.pi / rng.uniform(1.2, 1.8)
        acc += np.cos(k * (v[0] * x + v[1] * y + v[2] * z) + rng.uniform(0, 2 * np.pi)).astype(np.float32)
    return np.clip(acc / np.sqrt(n_waves / 2.0), -1.0, 1.0)


def femur_arrays(seed: int = 0, voxel_m: float = 0.5e-3) -> dict[str, Any]:
    """The phantom as plain arrays: ``hu`` (float32, (nz, ny, nx)), ``labels`` (uint8),
    ``spacing_m``, ``origin_m``, and the landmarks (m). Deterministic for a seed."""
    if not (np.isfinite(voxel_m) and 0.2e-3 <= voxel_m <= 4e-3):
        raise InvalidInputError(f"voxel_m must be within [0.2e-3, 4e-3] m, got {voxel_m}")
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise InvalidInputError(f"seed must be a whole number >= 0, got {seed!r}")
    rng = np.random.default_rng(seed)
    h_mm = voxel_m * 1e3
    axes = [np.arange(lo, hi + 1e-9, h_mm, dtype=np.float64) for lo, hi in FIELD_OF_VIEW_MM]
    x = axes[0][None, None, :]
    y = axes[1][None, :, None]
    z = axes[2][:, None, None]
    shape = (axes[2].size, axes[1].size, axes[0].size)

    sdf = _bone_sdf(x, y, z)
    inside = sdf < 0.0
    cortical = inside & (sdf > -_cortical_thickness_mm(x, y, z))
    canal = (np.sqrt(x**2 + y**2) < _canal_radius_mm(z)) & np.broadcast_to(True, shape)
    marrow = inside & ~cortical & canal
    lc = lesion_center_mm()
    r_lesion = np.sqrt((x - lc[0]) ** 2 + (y - lc[1]) ** 2 + (z - lc[2]) ** 2)
    lesion = inside & ~cortical & (r_lesion < LESION_CORE_MM + LESION_RIM_MM)
    cancellous = inside & ~cortical & ~marrow & ~lesion

    labels = np.zeros(shape, dtype=np.uint8)
    labels[cortical] = Layer.CORTICAL
    labels[cancellous] = Layer.CANCELLOUS
    labels[marrow & ~lesion] = Layer.MARROW
    labels[lesion] = Layer.NECROSIS

    hu = np.full(shape, SOFT_TISSUE_HU, dtype=np.float32)
    # Cortical bone: denser where the shell is thick (the shaft). 1500-1850 HU lies within bone's
    # 700-3000 HU in CT reference tables (Buzug 2008, as Radclass tabulates it); the values are the
    # phantom's choice. Cancellous
    # bone below, 160-690 HU, and marrow, -30 HU (fatty marrow is below 115 HU: Suchacki et al.
    # 2020), likewise.
    zz = np.broadcast_to(z, shape)
    hu[cortical] = np.interp(zz[cortical], [35.0, 70.0], [1850.0, 1500.0])
    # Cancellous: denser towards the head (principal compressive trabeculae), textured.
    hc = head_center_mm()
    ci = np.nonzero(cancellous)
    cx, cy, cz = axes[0][ci[2]], axes[1][ci[1]], axes[2][ci[0]]
    near_head = np.exp(-((cx - hc[0]) ** 2 + (cy - hc[1]) ** 2 + (cz - hc[2]) ** 2) / (2 * 20.0**2))
    texture = _trabecular_texture(cx, cy, cz, rng)
    hu[ci] = np.clip(260.0 + 220.0 * near_head + 140.0 * texture, 160.0, 690.0)
    hu[labels == Layer.MARROW] = -30.0
    core = lesion & (r_lesion < LESION_CORE_MM)
    hu[lesion] = 900.0
    hu[core] = 60.0
    # CT noise.
    hu += rng.normal(0.0, 15.0, size=shape).astype(np.float32)

    # The task: B is 6 mm below the head's surface on the neck axis; A is where the axis, followed
    # back laterally, meets the outer surface of the lateral cortex.
    d = neck_axis()
    target_mm = hc + (HEAD_RADIUS_MM - TARGET_DEPTH_BELOW_SURFACE_MM) * d
    s = np.arange(0.0, 80.0, 0.05)
    line = NECK_BASE_MM[None, :] - s[:, None] * d[None, :]
    line_sdf = _bone_sdf(line[:, 0], line[:, 1], line[:, 2])
    outside = np.nonzero(line_sdf >= 0.0)[0]
    entry_mm = line[outside[0]] if outside.size else line[-1]

    mm = 1e-3
    return {
        "hu": hu,
        "labels": labels,
        "spacing_m": (voxel_m, voxel_m, voxel_m),
        "origin_m": tuple(float(a[0]) * mm for a in axes),
        "entry_m": entry_mm * mm,
        "target_m": target_mm * mm,
        "landmarks_m": {
            "head_center": (hc * mm).tolist(),
            "head_radius": HEAD_RADIUS_MM * mm,
            "neck_base": (NECK_BASE_MM * mm).tolist(),
            "neck_axis": d.tolist(),
            "lesion_center": (lc * mm).tolist(),
            "lesion_radius": (LESION_CORE_MM + LESION_RIM_MM) * mm,
        },
    }


@dataclass(frozen=True)
class Phantom:
    """The phantom femur: its volume, the default planned path and anatomical landmarks (m)."""

    volume: Volume
    path: PlannedPath
    landmarks_m: dict[str, Any] = field(default_factory=dict)
    seed: int = 0


def femur(seed: int = 0, voxel_m: float = 0.5e-3, mapping: HuMapping | None = None) -> Phantom:
    """Builds the phantom femur CT at ``voxel_m`` (m) isotropic voxels (default 0.5 mm).

    Deterministic for a seed (which changes the trabecular texture and CT noise, not the anatomy).
    """
    arrays = femur_arrays(seed, voxel_m)
    path = PlannedPath(arrays["entry_m"], arrays["target_m"])
    meta = {
        "source": "dhg.bone.phantom.femur",
        "seed": int(seed),
        "voxel_m": float(voxel_m),
        "planned_path": path.to_dict(),
        "landmarks_m": arrays["landmarks_m"],
    }
    volume = Volume.from_hu(
        arrays["hu"],
        arrays["spacing_m"],
        arrays["origin_m"],
        labels=arrays["labels"],
        mapping=mapping,
        meta=meta,
    )
    return Phantom(volume, path, arrays["landmarks_m"], int(seed))


def default_phantom(seed: int = 0, voxel_m: float = 0.5e-3) -> Phantom:
    """The embedded default phantom, built once per process and shared (volumes are immutable):
    the same (seed, voxel size) gives the same instance however the arguments are passed."""
    return _shared_phantom(int(seed), float(voxel_m))


@lru_cache(maxsize=4)
def _shared_phantom(seed: int, voxel_m: float) -> Phantom:
    return femur(seed, voxel_m)
