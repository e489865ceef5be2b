"""Drawing the bone in a page of ``dhg view``, shared by the trainee's and the instructor's pages
(:mod:`dhg.view.pages`, :mod:`dhg.view.instructor`): the viser server each page runs, the layer
surfaces' meshes, the camera and the drill's direction.

The 3D scene is drawn in millimetres (world metres × :data:`SCENE_MM_PER_M`), in the volume's
world frame with +z up.
"""

from __future__ import annotations

import io
import logging
from typing import Any

import numpy as np

from dhg.core.layers import Layer
from dhg.view.feed import VolumeData
from dhg.view.surfaces import ChunkMesh, LayerSurfaces

__all__ = [
    "LAYER_NAMES",
    "SCENE_MM_PER_M",
    "add_bone_piece",
    "add_whole_bone",
    "along",
    "look_at",
    "stop_quietly",
    "viser_server",
]

SCENE_MM_PER_M = 1000.0
"""Scene units per metre: the scene is in millimetres, the scale a surgeon reads."""

LAYER_NAMES = {int(layer): layer.name.lower() for layer in Layer}
"""Each layer id's name, as the pages show it (``cortical``, ...)."""


def viser_server(host: str, port: int, label: str) -> Any:
    """A viser server without the banner it prints on stdout (``dhg view`` prints the URL)."""
    import contextlib

    import viser

    logging.getLogger("viser").setLevel(logging.WARNING)  # it logs every connection at INFO
    with contextlib.redirect_stdout(io.StringIO()):
        server = viser.ViserServer(host=host, port=port, label=label, verbose=False)
    # viser lights a scene with an HDR environment map and shadow-casting lights by default. Drawn
    # in software (SwiftShader: a lab PC without a GPU, the headless Chromium of the tests) the map
    # alone kept Chromium's GPU process at 1.45 of 2 cores with one small mesh in view (0.09
    # without it), and shadows tripled the cost of each frame of an 80k-triangle mesh (0.49 ->
    # 0.15 cores): docs/benchmarks.md "The live view". Plain lights without shadows show the bone.
    server.scene.configure_environment_map(None)
    server.scene.configure_default_lights(True, cast_shadow=False)
    return server


def stop_quietly(server: Any) -> None:
    import contextlib

    with contextlib.redirect_stdout(io.StringIO()):
        server.stop()


def add_bone_piece(server: Any, surfaces: LayerSurfaces, meshes: dict[str, Any], piece: ChunkMesh) -> None:
    """Shows (or replaces, or removes when empty) one chunk's piece of a surface; a piece as it is
    shown already is left alone (a cut re-marches every surface of its chunks, and most of those
    pieces do not change: sending them again cost the page most of its re-meshing CPU)."""
    name = f"/bone/{piece.name}"
    old = meshes.get(name)
    if len(piece.faces) == 0:
        if old is not None:
            meshes.pop(name).remove()
        return
    vertices = piece.vertices_m * np.float32(SCENE_MM_PER_M)
    if old is not None and np.array_equal(old.faces, piece.faces) and np.array_equal(old.vertices, vertices):
        return
    s = next(s for s in surfaces.surfaces if s.name == piece.surface)
    meshes[name] = server.scene.add_mesh_simple(
        name,
        vertices,
        piece.faces,
        color=s.color,
        opacity=None if s.opacity >= 1.0 else s.opacity,
        side="double" if s.opacity < 1.0 else "front",
        cast_shadow=False,
        receive_shadow=False,
    )


def along(d: np.ndarray) -> tuple[float, float, float, float]:
    """The quaternion (w, x, y, z) turning the tool's +z onto direction ``d`` (half-way rotation)."""
    d = d / np.linalg.norm(d)
    q = np.array([1.0 + d[2], -d[1], d[0], 0.0])  # 1 + z·d, z × d
    n = np.linalg.norm(q)
    return (0.0, 1.0, 0.0, 0.0) if n < 1e-9 else (float(q[0] / n), float(q[1] / n), float(q[2] / n), float(q[3] / n))


def add_whole_bone(server: Any, surfaces: LayerSurfaces, meshes: dict[str, Any]) -> None:
    """Marches and shows every chunk (a page's start)."""
    for chunk in surfaces.all_chunks():
        for piece in surfaces.mesh(chunk):
            add_bone_piece(server, surfaces, meshes, piece)


def look_at(client: Any, volume: VolumeData) -> None:
    """Points a new browser's camera at the bone, from the front and a little above."""
    lo = volume.origin_m
    hi = volume.origin_m + volume.direction @ (volume.spacing_m * np.array(volume.labels.shape[::-1]))
    c, extent = (lo + hi) / 2 * SCENE_MM_PER_M, float(np.linalg.norm(hi - lo) * SCENE_MM_PER_M)
    client.camera.up_direction = (0.0, 0.0, 1.0)
    client.camera.position = tuple(c + np.array([1.0, -1.2, 0.4]) * extent * 0.45)
    client.camera.look_at = tuple(c)
