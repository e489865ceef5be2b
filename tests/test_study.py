"""``dhg study``: the protocol, paired arms offline, statistics, outputs (a 2 × 2 smoke run)."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

from dhg.core.errors import InvalidInputError
from dhg.core.surgeon import MAX_ATTEMPT_S
from dhg.study.runner import ARMS, Protocol, StudyResult, parse_arms, run_study


def test_arms_parse_with_gains_and_refuse_nonsense():
    arms = parse_arms("none, shaped@0.5 ,brake")
    assert [(a.name, a.mode, a.gain) for a in arms] == [
        ("none", None, 0.0),
        ("shaped@0.5", "shaped", 0.5),
        ("brake", "brake", 1.0),
    ]
    assert set(ARMS) == {"none", "paper", "corridor", "brake", "shaped", "shaped-fading"}
    assert ARMS["shaped-fading"].fading and ARMS["shaped-fading"].mode == "shaped"
    for bad, match in (
        ("stiff", "unknown arm"),
        ("shaped", "first arm"),
        ("none,brake@9", "0..4"),
        ("none,none", "repeat"),
    ):
        with pytest.raises(InvalidInputError, match=match):
            parse_arms(bad)


def _attempts(plunges_pre_train_post):
    return [
        [{"phase": ph, "plunge_depth_m": v} for ph, v in zip(("pre", "train", "post"), seed, strict=True)]
        for seed in plunges_pre_train_post
    ]


def test_paired_statistics_are_per_seed_differences():
    arms = parse_arms("none,brake")
    r = StudyResult(
        arms,
        [1, 2, 3],
        {
            "none": _attempts([(0.005, 0.004, 0.003), (0.005, 0.006, 0.005), (0.009, 0.008, 0.004)]),
            "brake": _attempts([(0.005, 0.001, 0.004), (0.005, 0.002, 0.006), (0.009, 0.004, 0.009)]),
        },
    )
    from scipy import stats

    def interval(d):
        half = stats.t.ppf(0.975, len(d) - 1) * d.std(ddof=1) / np.sqrt(len(d))
        return d.mean(), d.mean() - half, d.mean() + half

    # The first training attempt, paired with the unguided arm's.
    assert r.paired("brake", "plunge_depth_m") == pytest.approx(interval(np.array([-0.003, -0.004, -0.004])))
    # The post-test, paired likewise; and post − pre within an arm.
    assert r.paired("brake", "plunge_depth_m", "post") == pytest.approx(interval(np.array([0.001, 0.001, 0.005])))
    assert r.learning("none", "plunge_depth_m") == pytest.approx(interval(np.array([-0.002, 0.0, -0.005])))


def test_a_study_smoke_run_writes_its_tables_json_and_figure(tmp_path):
    out = tmp_path / "study"
    done = subprocess.run(
        [
            sys.executable,
            "-m",
            "dhg.cli.main",
            "study",
            "--out",
            str(out),
            "--seeds",
            "3,4",
            "--arms",
            "none,shaped-fading",
            "--train",
            "2",
            "--probe-every",
            "2",
            "--duration",
            "30",
            "--workers",
            "2",
        ],
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert done.returncode == 0, done.stderr
    table = (out / "results.md").read_text()
    assert "| none |" in table and "| shaped-fading |" in table and "95 % interval" in table
    assert "Post-test" in table and "post-test − pre-test" in table
    data = json.loads((out / "results.json").read_text())
    assert data["seeds"] == [3, 4] and set(data["attempts"]) == {"none", "shaped-fading"}
    assert data["operator"] == "impedance" and data["protocol"]["train"] == 2
    for arm in ("none", "shaped-fading"):
        for atts in data["attempts"][arm]:
            assert [a["phase"] for a in atts] == ["pre", "train", "train", "post"]
            assert atts[-1]["gain"] == 0.0 and "plunge_depth_m" in atts[-1]
    # Both arms start from the same pre-test; the fading arm's second training attempt is a probe.
    assert data["attempts"]["none"][0][0] == data["attempts"]["shaped-fading"][0][0]
    for atts in data["attempts"]["shaped-fading"]:
        assert (atts[1]["gain"], atts[2]["probe"], atts[2]["gain"]) == (1.0, True, 0.0)
    assert all(a["gain"] == 0.0 for atts in data["attempts"]["none"] for a in atts)
    assert "plunge_depth_m" in data["paired_post"]["shaped-fading"]
    assert (out / "study.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_a_protocol_needs_training_and_an_operator_it_knows(tmp_path):
    arms = parse_arms("none,shaped")
    with pytest.raises(InvalidInputError, match="training attempt"):
        run_study([1], arms, tmp_path / "m.ts", Protocol(train=0))
    with pytest.raises(InvalidInputError, match="operator"):
        run_study([1], arms, tmp_path / "m.ts", operator="robot")  # type: ignore[arg-type]
    # An attempt longer than the core's surgeon takes is refused before any attempt runs.
    Protocol(duration_s=MAX_ATTEMPT_S).validate()
    with pytest.raises(InvalidInputError, match="at most 3600 s"):
        run_study([1], arms, tmp_path / "m.ts", Protocol(duration_s=MAX_ATTEMPT_S + 1))


@pytest.mark.parametrize("workers", [1, 2])
def test_a_missing_or_foreign_model_is_its_own_error_not_a_broken_pool(tmp_path, workers):
    from dhg.learning.model_file import ModelFileError

    arms = parse_arms("none,shaped")
    with pytest.raises(ModelFileError, match="no such model file"):
        run_study([1, 2], arms, tmp_path / "missing.ts", workers=workers)
    (tmp_path / "notes.ts").write_text("not a model")
    with pytest.raises(ModelFileError, match="unreadable model file"):
        run_study([1, 2], arms, tmp_path / "notes.ts", workers=workers)


def test_a_protocols_drill_and_guidance_laws_reach_every_attempts_session(coarse_phantom, tmp_path):
    from dhg.study.runner import _LocalStation

    protocol = Protocol(burr_radius_m=2.25e-3, guidance=(("corridor_deadband_m", 0.1e-3),))
    protocol.validate()
    station = _LocalStation(coarse_phantom, None, protocol.guidance, protocol.burr_radius_m)
    assert station.session.config.burr_radius_m == 2.25e-3  # a 4.5 mm drill
    assert station.session._s.config()["burr_radius_m"] == 2.25e-3
    assert station.session.guidance_params["corridor_deadband_m"] == 0.1e-3
    arms = parse_arms("none,shaped")
    with pytest.raises(InvalidInputError, match="burr radius"):
        run_study([1], arms, tmp_path / "m.ts", Protocol(burr_radius_m=0.1))
    with pytest.raises(InvalidInputError, match="unknown guidance parameter 'deadband'"):
        run_study([1], arms, tmp_path / "m.ts", Protocol(guidance=(("deadband", 1e-4),)))
    with pytest.raises(InvalidInputError, match="server's guidance laws"):
        run_study([1], arms, tmp_path / "m.ts", Protocol(guidance=(("corridor_deadband_m", 1e-4),)), live="tcp/x:1")


def test_study_refuses_bad_arguments_with_exit_code_3(tmp_path):
    done = subprocess.run(
        [sys.executable, "-m", "dhg.cli.main", "study", "--out", str(tmp_path), "--arms", "shaped"],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert done.returncode == 3 and "first arm" in done.stderr


def test_a_novices_result_does_not_depend_on_who_shares_its_model_batches():
    """Offline, the model answers many attempts' queries in one batch; a novice run with others
    must drill exactly as when run alone (batched float32 passes of different sizes differ in
    the last bits, and a drilling hand amplifies that)."""
    from dhg.learning.weights import default_model_path

    arms, protocol = parse_arms("none,shaped"), Protocol(train=1, duration_s=12)
    together = run_study([3, 4], arms, default_model_path(), protocol, workers=1)
    alone = run_study([4], arms, default_model_path(), protocol, workers=1)
    for arm in ("none", "shaped"):
        assert together.attempts[arm][1] == alone.attempts[arm][0]
    assert together.attempts["shaped"][1][1]["gain"] == 1.0


def test_replicated_tests_measure_the_same_learned_state_and_change_nothing_else():
    """``test_replicates``: each test is drilled K times from one learned state, each with its own
    hand noise, and reported as their mean; the novice learns from the first alone, so training
    and what it leaves are exactly those of the one-attempt protocol."""
    from dhg.learning.weights import default_model_path

    arms = parse_arms("none,shaped")
    counts: list[tuple[int, int]] = []
    one = run_study([3], arms, default_model_path(), Protocol(train=1), workers=1)
    three = run_study(
        [3],
        arms,
        default_model_path(),
        Protocol(train=1, test_replicates=3),
        workers=1,
        progress=lambda done, total: counts.append((done, total)),
    )
    assert counts[-1] == (11, 11)  # 3 pre-test replicates, then per arm 1 training attempt and 3 post-test ones
    for arm in ("none", "shaped"):
        (pre1, train1, post1), (pre3, train3, post3) = one.attempts[arm][0], three.attempts[arm][0]
        assert train3 == train1  # the same training: learned from replicate 0 only
        for k1, k3 in ((pre1, pre3), (post1, post3)):
            runs = k3["replicates"]
            assert len(runs) == 3 and runs[0] == {k: v for k, v in k1.items() if k in runs[0]}
            deviations = [r["max_deviation_m"] for r in runs]
            assert len(set(deviations)) == 3  # each its own hand noise
            assert k3["max_deviation_m"] == pytest.approx(np.mean(deviations))
            assert three.values(arm, "max_deviation_m", k3["phase"])[0] == pytest.approx(np.mean(deviations))
    with pytest.raises(InvalidInputError, match="test_replicates"):
        run_study([3], arms, default_model_path(), Protocol(test_replicates=0))


@pytest.mark.slow  # make test-all (and CI) runs it; make test leaves it out
def test_a_live_study_drills_through_a_running_server(tmp_path):
    """``dhg study --live``: every attempt is drilled in real time through dhg-serve, which guides
    with its own model; the fading arm's schedule (gain, probe) is the server's, read over control."""
    from dhg.live.client import TraineeClient
    from dhg.live.process import ServerProcess, free_port

    endpoint = f"tcp/127.0.0.1:{free_port()}"
    server = ServerProcess(["--listen", endpoint, "--voxel-mm", "1.0"], echo=False)
    try:
        out = tmp_path / "live"
        cmd = [sys.executable, "-m", "dhg.cli.main", "study", "--out", str(out), "--live", endpoint, "--seeds", "3"]
        cmd += ["--arms", "none,shaped-fading", "--train", "2", "--probe-every", "2", "--duration", "9"]
        done = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
        with TraineeClient(endpoint) as probe:
            left = probe.health()["sessions"]
    finally:
        assert server.stop() == 0
    assert done.returncode == 0, done.stderr
    assert f"live through the server at {endpoint}" in (out / "results.md").read_text()
    data = json.loads((out / "results.json").read_text())
    (none,), (faded,) = data["attempts"]["none"], data["attempts"]["shaped-fading"]
    assert [a["phase"] for a in faded] == ["pre", "train", "train", "post"]
    assert (faded[1]["gain"], faded[1]["probe"], faded[2]["gain"], faded[2]["probe"]) == (1.0, False, 0.0, True)
    assert none[0] == faded[0] and all(a["gain"] == 0.0 for a in none)
    # Each attempt ran: the drill was switched on for seconds, and the tip came from 25 mm before A
    # to the bone at A (A→B is 85.8 mm; this hand then feeds slowly through the soft tissue).
    for a in none + faded[1:]:
        assert a["completion_time_s"] > 1.0 and a["target_distance_m"] < 0.0858 + 0.004
    assert left == 0  # the study closed its sessions: none is left holding a slot
