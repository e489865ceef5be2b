"""The bone's layer surfaces for the live view, marched in chunks so that drilling re-meshes only
the chunks whose bricks changed (never the whole volume per frame).

The volume is cut into cubes of :data:`CHUNK_EDGE` voxels. Each surface is the 0.5 iso-surface
of its layers' mask times the material left (1 pristine, 0 drilled out), marched per chunk by
scikit-image's marching cubes (Lewiner et al. 2003) over the chunk's voxels and the first plane
of the next chunk, so neighbouring chunks share their border vertices and the surface has no
cracks. The session's drilled bricks (8³ voxels, ``DrilledVolume.bricks``) replace the pristine
material where they exist; :meth:`LayerSurfaces.update` returns the chunks they touched. A
``step`` of 2 samples every second voxel (a quarter of the triangles) for volumes finer than the
screen needs: :func:`display_step`.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from dhg.core import volume as _core_volume
from dhg.core.layers import Layer

__all__ = ["CHUNK_EDGE", "DISPLAY_VOXEL_M", "SURFACES", "ChunkMesh", "LayerSurfaces", "Surface", "display_step"]

CHUNK_EDGE = 32
"""Voxels along a chunk's edge (4 bricks of 8): a drilled brick re-meshes one chunk, or up to 8
where it lies on chunk borders."""

DISPLAY_VOXEL_M = 1e-3
"""The finest sampling the live view draws (m): a 0.5 mm CT is marched every second voxel, which
keeps a femur near 100 000 triangles, few enough for a browser drawing in software."""


def display_step(spacing_m: Iterable[float]) -> int:
    """The marching step (voxels) for a volume of this spacing: :data:`DISPLAY_VOXEL_M` or finer."""
    return int(min(4, max(1, round(DISPLAY_VOXEL_M / max(spacing_m)))))


BRICK_EDGE: int = _core_volume.BRICK_EDGE
"""Voxels along a drilled brick's edge (from the core)."""

FULL_MATERIAL: int = _core_volume.FULL_MATERIAL
"""The core's material fraction 1 (``u16``)."""


@dataclass(frozen=True)
class Surface:
    """One drawn surface: the boundary of the voxels whose layer is in ``layers``."""

    name: str
    layers: frozenset[int]
    color: tuple[int, int, int]
    opacity: float


_BONE = frozenset({Layer.CORTICAL, Layer.CANCELLOUS, Layer.MARROW, Layer.NECROSIS})

SURFACES = (
    # The bone's outer surface, as cortex: semi-transparent so the inner layers and the drill show.
    Surface(
        "cortex", frozenset({Layer.CORTICAL, Layer.CANCELLOUS, Layer.MARROW, Layer.NECROSIS}), (233, 223, 196), 0.35
    ),
    # Inside the cortex: the cancellous bone (with the marrow canal it surrounds).
    Surface("cancellous", frozenset({Layer.CANCELLOUS, Layer.MARROW, Layer.NECROSIS}), (214, 160, 112), 0.7),
    Surface("necrosis", frozenset({Layer.NECROSIS}), (200, 40, 40), 1.0),
)
"""The layers drawn, outermost first (the paper's Figure 3: cortex, cancellous bone, lesion)."""


@dataclass(frozen=True)
class ChunkMesh:
    """One chunk's piece of one surface: vertices in world metres (n, 3) and triangles (m, 3).
    Empty arrays mean the chunk holds none of that surface (any earlier piece goes)."""

    surface: str
    chunk: tuple[int, int, int]
    vertices_m: npt.NDArray[np.float32]
    faces: npt.NDArray[np.uint32]

    @property
    def name(self) -> str:
        """A stable scene name: ``<surface>/<ci>_<cj>_<ck>``."""
        return f"{self.surface}/{self.chunk[0]}_{self.chunk[1]}_{self.chunk[2]}"


