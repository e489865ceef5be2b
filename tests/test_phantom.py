"""The phantom femur's anatomy and its default hip-pinning task."""

from __future__ import annotations

import numpy as np

import dhg
from dhg import Layer
from dhg.bone.planning import layer_runs


def test_layer_sequence_along_the_default_path(phantom):
    runs = [name for name, start, end in layer_runs(phantom.volume.drill(), phantom.path) if end - start > 0.5e-3]
    assert runs == ["cortical", "cancellous", "marrow", "cancellous", "necrosis", "cancellous"]


def test_path_runs_from_lateral_cortex_to_the_head(phantom):
    lm, path = phantom.landmarks_m, phantom.path
    # A sits on the bone surface: just outside is soft tissue, just inside is cortical bone.
    before, after = path.point_at([-0.5e-3, 1.0e-3])
    assert phantom.volume.layer_at(before)[0] == Layer.OUTSIDE
    assert phantom.volume.layer_at(after)[0] == Layer.CORTICAL
    # Lateral (−x in LPS for a right femur) and below the neck base.
    assert path.entry_m[0] < -0.010
    assert path.entry_m[2] < lm["neck_base"][2]
    # B is inside the head, 6 mm below its surface.
    dist_b = np.linalg.norm(path.target_m - np.array(lm["head_center"]))
    assert abs((lm["head_radius"] - dist_b) - 6e-3) < 1e-6
    assert 0.07 < path.length_m < 0.10


def _surface_distance(volume, origin, direction, max_m=0.05, step=0.1e-3):
    """Distance along a ray until the layer turns OUTSIDE."""
    s = np.arange(0.0, max_m, step)
    layers = volume.layer_at(origin + s[:, None] * direction)
    return s[np.argmax(layers == Layer.OUTSIDE)]


def test_head_radius_and_neck_shaft_angle(phantom):
    lm = phantom.landmarks_m
    centre = np.array(lm["head_center"])
    # The head's superior and anterior/posterior surfaces sit one radius from its centre.
    for d in ([0, 0, 1], [0, 1, 0], [0, -1, 0]):
        r = _surface_distance(phantom.volume, centre, np.array(d, float))
        assert 22e-3 <= r <= 25e-3, f"head radius {r * 1e3:.1f} mm along {d}"
    axis = np.array(lm["neck_axis"])
    angle = np.degrees(np.arccos(axis @ np.array([0.0, 0.0, -1.0])))
    assert abs(angle - 129.0) < 0.5


def test_cortex_is_thick_on_the_shaft_and_thin_at_the_head(phantom):
    vol = phantom.volume
    # Shaft at z = 20 mm: walk inward from the lateral surface.
    s = np.arange(0.0, 0.012, 0.1e-3)
    shaft = vol.layer_at(np.stack([-0.0135 + s, 0 * s, 0.02 + 0 * s], axis=1))
    shaft_cortex = np.sum(shaft == Layer.CORTICAL) * 0.1e-3
    centre = np.array(phantom.landmarks_m["head_center"])
    head = vol.layer_at(centre + np.outer(np.arange(0.0, 0.0235, 0.1e-3), [0.0, 0.0, 1.0]))
    head_cortex = np.sum(head == Layer.CORTICAL) * 0.1e-3
    assert 3.5e-3 <= shaft_cortex <= 5.5e-3
    assert 0.5e-3 <= head_cortex <= 1.6e-3
    # Cortical bone is the densest layer, marrow the softest.
    labels, hu = vol.labels(), vol.hu()
    med = {layer: float(np.median(hu[labels == layer])) for layer in Layer if layer != Layer.OUTSIDE}
    assert med[Layer.CORTICAL] > 1400 > med[Layer.CANCELLOUS] > 150 > med[Layer.MARROW]


def test_cancellous_density_rises_towards_the_head(phantom):
    vol = phantom.volume
    labels, hu = vol.labels(), vol.hu()
    ijk = np.argwhere(labels == Layer.CANCELLOUS)[:, ::-1].astype(float)
    world = vol.index_to_world(ijk)
    dist = np.linalg.norm(world - np.array(phantom.landmarks_m["head_center"]), axis=1)
    values = hu[labels == Layer.CANCELLOUS]
    assert values[dist < 0.015].mean() > values[dist > 0.04].mean() + 80


def test_deterministic_for_a_seed():
    a, b, c = (dhg.bone.phantom.femur_arrays(seed, 2e-3) for seed in (3, 3, 4))
    assert np.array_equal(a["hu"], b["hu"]) and np.array_equal(a["labels"], b["labels"])
    assert not np.array_equal(a["hu"], c["hu"]), "the seed must change texture and noise"
    assert np.array_equal(a["labels"], c["labels"]), "the seed must not change the anatomy"


def test_default_voxel_size_and_shared_instance(phantom):
    assert phantom.volume.spacing_m == (0.5e-3, 0.5e-3, 0.5e-3)
    assert dhg.default_phantom() is phantom
    assert dhg.default_phantom(voxel_m=0.5e-3) is phantom and dhg.default_phantom(0, 0.5e-3) is phantom
