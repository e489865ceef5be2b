"""The virtual surgeon's response to a guidance cue (the operator model behind ``dhg trainee``)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from dhg.bone.planning import layer_runs, planned_breakthrough_depth_m
from dhg.core.errors import InvalidInputError
from dhg.core.features import TICK_S
from dhg.core.layers import Layer
from dhg.core.path import PlannedPath, TaskRules
from dhg.core.surgeon import MAX_ATTEMPT_S, SurgeonController
from dhg.core.volume import DrilledVolume
from dhg.operators.styles import sample_style

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
    """No cue, no lean: given only the force the device renders (the bone pushing back), a hand
    that follows cues drives exactly the poses of one that never follows them; the same force
    with a guidance share in it makes the follower drive differently."""
    bone_back = (0.0, 0.0, -1.0)

    def rows(follow_per_s: float | None, cue_n: tuple[float, float, float] | None) -> list[tuple[float, ...]]:
        rng = np.random.default_rng(5)
        style = sample_style("novice", rng)
        if follow_per_s is not None:
            style = dataclasses.replace(style, cue_follow_per_s=follow_per_s)
        surgeon = SurgeonController(PATH, style, rng)
        # In cortex, 1 mm deep: the feed controller is pushing, and would lean on a cue.
        feedback = (0.0, 0.0, 1e-3, 1e-3, 0.0, 37.0, int(Layer.CORTICAL), True, 0, False, 0.0)
        out = []
        for _ in range(3000):
            step = surgeon.step(feedback, bone_back) if cue_n is None else surgeon.step(feedback, bone_back, cue_n)
            if step is None:
                break
            out.append(step)
        return out

    style = sample_style("novice", np.random.default_rng(5))
    assert style.cue_follow_per_s > 0, "the sampled novice must follow cues for this test to mean anything"
    unguided = rows(None, None)
    assert len(unguided) > 1000
    assert unguided == rows(0.0, None), "without a cue, following cues changed the hand"
    assert rows(None, (0.0, 0.0, -0.4)) != unguided, "a cue in the same force changed nothing"
    assert rows(0.0, (0.0, 0.0, -0.4)) == unguided, "a hand that never follows cues read the cue"


def _expert_push_at(depth_m: float, breakthrough_depth_m: float | None, seconds: float = 5.0) -> float:
    """The push (N) an expert means to make after ``seconds`` (past the approach and alignment)
    while the tip is perceived stalled in cortex at ``depth_m``: the feed controller has raised it
    to the layer's ceiling."""
    rng = np.random.default_rng(8)
    style = dataclasses.replace(sample_style("expert", rng), noise_fraction=0.0, caution_temp_c=90.0)
    surgeon = SurgeonController(PATH, style, rng, breakthrough_depth_m=breakthrough_depth_m)
    feedback = (0.0, 0.0, depth_m, depth_m, 0.0, 37.0, int(Layer.CORTICAL), True, 0, False, 0.0)
    for _ in range(int(seconds * 1000)):
        surgeon.step(feedback, (0.0, 0.0, -1.0))  # the bone pushes back with 1 N
    assert surgeon.phase == "feed"
    return surgeon.push


def test_an_expert_eases_off_before_the_planned_breakthrough():
    """1.5 mm into the cortex: an expert whose plan says the cortex gives at 1.7 mm pushes only
    the eased push, one whose plan says 6 mm still pushes its full cortical push."""
    style = sample_style("expert", np.random.default_rng(8))
    near = _expert_push_at(1.5e-3, breakthrough_depth_m=1.7e-3)
    far = _expert_push_at(1.5e-3, breakthrough_depth_m=6e-3)
    assert abs(far - style.push_cortical_n) < 1e-9, f"far {far} N vs {style.push_cortical_n} N"
    assert abs(near - style.ease_fraction * style.push_cortical_n) < 1e-9, f"near {near} N"
    assert near < 0.95 * far


def test_the_planned_breakthrough_is_where_the_first_cortex_ends_less_the_burr(coarse_phantom):
    bone = DrilledVolume(coarse_phantom.volume)
    runs = layer_runs(bone, coarse_phantom.path)
    first_cortex_end = next(end for name, _, end in runs if name == "cortical")
    planned = planned_breakthrough_depth_m(coarse_phantom.volume, coarse_phantom.path, 1.25e-3)
    assert planned is not None
    assert abs(planned - (first_cortex_end - 1.25e-3)) <= 0.25e-3
    # A path through air crosses no cortex.
    far = np.array([1.0, 1.0, 1.0])
    assert planned_breakthrough_depth_m(coarse_phantom.volume, PlannedPath(far, far + 0.01), 1.25e-3) is None


