"""The viewer's layer surfaces: marched in chunks that join without cracks, and re-meshed only
where the drill changed bricks, to the same surface as marching the whole drilled volume."""

from __future__ import annotations

import numpy as np
import pytest
from skimage.measure import marching_cubes, mesh_surface_area

from dhg.core.layers import Layer
from dhg.view.surfaces import SURFACES, LayerSurfaces, display_step


def _area(pieces: dict) -> dict[str, float]:
    out = {s.name: 0.0 for s in SURFACES}
    for p in pieces.values():
        if len(p.faces):
            out[p.surface] += mesh_surface_area(p.vertices_m.astype(np.float64), p.faces)
    return out


def _whole(labels: np.ndarray, material: np.ndarray, spacing: float, step: int = 1) -> dict[str, float]:
    """Each surface marched over the whole volume at once (padded like the chunks)."""
    out = {}
    for s in SURFACES:
        pad = [(1, 1 + (-(n + 1)) % step) for n in labels.shape]
        field = np.pad(np.isin(labels, list(s.layers)) * material, pad).astype(np.float32)
        if field.max() < 0.5:
            out[s.name] = 0.0
            continue
        v, f, _, _ = marching_cubes(field, 0.5, spacing=(spacing,) * 3, step_size=step, allow_degenerate=False)
        out[s.name] = mesh_surface_area(v, f)
    return out


def _mesh_all(surf: LayerSurfaces, chunks) -> dict:
    return {(p.surface, p.chunk): p for c in chunks for p in surf.mesh(c)}


@pytest.fixture(scope="module")
def femur_2mm():
    from dhg.bone import phantom as ph

    return ph.default_phantom(0, 2e-3)  # 2 mm voxels: 50x32x62, several chunks a side


@pytest.mark.parametrize("step", [1, 2])
def test_the_chunks_join_into_the_surface_of_the_whole_volume(femur_2mm, step):
    v = femur_2mm.volume
    surf = LayerSurfaces(v.labels(), v.spacing_m, v.origin_m, v.direction, step=step)
    pieces = _mesh_all(surf, surf.all_chunks())
    assert surf.chunks_per_axis == (2, 2, 2)  # 50x32x62 voxels (+2 padding) in 32-voxel chunks
    whole = _whole(v.labels(), (v.labels() != Layer.OUTSIDE).astype(np.float32), v.spacing_m[0], step)
    got = _area(pieces)
    for name, area in whole.items():
        assert area > 0 and got[name] == pytest.approx(area, rel=1e-6), name
    # The vertices are in the world: inside the volume's bounds.
    lo, hi = v.bounds_m()
    allv = np.concatenate([p.vertices_m for p in pieces.values() if len(p.faces)])
    assert np.all(allv >= lo - v.spacing_m[0]) and np.all(allv <= hi + v.spacing_m[0])


def test_drilling_re_meshes_only_the_chunks_it_touched_and_a_reset_restores_the_bone(femur_2mm):
    v = femur_2mm.volume
    surf = LayerSurfaces(v.labels(), v.spacing_m, v.origin_m, v.direction)
    pieces = _mesh_all(surf, surf.all_chunks())
    pristine = _area(pieces)
    bone = v.drill()
    a, b = femur_2mm.path.entry_m, femur_2mm.path.target_m
    bone.remove_along(a + (b - a) * np.linspace(-0.05, 0.3, 60)[:, None], 2.5e-3, 1250.0, 0.001)
    # And a cut on the plane two chunks share (voxel 31 of each axis is a chunk's last sample).
    labels = v.labels()
    k, j = np.argwhere(labels[:, :, 31] == Layer.CORTICAL)[0]
    bone.remove(tuple(v.index_to_world(np.array([[29.8, j, k]]))[0]), 3e-3, 1250.0, 0.05)  # reaches 31, not 32
    origins, material = bone.bricks()
    assert len(origins) > 0 and material.shape == (len(origins), 8, 8, 8) and material.dtype == np.uint16
    changed = surf.update(origins, material)
    assert 0 < len(changed) < len(surf.all_chunks())
    pieces.update(_mesh_all(surf, changed))
    drilled = _area(pieces)
    whole = _whole(v.labels(), bone.material_grid(), v.spacing_m[0])
    for name in ("cortex", "cancellous"):
        assert drilled[name] == pytest.approx(whole[name], rel=1e-6), name
    assert drilled["cortex"] != pytest.approx(pristine["cortex"], rel=1e-3)  # the hole shows
    # The same bricks again change nothing; none (a reset) restores the pristine surfaces.
    assert surf.update(origins, material) == set()
    restored = surf.update(np.zeros((0, 3)), np.zeros((0, 8, 8, 8)))
    assert restored == changed and surf.drilled_bricks == 0
    pieces.update(_mesh_all(surf, restored))
    assert _area(pieces) == pytest.approx(pristine, rel=1e-9)


