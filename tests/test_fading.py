"""Fading guidance offline, the operator models and learning across attempts."""

from __future__ import annotations

import numpy as np
import pytest

from dhg import default_phantom
from dhg.core.errors import InvalidInputError
from dhg.core.path import TaskRules
from dhg.core.session import DrillingSession
from dhg.core.surgeon import SurgeonController
from dhg.operators.episodes import run_episode
from dhg.operators.models import (
    ARM_MASS_KG,
    ARM_STIFFNESS_N_PER_M,
    NOVICE_REACTION_S,
    Learner,
    cue_meaning,
    operator_style,
)
from dhg.operators.scripted import scripted_stylus
from dhg.operators.styles import sample_style


@pytest.fixture(scope="module")
def phantom():
    return default_phantom(voxel_m=0.5e-3)


def test_a_session_fades_its_gain_over_drilled_attempts_and_probes(phantom):
    s = DrillingSession(phantom.volume, phantom.path)
    s.set_guidance("shaped", 1.0)
    s.set_fading({"probe_every": 3, "forget": 0.5, "learn": 0.25})
    assert s.fading["gain"] == 1.0 and s.guidance == ("shaped", 1.0)
    s.reset()
    assert s.fading["attempts"] == 0, "a reset before any pose is not an attempt"
    poses = scripted_stylus(phantom.path, duration_s=6.0)  # into the bone along the line
    gains = []
    for _ in range(4):
        s.step(poses)
        s.reset()
        gains.append(s.guidance[1])
        f = s.fading
        assert f["last_error"] is not None and f["last_error"] >= 0.0
    f = s.fading
    assert f["attempts"] == 4
    # attempt 3 of every 3 is a probe (gain 0); the others get the assistance.
    assert gains[1] == 0.0 and all(g > 0 for i, g in enumerate(gains) if i != 1), gains
    assert not f["probe"] and gains[3] == pytest.approx(f["assistance"])
    s.set_fading(enabled=False)
    assert s.fading is None and s.guidance[1] == pytest.approx(gains[3]), "stopping keeps the gain"
    for bad, match in (({"forget": 1.0}, "forget"), ({"max_gain": 9.0}, "gain"), ({"tempo": 1}, "unknown field")):
        with pytest.raises(InvalidInputError, match=match):
            s.set_fading(bad)


def test_the_impedance_operator_has_the_cited_arm_and_reads_no_cue():
    rng = np.random.default_rng(5)
    base = sample_style("novice", np.random.default_rng(1))
    assert operator_style(base, "instructed", rng) is base
    for _ in range(20):
        st = operator_style(base, "impedance", rng)
        assert 0.8 * ARM_MASS_KG <= st.hand_mass_kg <= 1.2 * ARM_MASS_KG
        assert 0.8 * ARM_STIFFNESS_N_PER_M <= st.arm_stiffness_n_per_m <= 1.2 * ARM_STIFFNESS_N_PER_M
        assert st.lateral_stiffness_n_per_m == st.arm_stiffness_n_per_m
        assert NOVICE_REACTION_S[0] <= st.reaction_delay_s <= NOVICE_REACTION_S[1]
    assert cue_meaning("impedance", "paper") == "felt" and cue_meaning("impedance", "shaped") == "felt"
    assert (cue_meaning("instructed", "paper"), cue_meaning("instructed", "brake")) == ("match", "yield")
    with pytest.raises(ValueError, match="operator"):
        operator_style(base, "robot", rng)  # type: ignore[arg-type]


def test_a_felt_cue_moves_the_hand_only_through_its_force(phantom):
    """The same hand and the same pushing cue: the instructed trainee (told the paper's cue means
    'press like the expert') builds up a lean; the impedance trainee's lean stays 0."""
    style = sample_style("novice", np.random.default_rng(2))
    leans = {}
    for meaning in ("match", "felt"):
        c = SurgeonController(phantom.path, style, np.random.default_rng(3), TaskRules(), cue_meaning=meaning)
        fb = (0.0, 0.0, 0.0, 0.5e-3, 0.0, 30.0, 1, 1, 0, 0, 0.0)
        cue = tuple(-0.5 * phantom.path.direction)  # the cue pushes back: the expert pressed harder
        most = 0.0
        for _ in range(6000):
            if c.step(fb, cue, cue) is None:
                break
            most = max(most, abs(c.lean))
        leans[meaning] = most
    assert leans["match"] > 0.05 and leans["felt"] == 0.0, leans


def test_the_learner_learns_from_errors_and_forgets_without_them():
    base = sample_style("novice", np.random.default_rng(4))
    learner = Learner()
    assert learner.style(base) == base, "nothing learned yet"
    for _ in range(3):
        learner.update(plunge_m=6e-3, max_deviation_m=4e-3)
    learned = learner.anticipation
    st = learner.style(base)
    assert learned > 0.5 and st.anticipates_breakthrough and st.ease_fraction < 1.0
    assert st.drift_m < base.drift_m
    # Guidance that hides the error: the skill decays (forgetting), as in Emken et al. 2007.
    for _ in range(3):
        learner.update(plunge_m=0.0, max_deviation_m=0.0)
    assert learner.anticipation == pytest.approx(learned * learner.forget**3)


def test_a_trained_novice_plunges_less_than_the_same_novice_untrained(phantom):
    """Learning acts where it should: a fully learned anticipation eases the push and braces the
    arm before the planned breakthrough, and shortens the plunge of the same hand with the same
    noise. Over 20 novices (30 s attempts), among those whose untrained hand plunged more than
    3 mm: in total by more than 30 %, and in at least two of three of them."""
    untrained, trained = [], []
    for seed in range(10, 30):
        style = sample_style("novice", np.random.default_rng(seed))
        plunges = {}
        for name, a in (("untrained", 0.0), ("trained", 1.0)):
            s = DrillingSession(phantom.volume, phantom.path)
            rules = TaskRules(max_duration_s=30.0)
            ep = run_episode(s, Learner(anticipation=a).style(style), np.random.default_rng(12), rules=rules)
            plunges[name] = ep.metrics["plunge_depth_m"]
        if plunges["untrained"] > 3e-3:
            untrained.append(plunges["untrained"])
            trained.append(plunges["trained"])
    u, t = np.array(untrained), np.array(trained)
    assert len(u) >= 5, f"only {len(u)} untrained novices plunged more than 3 mm"
    assert t.sum() < 0.7 * u.sum(), f"trained {t} m vs untrained {u} m"
    assert np.mean(t < u) >= 2 / 3, f"trained {t} m vs untrained {u} m"
