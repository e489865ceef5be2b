"""Where one `dhg study` attempt spends its time: the model's 10 Hz queries, the virtual
surgeon's 1 kHz Python step and the core's tick (cProfile, one guided novice attempt).

    python tests/benchmarks/study_attempt_profile.py [--duration 30] [--seed 3]

Prints each part's share of the attempt's wall time. Run it on an otherwise idle machine: with
other processes on the cores the shares move.
"""

from __future__ import annotations

import argparse
import cProfile
import pstats

import numpy as np
import torch

from dhg import default_phantom
from dhg.core.path import TaskRules
from dhg.core.session import DrillingSession
from dhg.learning.torchscript import load_model
from dhg.learning.weights import default_model_path
from dhg.operators.episodes import run_episode
from dhg.operators.styles import sample_style


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--duration", type=float, default=30.0, help="most seconds of the attempt (default 30)")
    ap.add_argument("--seed", type=int, default=3, help="novice seed (default 3)")
    args = ap.parse_args()
    torch.set_num_threads(1)  # as dhg study's workers run
    phantom = default_phantom(voxel_m=0.5e-3)
    model = load_model(default_model_path())
    session = DrillingSession(phantom.volume, phantom.path)
    session.set_guidance("shaped", 1.0)
    style = sample_style("novice", np.random.default_rng(args.seed))
    rules = TaskRules(max_duration_s=args.duration)
    prof = cProfile.Profile()
    prof.enable()
    run_episode(
        session,
        style,
        np.random.default_rng([args.seed, 1]),
        rules=rules,
        predictor=lambda w: model.predict(w)[0],
        cue_meaning="felt",
    )
    prof.disable()
    stats = pstats.Stats(prof)
    total = stats.total_tt  # type: ignore[attr-defined]
    parts = {"model queries (GuidanceModel.predict)": 0.0, "surgeon step (Python)": 0.0, "core tick (Rust)": 0.0}
    for (file, _, name), (_, _, _, cum, _) in stats.stats.items():  # type: ignore[attr-defined]
        if name == "predict" and file.endswith("export.py"):
            parts["model queries (GuidanceModel.predict)"] += cum
        elif name == "step" and file.endswith("surgeons.py"):
            parts["surgeon step (Python)"] += cum
        elif "method 'tick'" in name:
            parts["core tick (Rust)"] += cum
    print(f"one {args.duration:g} s attempt (seed {args.seed}, shaped guidance): {total:.2f} s of CPU under cProfile")
    for part, t in parts.items():
        print(f"  {part:40s} {t:6.2f} s  {100 * t / total:5.1f} %")


if __name__ == "__main__":
    main()