def test_bad_volumes_and_bricks_are_refused_with_the_reason():
    with pytest.raises(ValueError, match="3D uint8"):
        LayerSurfaces(np.zeros((4, 4), np.uint8), (1e-3,) * 3, (0.0,) * 3)
    with pytest.raises(ValueError, match="step must be"):
        LayerSurfaces(np.zeros((4, 4, 4), np.uint8), (1e-3,) * 3, (0.0,) * 3, step=0)
    assert display_step((0.5e-3,) * 3) == 2 and display_step((1e-3,) * 3) == 1 and display_step((2e-3,) * 3) == 1
    with pytest.raises(ValueError, match="3 values"):
        LayerSurfaces(np.zeros((4, 4, 4), np.uint8), (1e-3,) * 2, (0.0,) * 3)
    surf = LayerSurfaces(np.ones((4, 4, 4), np.uint8), (1e-3,) * 3, (0.0,) * 3)
    with pytest.raises(ValueError, match="2 brick origins for 1 bricks"):
        surf.update(np.zeros((2, 3)), np.zeros((1, 8, 8, 8)))


def test_a_page_sends_only_the_pieces_a_cut_changed(femur_2mm):
    """A cut re-marches every surface of the chunks it touched; the page sends a piece again only
    when it changed (a new mesh handle) and keeps the rest as shown."""
    from dhg.view.scene import add_bone_piece, add_whole_bone, stop_quietly, viser_server

    v = femur_2mm.volume
    surf = LayerSurfaces(v.labels(), v.spacing_m, v.origin_m, v.direction)
    server = viser_server("127.0.0.1", 0, "test")
    try:
        meshes: dict = {}
        add_whole_bone(server, surf, meshes)
        before = dict(meshes)
        bone = v.drill()
        labels = v.labels()  # a cut into the cortex alone: the cancellous piece of its chunk stays
        k, j, i = np.argwhere(labels == Layer.CORTICAL)[len(np.argwhere(labels == Layer.CORTICAL)) // 2]
        bone.remove(tuple(v.index_to_world(np.array([[i, j, k]], dtype=float))[0]), 2e-3, 1250.0, 0.05)
        changed = surf.update(*bone.bricks())
        pieces = [p for c in sorted(changed) for p in surf.mesh(c)]
        for p in pieces:
            add_bone_piece(server, surf, meshes, p)
        resent = {n for n in meshes if meshes[n] is not before.get(n)}
        kept = {n for n in before if meshes.get(n) is before[n]}
        assert resent and kept  # the hole's pieces went again, the rest of the bone stayed
        shown = {f"/bone/{p.name}": p for p in pieces if len(p.faces)}
        for name in resent:
            np.testing.assert_array_equal(meshes[name].faces, shown[name].faces)
        untouched = [p for p in pieces if f"/bone/{p.name}" in kept]
        assert untouched  # pieces of re-marched chunks that did not change were not sent again
        # The same pieces again send nothing.
        now = dict(meshes)
        for p in pieces:
            add_bone_piece(server, surf, meshes, p)
        assert all(meshes[n] is now[n] for n in now) and meshes.keys() == now.keys()
    finally:
        stop_quietly(server)
