"""The virtual surgeon's response to a guidance cue (the operator model behind ``dhg trainee``)."""

from __future__ import annotations

import dataclasses

import numpy as np

from dhg.layers import Layer
from dhg.surgeons import SurgeonController, sample_style
from dhg.task import PlannedPath

PATH = PlannedPath(np.array([0.0, 0.0, 0.0]), np.array([0.0, 0.0, 0.08]))


def _drive(cue_along_d_n: float, follow_per_s: float | None = None, seconds: float = 4.0) -> float:
    """Feeds a novice hand in cortical bone at a fixed depth, with the device rendering only a
    constant cue along the drill (N). Returns how far along A→B the hand ended (m)."""
    rng = np.random.default_rng(3)
    style = sample_style("novice", rng)
    style = dataclasses.replace(style, hesitations_per_s=0.0, noise_fraction=0.0)
    if follow_per_s is not None:
        style = dataclasses.replace(style, cue_follow_per_s=follow_per_s)
    surgeon = SurgeonController(PATH, style, rng)
    # In cortex, 1 mm deep, not moving: the feed controller wants more push, up to its ceiling.
    feedback = (0.0, 0.0, 1e-3, 1e-3, 0.0, 37.0, int(Layer.CORTICAL), True, 0, False, 0.0)
    cue = (0.0, 0.0, cue_along_d_n)
    row = None
    for _ in range(int(seconds * 1000)):
        step = surgeon.step(feedback, cue, cue)
        if step is None:
            break
        row = step
    assert row is not None
    return float(row[2])


def test_a_trainee_leans_into_a_cue_that_pushes_back():
    """A cue pushing the drill back means "the expert pressed harder": the trainee who follows it
    pushes harder and ends further along than a passive hand, which only gets pushed back."""
    passive = _drive(-0.4, follow_per_s=0.0)
    follows = _drive(-0.4)
    assert follows > passive + 1e-3, f"passive {passive * 1e3:.2f} mm, following {follows * 1e3:.2f} mm"


def test_a_trainee_eases_off_when_the_cue_pulls_in():
    """A cue pulling the drill in means "the expert pressed less": the follower ends behind the
    passive hand that the cue simply drags forward."""
    passive = _drive(0.4, follow_per_s=0.0)
    follows = _drive(0.4)
    assert follows < passive - 1e-3, f"passive {passive * 1e3:.2f} mm, following {follows * 1e3:.2f} mm"


def test_without_a_cue_the_hand_is_the_unguided_one():
    """No cue, no lean: the same seed drives the same poses with or without the cue argument."""

    def rows(with_cue: bool) -> list[tuple[float, ...]]:
        rng = np.random.default_rng(5)
        surgeon = SurgeonController(PATH, sample_style("novice", rng), rng)
        feedback = (0.0, 0.0, 0.0, 0.0, 0.0, 37.0, 0, False, 0, False, 0.0)
        out = []
        for _ in range(3000):
            step = surgeon.step(feedback, (0.0, 0.0, 0.0), (0.0, 0.0, 0.0)) if with_cue else surgeon.step(
                feedback, (0.0, 0.0, 0.0)
            )
            assert step is not None
            out.append(step)
        return out

    assert rows(True) == rows(False)
