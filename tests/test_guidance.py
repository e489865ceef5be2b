"""The guidance modes through the Python API of an offline session (the same core as dhg-serve)."""

from __future__ import annotations

import numpy as np
import pytest

from dhg.core.errors import InvalidInputError, ShapeError
from dhg.core.session import GUIDANCE_MODES, DrillingSession
from support import tool_quaternion as _axis_quaternion


def test_modes_gain_and_predictions_are_checked(coarse_phantom):
    s = DrillingSession(coarse_phantom.volume, coarse_phantom.path)
    assert GUIDANCE_MODES == ("paper", "corridor", "brake", "shaped")
    assert s.guidance == ("paper", 0.0), "an offline session renders no guidance until asked"
    with pytest.raises(InvalidInputError, match="paper, corridor, brake, shaped"):
        s.set_guidance("stiff", 1.0)  # type: ignore[arg-type]
    with pytest.raises(InvalidInputError, match="gain"):
        s.set_guidance("shaped", 5.0)
    assert s.guidance == ("paper", 0.0)
    s.set_guidance("shaped", 2.0)
    assert s.guidance == ("shaped", 2.0)
    with pytest.raises(ShapeError):
        s.set_prediction([1.0, 2.0])
    with pytest.raises(InvalidInputError, match="finite"):
        s.set_prediction([np.nan, 0.0, 0.0])
    # The paper's guidance as mixed: gain × (predicted − feedback), clamped to 0.88 N.
    np.testing.assert_allclose(s.set_prediction([0.0, 0.0, 0.3]), [0.0, 0.0, 0.6])
    assert np.linalg.norm(s.set_prediction([5.0, 0.0, 0.0])) == pytest.approx(0.88)
    planned = s.planned_breakthrough_depth_m
    assert planned is not None and 1e-3 < planned < 5e-3


def test_the_corridor_pulls_a_stylus_back_to_the_path_and_the_record_keeps_the_bone_force(coarse_phantom):
    path = coarse_phantom.path
    s = DrillingSession(coarse_phantom.volume, path)
    s.set_guidance("corridor", 1.0)
    helper = np.array([1.0, 0.0, 0.0])
    side = np.cross(path.direction, helper)
    side /= np.linalg.norm(side)
    q = _axis_quaternion(path.direction)
    at = path.entry_m - 10e-3 * path.direction + 2e-3 * side
    for tick in range(600):
        if tick % 100 == 0:
            s.set_prediction(s.state.feedback_n)  # a model that says "as you are": no paper cue
        force, record = s.tick(at, q, True, 1200.0)
    st = s.state
    assert st.model_available
    assert st.guidance_n @ side < -0.3 and abs(st.guidance_n @ path.direction) < 1e-9
    np.testing.assert_allclose(st.force_n, st.feedback_n + st.guidance_n, atol=1e-12)
    assert record is not None
    np.testing.assert_allclose(record[1:4], st.feedback_n, atol=1e-12), "records hold the bone's force"


def test_guidance_laws_are_settable_offline_and_change_what_the_corridor_renders(coarse_phantom):
    """``set_guidance_params``: the core's laws by name (a study varies them, `dhg study
    --guidance-param`); a stylus 0.4 mm off the line is inside the default 0.5 mm deadband, and
    outside a 0.1 mm one."""
    path = coarse_phantom.path
    side = np.cross(path.direction, [1.0, 0.0, 0.0])
    side /= np.linalg.norm(side)
    q = _axis_quaternion(path.direction)
    at = path.entry_m - 10e-3 * path.direction + 0.4e-3 * side

    def pull(**laws) -> float:
        s = DrillingSession(coarse_phantom.volume, path)
        s.set_guidance("corridor", 1.0)
        if laws:
            s.set_guidance_params(**laws)
        for tick in range(300):
            if tick % 100 == 0:
                s.set_prediction(s.state.feedback_n)
            s.tick(at, q, True, 1200.0)
        return float(-s.state.guidance_n @ side)

    s = DrillingSession(coarse_phantom.volume, path)
    assert s.guidance_params["corridor_deadband_m"] == 0.5e-3
    assert pull() == 0.0
    assert pull(corridor_deadband_m=0.1e-3) > 0.05  # 0.3 mm past the deadband at up to 400 N/m
    with pytest.raises(InvalidInputError, match="unknown field `corridor_deadband`"):
        s.set_guidance_params(corridor_deadband=0.1e-3)
    with pytest.raises(InvalidInputError):
        s.set_guidance_params(corridor_deadband_m=-1.0)
    assert s.guidance_params["corridor_deadband_m"] == 0.5e-3, "a refused change leaves the laws as they were"
