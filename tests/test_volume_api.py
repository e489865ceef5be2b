"""The Python volume API: conversions, drilling, copy-on-write, files and every bad input."""

from __future__ import annotations

import numpy as np
import pytest

import dhg
from dhg import InvalidInputError, Layer, ShapeError, Volume, VolumeFileError


def block(n=16, hu=1500.0, spacing=0.5e-3):
    arr = np.full((n, n, n), -1000.0, np.float32)
    arr[2:-2, 2:-2, 2:-2] = hu
    return Volume.from_hu(arr, (spacing,) * 3)


def test_geometry_and_lookups():
    v = Volume.from_hu(np.zeros((2, 3, 4)), (1e-3, 2e-3, 3e-3), origin_m=(0.1, 0.2, 0.3))
    assert v.shape == (2, 3, 4)
    assert v.spacing_m == (1e-3, 2e-3, 3e-3)
    ijk = v.world_to_index([[0.1 + 3e-3, 0.2 + 4e-3, 0.3 + 3e-3]])
    np.testing.assert_allclose(ijk, [[3.0, 2.0, 1.0]], atol=1e-9)
    np.testing.assert_allclose(v.index_to_world(ijk), [[0.103, 0.204, 0.303]], atol=1e-12)


def test_threshold_labels_and_lookups_outside():
    v = block()
    assert v.layer_at([0.004, 0.004, 0.004])[0] == Layer.CORTICAL
    far = [[1.0, 1.0, 1.0], [-1.0, 0.0, 0.0]]
    assert list(v.layer_at(far)) == [0, 0]
    assert list(v.hu_at(far)) == [-1024.0, -1024.0]
    assert list(v.density_at(far)) == [0.0, 0.0]
    assert v.density_at([0.004] * 3)[0] == pytest.approx(1500.0)


@pytest.mark.parametrize(
    ("point", "exc"),
    [
        ([np.nan, 0.0, 0.0], InvalidInputError),
        ([0.0, np.inf, 0.0], InvalidInputError),
        ([0.0, 0.0], ShapeError),
        ([[0.0, 0.0, 0.0, 0.0]], ShapeError),
        (["a", "b", "c"], TypeError),
    ],
)
def test_bad_points_are_clear_errors(point, exc):
    v = block()
    with pytest.raises(exc):
        v.layer_at(point)
    with pytest.raises(exc):
        v.hu_at(point)


def test_bad_volumes_are_clear_errors():
    hu = np.zeros((4, 4, 4), np.float32)
    with pytest.raises(InvalidInputError, match="spacing"):
        Volume.from_hu(hu, (0.0, 1e-3, 1e-3))
    with pytest.raises(InvalidInputError, match="spacing"):
        Volume.from_hu(hu, (-1e-3, 1e-3, 1e-3))
    with pytest.raises(InvalidInputError, match="spacing_m must be finite"):
        Volume.from_hu(hu, (np.nan, 1e-3, 1e-3))
    with pytest.raises(ShapeError, match="3-D"):
        Volume.from_hu(np.zeros((4, 4)), (1e-3,) * 3)
    with pytest.raises(ShapeError, match="empty"):
        Volume.from_hu(np.zeros((0, 4, 4)), (1e-3,) * 3)
    with pytest.raises(TypeError, match="numeric"):
        Volume.from_hu(np.full((2, 2, 2), "x"), (1e-3,) * 3)
    bad = hu.copy()
    bad[1, 2, 3] = np.nan
    with pytest.raises(InvalidInputError, match="HU value must be finite"):
        Volume.from_hu(bad, (1e-3,) * 3)
    with pytest.raises(ShapeError, match="labels shape"):
        Volume.from_hu(hu, (1e-3,) * 3, labels=np.zeros((4, 4, 5), np.uint8))
    with pytest.raises(InvalidInputError, match="layer id 7"):
        Volume.from_hu(hu, (1e-3,) * 3, labels=np.full((4, 4, 4), 7))
    with pytest.raises(InvalidInputError, match="layer id -1"):
        Volume.from_hu(hu, (1e-3,) * 3, labels=np.full((4, 4, 4), -1))
    with pytest.raises(TypeError, match="integer"):
        Volume.from_hu(hu, (1e-3,) * 3, labels=np.zeros((4, 4, 4), float))
    with pytest.raises(InvalidInputError, match="rotation"):
        Volume.from_hu(hu, (1e-3,) * 3, direction=np.diag([-1.0, 1.0, 1.0]))
    with pytest.raises(ShapeError, match="direction"):
        Volume.from_hu(hu, (1e-3,) * 3, direction=np.eye(2))
    with pytest.raises(InvalidInputError, match="cancellous_min_hu"):
        Volume.from_hu(hu, (1e-3,) * 3, mapping=dhg.HuMapping(cancellous_min_hu=900.0))
    with pytest.raises(InvalidInputError, match="unknown HU mapping keys"):
        dhg.HuMapping.from_dict({"bogus": 1.0})


