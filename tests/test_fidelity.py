"""The simulator's fidelity contract through the Python API (issue 19): breakthroughs on the
phantom, the sanity limits on poses, the device's continuous limit."""

from __future__ import annotations

import numpy as np
import pytest

import dhg
from dhg.bone.planning import planned_breakthrough_depth_m
from dhg.core.session import MAX_POSITION_M, MAX_SPINDLE_RPM, DrillingSession
from dhg.core.surgeon import SurgeonController
from dhg.operators.styles import sample_style
from support import tool_quaternion

BREAKTHROUGHS, PLUNGE = 8, 10  # indices in the session's feedback tuple


def _novice_attempt(phantom: dhg.Phantom, seed: int, index: int, attempt: int) -> dict[str, float]:
    """One novice attempt of ``dhg synth --seed SEED`` (subject ``index``, attempt ``attempt``),
    tick by tick: where each breakthrough came, the plunge reported, and how far the tip ran."""
    session = DrillingSession(phantom.volume, phantom.path)
    native = session._s
    style = sample_style("novice", np.random.default_rng([seed, 1, index]))
    rng = np.random.default_rng([seed, 1, index, attempt + 1])
    planned = planned_breakthrough_depth_m(phantom.volume, phantom.path, session.config.burr_radius_m)
    surgeon = SurgeonController(phantom.path, style, rng, breakthrough_depth_m=planned)
    force = (0.0, 0.0, 0.0)
    depths: list[float] = []
    bt_ticks: list[int] = []
    while (row := surgeon.step(native.feedback(), force)) is not None:
        f, _ = native.tick(row)
        force = (float(f[0]), float(f[1]), float(f[2]))
        fb = native.feedback()
        depths.append(fb[3])
        if fb[BREAKTHROUGHS] > len(bt_ticks):
            bt_ticks.append(len(depths) - 1)
    out: dict[str, float] = {"breakthroughs": float(len(bt_ticks)), "planned_m": float(planned or np.nan)}
    if bt_ticks:
        t0 = bt_ticks[0]
        out["at_m"] = depths[t0]
        # How far the tip ran on after the cortex gave way, until the trainee pulled it back.
        deepest = depths[t0]
        for d in depths[t0:]:
            if d < deepest - 0.5e-3:
                break
            deepest = max(deepest, d)
        out["ran_m"] = deepest - depths[t0]
        out["plunge_m"] = float(surgeon.max_plunge)
    return out


SKID_AT_ENTRY = pytest.mark.xfail(
    strict=True,
    reason="known defect: a skid on the curved lateral cortex at the entry, the burr's front meeting "
    "air ahead after boring 0.8 mm, reads as a breakthrough 0.04 mm deep (1 of 30 novice attempts)",
)


@pytest.mark.parametrize(
    "index,attempt", [(0, 0), (0, 1), (1, 0), (1, 1), (2, 0), pytest.param(2, 1, marks=SKID_AT_ENTRY)]
)
def test_the_novices_of_the_issue_break_through_once_at_the_cortex_and_their_plunge_is_measured(
    phantom, index, attempt
):
    """The novices of ``dhg synth --subjects 3 --attempts 2 --novices 3 --seed 4242``: each breaks
    through exactly once, where the plan says the cortex ends, and the plunge reported covers how
    far the tip ran on. (Issue 19 found a missed breakthrough, a false one at 0.32 mm and a
    0.05 mm plunge reported for a 3.57 mm advance among them; since the surgeon's noise comes
    from the core's generator they are other attempts, and novice 1's two attempts, whose tips
    gathered speed only after the cortex's first 100 ms of giving way, were reported as 0.29 and
    0.44 mm plunges for 3.2 and 2.5 mm of travel until the plunge's end was judged no sooner
    than a hand can react.)"""
    run = _novice_attempt(phantom, 4242, index, attempt)
    assert run["breakthroughs"] == 1, run
    assert abs(run["at_m"] - run["planned_m"]) < 1e-3, run
    assert run["plunge_m"] >= run["ran_m"] - 0.5e-3, run
    assert run["plunge_m"] <= run["ran_m"] + 1e-9, run


def test_poses_outside_physical_bounds_are_refused_and_counted(coarse_phantom):
    s = DrillingSession(coarse_phantom.volume, coarse_phantom.path)
    a = coarse_phantom.path.entry_m - 5e-3 * coarse_phantom.path.direction
    s.tick(a, drill_on=True, spindle_rpm=1200.0)
    assert MAX_SPINDLE_RPM == 2000.0 and MAX_POSITION_M == 10.0
    for position, rpm in (
        (a, 3.4e38),
        (a, MAX_SPINDLE_RPM * 1.01),
        (np.array([1e30, 0.0, 0.0]), 1200.0),
        (a + np.array([0.0, 0.0, MAX_POSITION_M * 1.1]), 1200.0),
    ):
        before = s.state.rejected_poses
        force, _ = s.tick(position, drill_on=True, spindle_rpm=rpm)
        assert s.state.rejected_poses == before + 1
        assert np.all(np.isfinite(force)) and np.all(np.isfinite(s.state.tip_m))
    s.tick(a, drill_on=True, spindle_rpm=MAX_SPINDLE_RPM)
    assert s.state.rejected_poses == 4
    assert s.state.temperature_c < 60.0


def test_a_long_press_settles_at_the_continuous_force(coarse_phantom):
    """Pressing the stylus into bone with the drill off: the Touch's peak is allowed at first, and
    after its motors' thermal budget is used the force settles at the 0.88 N continuous rating,
    never above it for long."""
    s = DrillingSession(coarse_phantom.volume, coarse_phantom.path)
    path = coarse_phantom.path
    q = tool_quaternion(path.direction)
    approach = path.point_at(np.linspace(-6e-3, 10e-3, 800))
    rows = dhg.core.session.poses(np.vstack([approach, np.repeat(approach[-1:], 30_000, axis=0)]), q, False, 0.0)
    forces = np.linalg.norm(s.step(rows).forces_n, axis=1)
    peak = s.config.device.peak_force_n
    cont = s.config.device.continuous_force_n
    assert forces.max() == pytest.approx(peak)
    assert forces[-1] == pytest.approx(cont, abs=0.01)
    assert s.state.device_thermal_load <= 1.0 + 1e-12
