"""X-ray views: they show the drilling, only where it happened, and render as PNG."""

from __future__ import annotations

import numpy as np
from PIL import Image

from dhg.bone.xray import render_views, view_pixel, write_views
from dhg.operators.scripted import straight_line_drill


def test_views_change_after_drilling_and_only_along_the_path(coarse_phantom):
    vol, path = coarse_phantom.volume, coarse_phantom.path
    bone = vol.drill()
    before = bone.xray()
    for name, img in before.as_dict().items():
        np.testing.assert_array_equal(img, vol.xray().as_dict()[name])
    straight_line_drill(bone, path, radius_m=1.5e-3, feed_m_s=3e-3)
    after = bone.xray()
    for name in ("top", "front", "side"):
        b, a = before.as_dict()[name], after.as_dict()[name]
        assert a.shape == b.shape
        diff = b - a
        assert diff.min() >= -1e-5, f"{name}: drilling cannot add attenuation"
        assert diff.max() > 0.02, f"{name}: the tunnel does not show"
        # Pixels far from the projected path are unchanged.
        mid = view_pixel(vol, name, path.point_at(np.linspace(0, path.length_m, 200)))
        rows, cols = np.indices(a.shape)
        if name in ("front", "side"):
            rows = a.shape[0] - 1 - rows  # view_pixel uses display rows (superior up)
        near = np.zeros(a.shape, bool)
        for r, c in mid:
            near |= (rows - r) ** 2 + (cols - c) ** 2 <= 6**2
        assert np.abs(diff[~near]).max() < 1e-5, f"{name}: changed away from the path"


def test_rendered_pngs(tmp_path, coarse_phantom):
    vol = coarse_phantom.volume
    images = render_views(vol, vol.xray(), coarse_phantom.path, tip_m=coarse_phantom.path.target_m)
    paths = write_views(images, tmp_path / "views")
    assert sorted(paths) == ["front", "side", "top"]
    nz, ny, nx = vol.shape
    with Image.open(paths["front"]) as img:
        assert img.mode == "RGB"
        assert img.width % nx == 0 and img.height % nz == 0
        arr = np.asarray(img)
    # Bone is brighter than the soft tissue at the image's corner; the tip is drawn in red.
    assert arr[..., 0].max() > 200 and arr[2, 2].mean() < 60
    assert np.any((arr[..., 0] > 200) & (arr[..., 1] < 80) & (arr[..., 2] < 80))
