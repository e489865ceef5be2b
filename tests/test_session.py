"""The drilling session's Python contract: the batched and per-tick APIs, records, config, errors."""

from __future__ import annotations

import numpy as np
import pytest

import dhg
from dhg import InvalidInputError, Layer, SessionConfig, ShapeError
from dhg.core.features import FEATURE_NAMES, FEATURE_UNITS, POSE_COLUMNS, RECORD_COLUMNS
from dhg.core.path import TaskRules
from dhg.core.session import poses
from dhg.core.skill import skill_metrics
from support import tool_quaternion as axis_quaternion


def drive(path, seconds, lead_m=4e-3, feed_m_s=1.5e-3, start_before_m=5e-3):
    """Poses that lead the drill along the path at a constant feed, `lead_m` ahead (a push)."""
    n = int(seconds * 1000)
    depth = -start_before_m + np.arange(n) * 1e-3 * feed_m_s + lead_m
    return poses(path.point_at(depth), axis_quaternion(path.direction), True, 1250.0)


@pytest.fixture(scope="module")
def run(coarse_phantom):
    s = dhg.DrillingSession(coarse_phantom.volume, coarse_phantom.path)
    result = s.step(drive(coarse_phantom.path, 30.0))
    return s, result


def test_feature_order_and_units_are_the_documented_ones():
    assert FEATURE_NAMES == (
        "force_x_n",
        "force_y_n",
        "force_z_n",
        "tip_x_m",
        "tip_y_m",
        "tip_z_m",
        "layer",
        "depth_m",
        "temperature_c",
    )
    assert FEATURE_UNITS == ("N", "N", "N", "m", "m", "m", "1", "m", "°C")
    assert RECORD_COLUMNS[0] == "time_s" and RECORD_COLUMNS[-1] == "drill_on"
    assert len(POSE_COLUMNS) == 9


def test_step_shapes_records_and_units(run, coarse_phantom):
    s, r = run
    assert r.forces_n.shape == (30_000, 3) and r.forces_n.dtype == np.float64
    assert r.records.shape == (300, 11)
    np.testing.assert_allclose(r.times_s, np.arange(1, 301) * 0.1)
    # The record's force is the force sent at that tick.
    np.testing.assert_array_equal(r.features[:, 0:3], r.forces_n[99::100])
    assert np.all(np.linalg.norm(r.forces_n, axis=1) <= 3.3 + 1e-12)
    # Tip positions lie near the planned path; depth grows; temperature in °C above body.
    dev = coarse_phantom.path.lateral_deviation(r.features[:, 3:6])
    assert dev.max() < 2e-3
    depth = r.features[:, 7]
    assert depth[-1] > depth[0] + 0.03
    assert np.all(r.features[:, 8] >= 37.0 - 1e-9) and r.features[:, 8].max() > 38.0
    assert set(np.unique(r.features[:, 6]).astype(int)) >= {Layer.CORTICAL, Layer.CANCELLOUS, Layer.MARROW}
    assert np.all(r.records[:, 10] == 1.0)
    st = s.state
    assert st.ticks == 30_000 and st.drill_on and st.removed_mass_kg > 0
    np.testing.assert_allclose(st.tip_m, r.features[-1, 3:6])


def test_step_equals_ticks_and_is_deterministic(coarse_phantom):
    rows = drive(coarse_phantom.path, 0.5)
    a = dhg.DrillingSession(coarse_phantom.volume, coarse_phantom.path)
    b = dhg.DrillingSession(coarse_phantom.volume, coarse_phantom.path)
    batch = a.step(rows)
    forces, records = [], []
    for row in rows:
        f, rec = b.tick(row[0:3], row[3:7], bool(row[7]), row[8])
        forces.append(f)
        if rec is not None:
            records.append(rec)
    np.testing.assert_array_equal(batch.forces_n, np.array(forces))
    np.testing.assert_array_equal(batch.records, np.array(records))
    again = dhg.DrillingSession(coarse_phantom.volume, coarse_phantom.path).step(rows)
    np.testing.assert_array_equal(again.forces_n, batch.forces_n)


