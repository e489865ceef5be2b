"""Demonstration profiles: per-depth expert statistics, built from a dataset and stored with a model."""

from __future__ import annotations

import numpy as np
import pytest

from dhg.core.errors import InvalidInputError
from dhg.core.layers import Layer
from dhg.core.path import PlannedPath
from dhg.data.dataset import EpisodeInput, load_dataset, write_dataset
from dhg.learning.profiles import CORRIDOR_N_PER_M, DemoProfiles, build_profiles

PATH = PlannedPath(np.zeros(3), np.array([0.0, 0.0, 0.004]))  # 4 mm along +z


def _episode(subject: str, side: float, skill: str = "expert") -> EpisodeInput:
    """A straight 2 mm/s run along +z: 0.2 mm off the line (times ``side``) over the first 2 mm,
    1.0 mm off it after; cortex to 1.5 mm, then cancellous bone; pushing 2 N against the drill."""
    t = np.arange(1, 21) * 0.1
    depth = 2e-3 * t - 1e-4
    lateral = np.where(depth < 2e-3, 0.2e-3, 1.0e-3) * side
    rec = np.zeros((len(t), 11))
    rec[:, 0] = t
    rec[:, 3] = -2.0  # the device pushes back along -z: thrust 2 N
    rec[:, 4] = lateral
    rec[:, 6] = depth
    rec[:, 7] = np.where(depth < 1.5e-3, Layer.CORTICAL, Layer.CANCELLOUS)
    rec[:, 8] = depth
    rec[:, 9] = 37.0
    rec[:, 10] = 1.0
    return EpisodeInput(subject, skill, 0, rec)


@pytest.fixture
def dataset(tmp_path):
    eps = [_episode("e1", 1.0), _episode("e2", -1.0), _episode("n1", 5.0, "novice")]
    return load_dataset(write_dataset(tmp_path / "ds", eps, {"planned_path": PATH.to_dict()}))


def test_profiles_hold_the_experts_spread_feed_thrust_and_breakthrough(dataset):
    p = build_profiles(dataset, bin_m=1e-3)
    assert p.episodes == 2 and p.depth_m == pytest.approx([0.5e-3, 1.5e-3, 2.5e-3, 3.5e-3])
    # Two experts at ±0.2 mm, then ±1.0 mm: the spread is 0.2 mm, then 1.0 mm (novices left out).
    assert p.lateral_spread_m[:2] == pytest.approx([0.2e-3, 0.2e-3])
    assert p.lateral_spread_m[2:] == pytest.approx([1e-3, 1e-3])
    assert p.lateral_mean_m == pytest.approx([0.2e-3, 0.2e-3, 1e-3, 1e-3])
    assert p.feed_mean_m_s == pytest.approx([2e-3] * 4) and max(p.feed_sd_m_s) < 1e-9
    assert p.thrust_mean_n == pytest.approx([2.0] * 4)
    assert p.breakthrough_depths_m == pytest.approx([1.5e-3, 1.5e-3], abs=1e-4)
    assert p.breakthrough_m == pytest.approx((1.5e-3, 0.0), abs=1e-4)
    # Stiff where they agree, compliant (1/σ²) where they vary, within the device's range.
    k = p.corridor_n_per_m
    # The median spread (0.6 mm) gets 400 N/m: 0.2 mm is clamped at 400, 1.0 mm gets 400 · 0.6².
    assert k == pytest.approx([400.0, 400.0, 144.0, 144.0])
    assert all(CORRIDOR_N_PER_M[0] <= v <= CORRIDOR_N_PER_M[1] for v in k)
    assert DemoProfiles.from_dict(p.to_dict()) == p


def test_profiles_need_a_path_experts_and_a_positive_bin(dataset, tmp_path):
    with pytest.raises(InvalidInputError, match="bin_m"):
        build_profiles(dataset, bin_m=0.0)
    with pytest.raises(InvalidInputError, match="no surgeon"):
        build_profiles(dataset, skill="surgeon")
    bare = load_dataset(write_dataset(tmp_path / "bare", [_episode("e1", 1.0)], {}))
    with pytest.raises(InvalidInputError, match="planned path"):
        build_profiles(bare)
    with pytest.raises(InvalidInputError, match="profiles"):
        DemoProfiles.from_dict({"bin_m": 1e-3})


def test_a_session_corridor_follows_a_profile(phantom):
    """The profile sets the corridor's stiffness per depth: the same offset pulls 4x less where
    the stiffness is 4x lower."""
    from dhg.core.session import DrillingSession

    s = DrillingSession(phantom.volume, phantom.path)
    s.set_guidance("corridor", 1.0)
    a, d = phantom.path.entry_m, phantom.path.direction
    helper = np.array([1.0, 0.0, 0.0]) if abs(d[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    side = np.cross(d, helper)
    side /= np.linalg.norm(side)
    from dhg.core.session import poses

    def pull(profile):
        s.reset()
        s.set_corridor_profile(1.0, profile)
        s.set_prediction([0.0, 0.0, 0.0])  # the model is live
        q = (1.0, 0.0, 0.0, 0.0)
        at = np.repeat((a - 20e-3 * d + 1.5e-3 * side)[None, :], 400, axis=0)  # in the air before A
        for _ in range(4):
            s.set_prediction([0.0, 0.0, 0.0])
            s.step(poses(at[:100], q, False, 0.0))
        return float(-(s.state.guidance_n @ side))

    stiff, soft = pull([400.0]), pull([100.0])
    assert stiff > 0.3 and soft == pytest.approx(stiff / 4, rel=0.05), (stiff, soft)
    with pytest.raises(InvalidInputError):
        s.set_corridor_profile(1e-3, [float("nan")])