def test_layer_runs_along_a_path_through_the_block():
    v = block()  # bone voxels 2..13 at 0.5 mm: centres 1.0 to 6.5 mm, faces at 0.75 and 6.75 mm
    runs = v.layer_runs([0.0, 0.004, 0.004], [0.0075, 0.004, 0.004], step_m=0.2e-3)
    assert [layer for layer, _, _ in runs] == [Layer.OUTSIDE, Layer.CORTICAL, Layer.OUTSIDE]
    assert runs[1][1:] == pytest.approx((0.8e-3, 6.6e-3), abs=1e-12)
    assert runs[2][2] == pytest.approx(7.4e-3, abs=1e-12)  # the last sample lies within step/2 of B
    with pytest.raises(InvalidInputError, match="step"):
        v.layer_runs([0.0, 0.004, 0.004], [0.0075, 0.004, 0.004], step_m=0.0)
    with pytest.raises(InvalidInputError, match="entry"):
        v.layer_runs([np.nan, 0.004, 0.004], [0.0075, 0.004, 0.004])
    with pytest.raises(ShapeError, match="one point"):
        v.layer_runs([[0.0, 0.004, 0.004]] * 2, [0.0075, 0.004, 0.004])


def test_errors_are_dhg_and_value_errors():
    with pytest.raises(dhg.InvalidInputError, match="finite") as info:
        block().layer_at([np.nan] * 3)
    assert isinstance(info.value, ValueError)  # code that catches ValueError keeps working
    with pytest.raises(ShapeError) as info:
        block().layer_at(np.zeros((2, 2)))
    assert isinstance(info.value, ValueError)


def test_drilling_isolation_reset_and_memory():
    v = block(24)
    a, b = v.drill(), v.drill()
    centre = [0.006, 0.006, 0.006]
    r = a.remove(centre, 2.5e-3, 1000.0, 1.0)
    assert r.voxels_removed > 0 and r.mass_removed_kg > 0
    assert a.material_at(centre)[0] == 0.0 and a.layer_at(centre)[0] == Layer.OUTSIDE
    assert b.material_at(centre)[0] == 1.0 and b.layer_at(centre)[0] == Layer.CORTICAL
    assert v.drill().material_grid().min() == 0.0  # the air margin, not the hole
    assert v.drill().material_grid()[12, 12, 12] == 1.0
    assert a.removed_mass_kg == pytest.approx(r.mass_removed_kg)
    assert a.drilled_bricks > 0 and b.drilled_bricks == 0
    assert a.memory_bytes < 1_000_000
    a.reset()
    assert a.material_at(centre)[0] == 1.0 and a.removed_voxels == 0 and a.drilled_bricks == 0


def test_bad_removals_change_nothing():
    v = block()
    d = v.drill()
    with pytest.raises(InvalidInputError, match="burr radius"):
        d.remove([0.004] * 3, 0.0, 1000.0, 0.1)
    with pytest.raises(InvalidInputError, match="burr radius"):
        d.remove([0.004] * 3, -1e-3, 1000.0, 0.1)
    with pytest.raises(InvalidInputError, match="burr centre"):
        d.remove([np.nan, 0.0, 0.0], 1e-3, 1000.0, 0.1)
    with pytest.raises(InvalidInputError, match="dt"):
        d.remove([0.004] * 3, 1e-3, 1000.0, -1.0)
    with pytest.raises(InvalidInputError, match="contact"):
        d.remove([0.004] * 3, 1e-3, 1000.0, 0.1, contact=2.0)
    with pytest.raises(ShapeError):
        d.remove([[0.004] * 3, [0.004] * 3], 1e-3, 1000.0, 0.1)
    path = np.array([[0.004] * 3, [0.005] * 3, [np.nan, 0, 0]])
    with pytest.raises(InvalidInputError):
        d.remove_along(path, 1e-3, 1000.0, 0.1)
    assert d.removed_mass_kg == 0.0 and d.drilled_bricks == 0, "a rejected batch must not be half-applied"
    with pytest.raises(InvalidInputError, match="reserve_bricks"):
        v.drill(reserve_bricks=-1)


def test_save_load_round_trip(tmp_path, coarse_phantom):
    vol = coarse_phantom.volume
    path = vol.save(tmp_path / "femur.npz")
    back = Volume.load(path)
    assert back.shape == vol.shape and back.spacing_m == vol.spacing_m
    np.testing.assert_array_equal(back.hu(), vol.hu())
    np.testing.assert_array_equal(back.labels(), vol.labels())
    np.testing.assert_allclose(back.origin_m, vol.origin_m)
    assert back.meta["planned_path"] == coarse_phantom.path.to_dict()
    assert back.mapping == vol.mapping
    assert not list(tmp_path.glob(".*tmp")), "no temporary file left behind"


def test_corrupt_and_foreign_volume_files(tmp_path, coarse_phantom):
    good = coarse_phantom.volume.save(tmp_path / "good.npz")
    data = good.read_bytes()
    (tmp_path / "truncated.npz").write_bytes(data[: len(data) // 2])
    with pytest.raises(VolumeFileError, match="truncated.npz"):
        Volume.load(tmp_path / "truncated.npz")
    (tmp_path / "text.npz").write_text("not a volume")
    with pytest.raises(VolumeFileError):
        Volume.load(tmp_path / "text.npz")
    np.savez(tmp_path / "other.npz", a=np.zeros(3))
    with pytest.raises(VolumeFileError, match="missing"):
        Volume.load(tmp_path / "other.npz")
    with pytest.raises(VolumeFileError, match="no such"):
        Volume.load(tmp_path / "absent.npz")
    import json

    with np.load(good) as z:
        header = json.loads(str(z["header"]))
        hu, labels = z["hu"], z["labels"]
    header["version"] = 99
    np.savez(tmp_path / "future.npz", header=np.array(json.dumps(header)), hu=hu, labels=labels)
    with pytest.raises(VolumeFileError, match="version 99"):
        Volume.load(tmp_path / "future.npz")