def test_nan_rows_and_silence_give_bounded_ramped_forces(coarse_phantom):
    s = dhg.DrillingSession(coarse_phantom.volume, coarse_phantom.path)
    rows = drive(coarse_phantom.path, 3.0)
    s.step(rows[:2000])
    bad = rows[2000:2300].copy()
    bad[::3, 0] = np.nan  # invalid: counted
    bad[1::3, 3:7] = 0.0  # zero quaternion: invalid
    bad[2::3] = np.nan  # no pose at all
    r = s.step(bad)
    assert np.all(np.isfinite(r.forces_n))
    assert np.all(np.linalg.norm(np.diff(r.forces_n, axis=0), axis=1) <= 0.2 + 1e-9)
    assert s.state.rejected_poses == 200
    assert s.state.stale and np.linalg.norm(r.forces_n[-1]) == 0.0


def test_reset_and_xray(coarse_phantom):
    s = dhg.DrillingSession(coarse_phantom.volume, coarse_phantom.path)
    before = s.xray().front.copy()
    s.step(drive(coarse_phantom.path, 5.0))
    assert (before - s.xray().front).max() > 0.01
    assert s.memory_bytes > 0
    s.reset()
    np.testing.assert_array_equal(s.xray().front, before)
    assert s.state.ticks == 0 and s.state.removed_mass_kg == 0.0


def test_config_round_trip_and_bad_config(coarse_phantom):
    cfg = SessionConfig(burr_radius_m=1.5e-3, device=dhg.DeviceProfile(peak_force_n=2.5))
    flat = cfg.to_flat_dict()
    assert flat["device.peak_force_n"] == 2.5 and "coupling_stiffness_n_per_m" not in flat
    assert SessionConfig.from_flat_dict(flat) == cfg
    s = dhg.DrillingSession(coarse_phantom.volume, coarse_phantom.path, cfg)
    r = s.step(drive(coarse_phantom.path, 20.0, lead_m=20e-3))
    assert np.linalg.norm(r.forces_n, axis=1).max() <= 2.5 + 1e-12
    with pytest.raises(InvalidInputError, match="burr_radius_m"):
        dhg.DrillingSession(coarse_phantom.volume, coarse_phantom.path, SessionConfig(burr_radius_m=-1.0))
    with pytest.raises(InvalidInputError, match="max_stiffness"):
        dhg.DrillingSession(coarse_phantom.volume, coarse_phantom.path, SessionConfig(coupling_stiffness_n_per_m=5e3))
    with pytest.raises(InvalidInputError, match="continuous_force_n"):
        dhg.DrillingSession(
            coarse_phantom.volume, coarse_phantom.path, SessionConfig(device=dhg.DeviceProfile(continuous_force_n=9.0))
        )
    with pytest.raises(InvalidInputError, match="unknown session config key"):
        SessionConfig.from_flat_dict({"device.bogus": 1.0})
    with pytest.raises(InvalidInputError, match="'burr_radius_m' must be a number, got 'abc'"):
        SessionConfig.from_flat_dict({"burr_radius_m": "abc"})


def test_wrong_types_and_malformed_paths_are_clear_errors(coarse_phantom):
    """The public constructors say what they take rather than failing later inside."""
    vol, path = coarse_phantom.volume, coarse_phantom.path
    with pytest.raises(InvalidInputError, match="path must be a dhg.PlannedPath"):
        dhg.DrillingSession(vol, (path.entry_m, path.target_m))
    with pytest.raises(InvalidInputError, match="volume must be a dhg.Volume"):
        dhg.DrillingSession(np.zeros((4, 4, 4)), path)
    with pytest.raises(InvalidInputError, match="config must be a SessionConfig"):
        dhg.DrillingSession(vol, path, {"burr_radius_m": 1e-3})
    with pytest.raises(InvalidInputError, match="Volume.from_hu"):
        dhg.Volume(np.zeros((4, 4, 4)))
    with pytest.raises(InvalidInputError, match="3-D points of numbers"):
        dhg.PlannedPath("ab", [0.0, 0.0, 0.0])
    with pytest.raises(InvalidInputError, match="needs target_m"):
        dhg.PlannedPath.from_dict({"entry_m": [0.0, 0.0, 0.0]})
    with pytest.raises(InvalidInputError, match="a planned path is a dict"):
        dhg.PlannedPath.from_dict([0.0, 0.0, 0.0])
    back = dhg.PlannedPath.from_dict(path.to_dict())
    np.testing.assert_array_equal(back.entry_m, path.entry_m)
    np.testing.assert_array_equal(back.target_m, path.target_m)