class LayerSurfaces:
    """The surfaces of one session's bone: the pristine labels (nz, ny, nx), the grid that puts
    voxel (i, j, k) in the world (``origin_m + direction @ (spacing_m * (i, j, k))``), and the
    drilled bricks applied so far."""

    def __init__(
        self,
        labels: npt.NDArray[np.uint8],
        spacing_m: Iterable[float],
        origin_m: Iterable[float],
        direction: npt.ArrayLike | None = None,
        surfaces: tuple[Surface, ...] = SURFACES,
        step: int = 1,
    ) -> None:
        labels = np.asarray(labels)
        if not (isinstance(step, int) and 1 <= step <= 4):
            raise ValueError(f"step must be 1, 2, 3 or 4 voxels, got {step!r}")
        self.step = step
        if labels.ndim != 3 or labels.dtype != np.uint8 or min(labels.shape) < 2:
            raise ValueError(f"labels must be a 3D uint8 array of at least 2 voxels a side, got {labels.shape}")
        self.shape = labels.shape  # (nz, ny, nx)
        self.spacing_m = np.asarray(list(spacing_m), dtype=np.float64)
        self.origin_m = np.asarray(list(origin_m), dtype=np.float64)
        self.direction = np.eye(3) if direction is None else np.asarray(direction, dtype=np.float64)
        if self.spacing_m.shape != (3,) or self.origin_m.shape != (3,) or self.direction.shape != (3, 3):
            raise ValueError("spacing_m and origin_m need 3 values and direction a 3x3 matrix")
        self.surfaces = surfaces
        # One voxel of nothing around the volume closes the surfaces where the scan ends; with a
        # step, more at the far ends, so that the last plane (padded index L - 1) is sampled.
        self._labels = np.pad(labels, [(1, 1 + (-(n + 1)) % step) for n in labels.shape])
        self._sampled = self._labels.shape[::-1]  # padded (i, j, k) lengths L
        self._pristine = (self._labels != Layer.OUTSIDE).astype(np.float32)
        self._material = self._pristine.copy()
        self._masks = {s.name: np.isin(self._labels, list(s.layers)) for s in surfaces}
        self._bricks: dict[tuple[int, int, int], npt.NDArray[np.uint16]] = {}  # origin (i, j, k) -> material
        # Chunks sample padded indices 0..L-1.
        self.chunks_per_axis = tuple(-(-(n - 1) // CHUNK_EDGE) for n in self._sampled)  # (ci, cj, ck)

    @property
    def drilled_bricks(self) -> int:
        """Drilled bricks applied now."""
        return len(self._bricks)

    def all_chunks(self) -> list[tuple[int, int, int]]:
        """Every chunk (ci, cj, ck) of the volume."""
        ni, nj, nk = self.chunks_per_axis
        return [(i, j, k) for k in range(nk) for j in range(nj) for i in range(ni)]

    def mesh(self, chunk: tuple[int, int, int]) -> list[ChunkMesh]:
        """Marches one chunk: its piece of every surface."""
        from skimage.measure import marching_cubes

        # Padded index of voxel v is v + 1; the chunk's samples are voxels [c·E - 1, (c+1)·E] so
        # the padding plane of the first chunk closes the surface and neighbours share a plane.
        lo = [c * CHUNK_EDGE for c in chunk]  # padded (i, j, k) of the chunk's first sample
        hi = [min(a + CHUNK_EDGE + 1, n) for a, n in zip(lo, self._sampled, strict=True)]
        sl = (slice(lo[2], hi[2]), slice(lo[1], hi[1]), slice(lo[0], hi[0]))
        material = self._material[sl]
        out = []
        for s in self.surfaces:
            field = self._masks[s.name][sl] * material
            if min(field.shape) < self.step + 1 or field.max() < 0.5 or field.min() >= 0.5:
                out.append(ChunkMesh(s.name, chunk, np.zeros((0, 3), np.float32), np.zeros((0, 3), np.uint32)))
                continue
            verts, faces, _, _ = marching_cubes(field, level=0.5, step_size=self.step, allow_degenerate=False)
            ijk = verts[:, ::-1] + np.array(lo, dtype=np.float64) - 1.0  # (k, j, i) -> unpadded (i, j, k)
            world = self.origin_m + (ijk * self.spacing_m) @ self.direction.T
            out.append(ChunkMesh(s.name, chunk, world.astype(np.float32), faces.astype(np.uint32)))
        return out

    def update(self, origins: npt.ArrayLike, material: npt.ArrayLike) -> set[tuple[int, int, int]]:
        """Applies a session's drilled bricks as they are now (``origins`` (n, 3) voxel (i, j, k),
        ``material`` (n, 8, 8, 8) u16 [k][j][i]); bricks no longer listed (a reset) become
        pristine again. Returns the chunks to re-mesh: those whose samples a changed brick holds."""
        origins = np.asarray(origins, dtype=np.int64).reshape(-1, 3)
        material = np.asarray(material, dtype=np.uint16).reshape(-1, BRICK_EDGE, BRICK_EDGE, BRICK_EDGE)
        if len(origins) != len(material):
            raise ValueError(f"{len(origins)} brick origins for {len(material)} bricks")
        changed: list[tuple[int, int, int]] = []
        now: dict[tuple[int, int, int], npt.NDArray[np.uint16]] = {}
        for o, m in zip(origins, material, strict=True):
            key = (int(o[0]), int(o[1]), int(o[2]))
            now[key] = m
            old = self._bricks.get(key)
            if old is None or not np.array_equal(old, m):
                self._write(key, np.divide(m, np.float32(FULL_MATERIAL), dtype=np.float32))
                changed.append(key)
        for key in self._bricks.keys() - now.keys():
            self._write(key, None)
            changed.append(key)
        self._bricks = {k: v.copy() for k, v in now.items()}
        return {c for key in changed for c in self._chunks_of(key)}

    def _write(self, origin: tuple[int, int, int], fraction: npt.NDArray[np.float32] | None) -> None:
        i, j, k = (v + 1 for v in origin)  # padded; a brick's voxels past the grid are not the bone's
        nz, ny, nx = self.shape
        sl = (
            slice(k, min(k + BRICK_EDGE, nz + 1)),
            slice(j, min(j + BRICK_EDGE, ny + 1)),
            slice(i, min(i + BRICK_EDGE, nx + 1)),
        )
        target = self._material[sl]
        if fraction is None:
            target[...] = self._pristine[sl]
        else:
            target[...] = fraction[: target.shape[0], : target.shape[1], : target.shape[2]]

    def _chunks_of(self, origin: tuple[int, int, int]) -> set[tuple[int, int, int]]:
        """Chunks whose samples include any voxel of the brick at ``origin``: chunk c samples
        padded indices [c·E, (c+1)·E], so a voxel on a border plane belongs to both."""
        ranges = []
        for v, n in zip(origin, self.chunks_per_axis, strict=True):
            first, last = v + 1, v + BRICK_EDGE  # padded
            lo, hi = max(0, (first - 1) // CHUNK_EDGE), min(n - 1, last // CHUNK_EDGE)
            ranges.append(range(lo, hi + 1))
        return {(a, b, c) for a in ranges[0] for b in ranges[1] for c in ranges[2]}