def test_the_offset_across_the_path_leaves_out_the_overshoot_past_b():
    from dhg.core.path import TaskRules
    from dhg.core.skill import skill_metrics

    path = PlannedPath(np.zeros(3), np.array([0.0, 0.0, 0.08]))
    # Tips: before A (not counted), 1 mm off inside, on the line past B by 3 mm, 0.5 mm off past B.
    tips = np.array([[2e-3, 0, -1e-3], [1e-3, 0, 0.04], [0, 0, 0.083], [0.5e-3, 0, 0.082]])
    np.testing.assert_allclose(path.offset_from_line(tips), [2e-3, 1e-3, 0.0, 0.5e-3], atol=1e-15)
    np.testing.assert_allclose(path.lateral_deviation(tips)[2], 3e-3, rtol=1e-9)  # the segment's distance
    records = np.zeros((len(tips), 11))
    records[:, 4:7] = tips
    records[:, 8] = tips[:, 2]  # depth along A→B (the path is along z)
    m = skill_metrics(records, path, TaskRules(), tips[-1], 10.0, 0.0, 40.0, 0.0)
    assert m["max_deviation_m"] == pytest.approx(3e-3)
    assert m["max_lateral_deviation_m"] == pytest.approx(1e-3)


def test_no_cue_but_the_heat_cue_is_felt_as_a_buzz(phantom):
    """A surgeon told what ``shaped``'s heat cue means pauses with the drill off while a vibration
    is felt in the guidance. Only the heat cue may read as one: with the 2.5 mm drill the bone
    stays below the cue's 45 °C, so the brake's damper, the corridor's pull and the warning of a
    whole guided attempt must never be felt as a buzz (nor, told nothing, by an impedance arm)."""
    from dhg.core.session import DrillingSession
    from dhg.learning.torchscript import load_model
    from dhg.learning.weights import default_model_path
    from dhg.operators.episodes import run_episode
    from dhg.operators.models import cue_meaning, operator_style

    model = load_model(default_model_path())
    session = DrillingSession(phantom.volume, phantom.path)
    profiles = model.profiles
    session.set_corridor_profile(profiles.bin_m, profiles.corridor_n_per_m)
    breakthrough_m = planned_breakthrough_depth_m(phantom.volume, phantom.path, session.config.burr_radius_m)
    for seed, mode, operator in ((3, "shaped", "instructed"), (4, "brake", "instructed"), (5, "shaped", "impedance")):
        rng = np.random.default_rng(seed)
        style = operator_style(sample_style("novice", rng), operator, rng)
        session.set_guidance(mode, 1.0)
        ep = run_episode(session, style, rng, predictor=model.predict, cue_meaning=cue_meaning(operator, mode))
        assert ep.metrics["peak_temperature_c"] < 45.0, "the heat cue was on: the test says nothing"
        assert ep.records[:, 8].max() > breakthrough_m, "the attempt ended before the breakthrough"
        assert ep.extra["buzz_felt_s"] == 0.0, (seed, mode, operator, ep.extra)


@pytest.mark.parametrize("seconds", [MAX_ATTEMPT_S * 1.01, 1e17])
def test_an_attempt_longer_than_the_core_allows_is_refused_not_a_panic(seconds):
    """A duration of 1e17 s used to size the kept raw ticks by it: pyo3's PanicException
    ("capacity overflow"), which ``except Exception`` does not catch."""
    style = sample_style("novice", np.random.default_rng(1))
    with pytest.raises(InvalidInputError, match="max_duration_s"):
        SurgeonController(PATH, style, np.random.default_rng(1), TaskRules(max_duration_s=seconds), keep_raw=True)
    longest = SurgeonController(
        PATH, style, np.random.default_rng(1), TaskRules(max_duration_s=MAX_ATTEMPT_S), keep_raw=True
    )
    assert longest.max_ticks == round(MAX_ATTEMPT_S / TICK_S)


@pytest.mark.parametrize(
    ("index", "value", "said"),
    [(3, float("nan"), "feedback"), (6, 9, "layer id"), (6, 1.5, "layer id"), (8, -1, "breakthroughs")],
)
def test_a_surgeon_refuses_feedback_it_cannot_read(index, value, said):
    """A NaN depth used to steer the hand to a NaN pose, and an unknown layer id read as outside."""
    surgeon = SurgeonController(PATH, sample_style("novice", np.random.default_rng(2)), np.random.default_rng(2))
    good = [0.0, 0.0, 1e-3, 1e-3, 0.0, 37.0, int(Layer.CORTICAL), True, 0, False, 0.0]
    assert surgeon.step(tuple(good), (0.0, 0.0, 0.0)) is not None
    bad = list(good)
    bad[index] = value
    with pytest.raises(InvalidInputError, match=said):
        surgeon.step(tuple(bad), (0.0, 0.0, 0.0))
    with pytest.raises(InvalidInputError, match="force_n"):
        surgeon.step(tuple(good), (0.0, float("inf"), 0.0))