def test_bad_pose_arrays_are_clear_errors(coarse_phantom):
    s = dhg.DrillingSession(coarse_phantom.volume, coarse_phantom.path)
    with pytest.raises(ShapeError, match=r"\(N, 9\)"):
        s.step(np.zeros((10, 8)))
    with pytest.raises(ShapeError):
        s.step(np.zeros(9))
    with pytest.raises(ShapeError, match="broadcast"):
        poses(np.zeros((5, 3)), np.zeros((4, 4)))
    with pytest.raises(ShapeError):
        s.tick(np.zeros((2, 3)))
    with pytest.raises(TypeError):
        s.step([["a"] * 9])
    assert s.state.ticks == 0, "nothing ran"


_GOOD_END = dict(
    final_tip_m=[0.0, 0.0, 0.05], drilling_s=1.0, plunge_depth_m=0.0, peak_temperature_c=40.0, time_above_47_s=0.0
)


@pytest.mark.parametrize(
    ("bad", "error", "said"),
    [
        ({"final_tip_m": [0.0, 0.0]}, ShapeError, "final_tip_m"),
        ({"records": np.zeros(len(RECORD_COLUMNS))}, ShapeError, "records"),
        ({"records": np.zeros((3, 5))}, ShapeError, "records"),
        ({"records": np.full((3, len(RECORD_COLUMNS)), np.nan)}, InvalidInputError, "records"),
        ({"forces_n": np.array([[0.0, np.inf, 0.0]] * 2)}, InvalidInputError, "forces_n"),
        ({"forces_n": np.zeros(3)}, ShapeError, "forces_n"),
        ({"drilling_s": float("nan")}, InvalidInputError, "drilling_s"),
        ({"drilling_s": -1.0}, InvalidInputError, "drilling_s"),
        ({"plunge_depth_m": -1e-3}, InvalidInputError, "plunge_depth_m"),
        ({"peak_temperature_c": float("inf")}, InvalidInputError, "peak_temperature_c"),
        ({"time_above_47_s": float("nan")}, InvalidInputError, "time_above_47_s"),
        ({"final_tip_m": [0.0, float("nan"), 0.0]}, InvalidInputError, "final_tip_m"),
    ],
)
def test_skill_metrics_refuse_bad_input_by_name(bad, error, said):
    """NaN metrics used to come back for a NaN drilling time, and numpy's reshape error for a
    short final tip."""
    path = dhg.PlannedPath(np.zeros(3), np.array([0.0, 0.0, 0.05]))
    args = {"records": np.zeros((3, len(RECORD_COLUMNS))), "path": path, "rules": TaskRules(), **_GOOD_END}
    assert skill_metrics(**args)["completion_time_s"] == 1.0  # the good input is taken
    with pytest.raises(error, match=said):
        skill_metrics(**(args | bad))


@pytest.mark.parametrize(
    ("kwargs", "said"),
    [
        ({"duration_s": -5.0}, "duration_s must be > 0"),
        ({"duration_s": float("nan")}, "duration_s must be > 0"),
        ({"duration_s": 1e9}, "at most 3600 s"),
        ({"duration_s": 1.0, "feed_m_s": 0.0}, "feed_m_s must be a number > 0"),
        ({"duration_s": 1.0, "feed_m_s": float("nan")}, "feed_m_s must be a number > 0"),
        ({"duration_s": 1.0, "lead_m": float("inf")}, "lead_m must be a number >= 0"),
        ({"duration_s": 1.0, "spindle_rpm": 5000.0}, "spindle_rpm must be 0 to"),
    ],
)
def test_the_scripted_stylus_refuses_what_it_cannot_drive(coarse_phantom, kwargs, said):
    from dhg.operators.scripted import scripted_stylus

    with pytest.raises(InvalidInputError, match=said):
        scripted_stylus(coarse_phantom.path, **kwargs)
    assert scripted_stylus(coarse_phantom.path, 0.5).shape == (500, 9)
