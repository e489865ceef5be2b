"""``dhg study``: paired arms offline, statistics, outputs (a 2 × 2 smoke run)."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

from dhg.errors import InvalidInputError
from dhg.study import ARMS, StudyResult, parse_arms


def test_arms_parse_with_gains_and_refuse_nonsense():
    arms = parse_arms("none, shaped@0.5 ,brake")
    assert [(a.name, a.mode, a.gain) for a in arms] == [
        ("none", None, 0.0),
        ("shaped@0.5", "shaped", 0.5),
        ("brake", "brake", 1.0),
    ]
    assert set(ARMS) == {"none", "paper", "corridor", "brake", "shaped"}
    for bad, match in (
        ("stiff", "unknown arm"),
        ("shaped", "first arm"),
        ("none,brake@9", "0..4"),
        ("none,none", "repeat"),
    ):
        with pytest.raises(InvalidInputError, match=match):
            parse_arms(bad)


def test_paired_statistics_are_per_seed_differences():
    arms = parse_arms("none,brake")
    r = StudyResult(
        arms,
        [1, 2, 3],
        {
            "none": [{"plunge_depth_m": v} for v in (0.004, 0.006, 0.008)],
            "brake": [{"plunge_depth_m": v} for v in (0.001, 0.002, 0.004)],
        },
    )
    mean, lo, hi = r.paired("brake", "plunge_depth_m")
    d = np.array([-0.003, -0.004, -0.004])
    assert mean == pytest.approx(d.mean())
    from scipy import stats

    half = stats.t.ppf(0.975, 2) * d.std(ddof=1) / np.sqrt(3)
    assert (lo, hi) == pytest.approx((d.mean() - half, d.mean() + half))


def test_a_study_smoke_run_writes_its_table_json_and_figure(tmp_path):
    out = tmp_path / "study"
    done = subprocess.run(
        [
            sys.executable,
            "-m",
            "dhg.cli",
            "study",
            "--out",
            str(out),
            "--seeds",
            "3,4",
            "--arms",
            "none,shaped",
            "--duration",
            "40",
            "--workers",
            "2",
        ],
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert done.returncode == 0, done.stderr
    table = (out / "results.md").read_text()
    assert "| none |" in table and "| shaped |" in table and "95 % interval" in table
    data = json.loads((out / "results.json").read_text())
    assert data["seeds"] == [3, 4] and set(data["metrics"]) == {"none", "shaped"}
    assert len(data["metrics"]["shaped"]) == 2 and "plunge_depth_m" in data["metrics"]["shaped"][0]
    assert "plunge_depth_m" in data["paired"]["shaped"]
    assert (out / "study.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_study_refuses_bad_arguments_with_exit_code_3(tmp_path):
    done = subprocess.run(
        [sys.executable, "-m", "dhg.cli", "study", "--out", str(tmp_path), "--arms", "shaped"],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert done.returncode == 3 and "first arm" in done.stderr
