"""What the virtual surgeon's 1 kHz step costs in the core against the Python step it replaced
(µs of one core per simulated 1 ms tick, unguided, one impedance novice, 20 s attempts).

    python tests/benchmarks/surgeon_step_cost.py [--before 795e2a6] [--rounds 3] [--subjects 12]

The Python surgeon is read from git at the commit ``--before`` (the last one that had it) and run
against today's core; the two alternate ``--rounds`` times in one run (on a shared VM compare the
ratio). Both drill the same style; their random draws differ, so their attempts are not the same
attempt, only the same kind: with ``--subjects N`` it also drills N experts and N novices (full
attempts, seeds 10..) with each and prints their mean skill metrics side by side.
"""

from __future__ import annotations

import argparse
import importlib.util
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from dhg import default_phantom
from dhg.core.path import TaskRules
from dhg.core.session import DrillingSession
from dhg.operators.episodes import run_episode
from dhg.operators.models import operator_style
from dhg.operators.styles import sample_style


def _python_surgeons(commit: str):
    root = Path(__file__).resolve().parents[2]
    text = subprocess.run(
        ["git", "show", f"{commit}:python/dhg/surgeons.py"], cwd=root, capture_output=True, text=True, check=True
    ).stdout
    path = Path(tempfile.mkdtemp()) / "python_surgeons.py"
    path.write_text(text)
    spec = importlib.util.spec_from_file_location("python_surgeons", path)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules["python_surgeons"] = module
    spec.loader.exec_module(module)
    return module


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--before", default="795e2a6", help="commit with the Python surgeon (default 795e2a6)")
    ap.add_argument("--rounds", type=int, default=3, help="alternations (default 3)")
    ap.add_argument("--subjects", type=int, default=0, help="also compare N experts and N novices (default 0)")
    args = ap.parse_args()
    before = _python_surgeons(args.before)
    phantom = default_phantom(voxel_m=0.5e-3)
    rules = TaskRules(max_duration_s=20.0)
    novice = sample_style("novice", np.random.default_rng([3, 1]))
    style = operator_style(novice, "impedance", np.random.default_rng([3, 2]))
    variants = {"Python step (before)": before.run_episode, "core step (after)": run_episode}
    results: dict[str, list[float]] = {k: [] for k in variants}
    for _ in range(args.rounds):
        for name, run in variants.items():
            s = DrillingSession(phantom.volume, phantom.path)
            t0 = time.perf_counter()
            ep = run(s, style, np.random.default_rng(1), rules=rules, cue_meaning="felt")
            results[name].append((time.perf_counter() - t0) / (len(ep.records) * 100) * 1e6)
    after = float(np.median(results["core step (after)"]))
    print(f"µs of one core per simulated 1 ms tick ({args.rounds} rounds alternating)")
    for name, v in results.items():
        print(f"  {name:22s} {np.median(v):5.1f}  ({', '.join(f'{x:.1f}' for x in v)})  × {np.median(v) / after:.2f}")
    if args.subjects:
        agreement(before, phantom, args.subjects)


def agreement(before, phantom, n: int) -> None:
    """Mean skill metrics of ``n`` experts and ``n`` novices with each surgeon."""
    keys = ["plunge_depth_m", "max_lateral_deviation_m", "completion_time_s", "target_distance_m"]
    for skill in ("expert", "novice"):
        means = {}
        for name, run in (("Python", before.run_episode), ("core", run_episode)):
            rows = []
            for seed in range(10, 10 + n):
                style = sample_style(skill, np.random.default_rng([seed, 1]))
                ep = run(DrillingSession(phantom.volume, phantom.path), style, np.random.default_rng(seed))
                rows.append([ep.metrics[k] for k in keys])
            means[name] = np.mean(rows, axis=0)
        print(
            f"{n} {skill}s, mean "
            + ", ".join(f"{k} {means['core'][i]:.4g} (Python {means['Python'][i]:.4g})" for i, k in enumerate(keys))
        )


if __name__ == "__main__":
    main()
