"""How much of one unguided attempt's plunge is the hand's noise (issue 20, ``dhg study
--test-replicates``): each `dhg study` novice drills unguided from fixed learned states
(``Learner`` anticipation = steadiness = 0, 0.5, 1) several times, each with its own hand noise
(the study's attempt seeds). Prints per learned state the mean plunge, the spread between novices
(of their means) and within a novice (the noise of one attempt), and the paired difference
between learned in full and not at all, with the same noise draw and with different ones.
The figures behind docs/results.md, "Measuring what was learned".

    python tests/benchmarks/plunge_noise.py --operator impedance --seeds 1000-1011 --draws 4
    python tests/benchmarks/plunge_noise.py --operator instructed --seeds 1000-1011 --draws 4
"""

from __future__ import annotations

import argparse
from concurrent.futures import ProcessPoolExecutor

import numpy as np

STATES = (0.0, 0.5, 1.0)


def _plunge_mm(job: tuple[int, float, int, str]) -> float:
    from dhg import default_phantom
    from dhg.core.path import TaskRules
    from dhg.core.session import DrillingSession, SessionConfig
    from dhg.operators.episodes import run_episode
    from dhg.operators.models import Learner, cue_meaning, operator_style
    from dhg.operators.styles import sample_style

    seed, state, draw, operator = job
    phantom = default_phantom(voxel_m=0.5e-3)
    session = DrillingSession(phantom.volume, phantom.path, SessionConfig())
    base = operator_style(  # the study's novice (dhg.study.runner._job)
        sample_style("novice", np.random.default_rng([seed, 1])), operator, np.random.default_rng([seed, 2])
    )
    style = Learner(anticipation=state, steadiness=state).style(base)
    rng = np.random.default_rng([seed, 1, 1, 0] + ([draw] if draw else []))  # a test's replicates
    rules = TaskRules(max_duration_s=150.0)
    ep = run_episode(session, style, rng, rules=rules, cue_meaning=cue_meaning(operator, None))
    return float(ep.metrics["plunge_depth_m"]) * 1e3


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--operator", choices=("impedance", "instructed"), default="impedance")
    ap.add_argument("--seeds", default="1000-1011", help="novice seeds, FIRST-LAST")
    ap.add_argument("--draws", type=int, default=4, help="noise draws per novice and learned state")
    ap.add_argument("--workers", type=int, default=2)
    args = ap.parse_args()
    first, _, last = args.seeds.partition("-")
    seeds = list(range(int(first), int(last or first) + 1))
    jobs = [(s, a, d, args.operator) for s in seeds for a in STATES for d in range(args.draws)]
    with ProcessPoolExecutor(args.workers) as pool:
        flat = list(pool.map(_plunge_mm, jobs))
    plunge = np.array(flat).reshape(len(seeds), len(STATES), args.draws)  # (novice, state, draw)
    print(f"{args.operator} operator, seeds {seeds[0]}..{seeds[-1]}, {args.draws} noise draws each; plunge (mm)")
    print("| learned | mean | SD between novices (of their means) | SD within a novice (one attempt) |")
    print("|---:|---:|---:|---:|")
    for k, a in enumerate(STATES):
        m = plunge[:, k, :]
        within = float(np.sqrt(m.var(axis=1, ddof=1).mean()))
        print(f"| {a:g} | {m.mean():.2f} | {m.mean(axis=1).std(ddof=1):.2f} | {within:.2f} |")
    same = plunge[:, -1, :] - plunge[:, 0, :]
    other = plunge[:, -1, :] - np.roll(plunge[:, 0, :], 1, axis=1)
    print(
        f"learned in full − not at all: {same.mean():+.2f} mm; SD of one paired difference "
        f"{same.std(ddof=1):.2f} (same noise draw), {other.std(ddof=1):.2f} (different draws)"
    )


if __name__ == "__main__":
    main()
