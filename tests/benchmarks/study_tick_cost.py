"""What one simulated 1 ms tick of a `dhg study` attempt costs (µs of one core): an unguided
attempt, a guided one answering each model query alone, and 16 guided attempts side by side
whose queries share one batched forward pass (as `dhg study` runs them, `dhg.study.runner._lockstep`).

    python tests/benchmarks/study_tick_cost.py [--duration 20] [--rounds 2]

The three variants alternate `--rounds` times in one run (on a shared VM compare the ratios).
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import torch

from dhg import default_phantom
from dhg.core.path import TaskRules
from dhg.core.session import DrillingSession
from dhg.learning.torchscript import load_model
from dhg.learning.weights import default_model_path
from dhg.operators.episodes import drill_episode, run_episode
from dhg.operators.models import operator_style
from dhg.operators.styles import sample_style
from dhg.study.runner import MODEL_BATCH, _lockstep


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--duration", type=float, default=20.0, help="simulated seconds per attempt (default 20)")
    ap.add_argument("--rounds", type=int, default=2, help="alternations of the three variants (default 2)")
    args = ap.parse_args()
    torch.set_num_threads(1)  # as dhg study's workers run
    phantom = default_phantom(voxel_m=0.5e-3)
    model = load_model(default_model_path())
    rules = TaskRules(max_duration_s=args.duration)

    def hand(seed: int):
        style = sample_style("novice", np.random.default_rng([seed, 1]))
        return operator_style(style, "impedance", np.random.default_rng([seed, 2]))

    def session(mode: str | None) -> DrillingSession:
        s = DrillingSession(phantom.volume, phantom.path)
        s.set_guidance(mode or "paper", 1.0 if mode else 0.0)
        return s

    def one(guided: bool) -> float:
        s = session("shaped" if guided else None)
        t0 = time.perf_counter()
        ep = run_episode(
            s,
            hand(3),
            np.random.default_rng(1),
            rules=rules,
            predictor=(lambda w: model.predict(w)[0]) if guided else None,
            cue_meaning="felt",
        )
        return (time.perf_counter() - t0) / (len(ep.records) * 100) * 1e6

    def batched() -> float:
        sessions = [session("shaped") for _ in range(MODEL_BATCH)]
        jobs = [
            drill_episode(s, hand(3 + k), np.random.default_rng(k), rules=rules, guided=True, cue_meaning="felt")
            for k, s in enumerate(sessions)
        ]
        t0 = time.perf_counter()
        eps = _lockstep(jobs, model.predict)
        return (time.perf_counter() - t0) / (sum(len(e.records) for e in eps) * 100) * 1e6

    variants = {"unguided": lambda: one(False), "guided, one query at a time": lambda: one(True)}
    variants[f"guided, {MODEL_BATCH} attempts batched"] = batched
    results: dict[str, list[float]] = {k: [] for k in variants}
    for _ in range(args.rounds):
        for name, run in variants.items():
            results[name].append(run())
    print(f"µs of one core per simulated 1 ms tick ({args.duration:g} s attempts, {args.rounds} rounds alternating)")
    base = np.median(results["unguided"])
    for name, v in results.items():
        print(f"  {name:32s} {np.median(v):6.1f}  ({', '.join(f'{x:.1f}' for x in v)})  × {np.median(v) / base:.2f}")


if __name__ == "__main__":
    main()
