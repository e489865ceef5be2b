"""How long a virtual surgeon feels a buzz in the guidance of whole 2.5 mm attempts, where the
bone stays below the heat cue's 45 °C, so that any buzz is a cue other than the heat cue read as
one (docs/results.md, "A cue that buzzed").

    python tests/benchmarks/buzz_count.py [--modes shaped,brake,corridor] [--seeds 3..12] [--operator instructed]

Prints, per mode, the seconds of buzz each novice felt and in how many attempts it felt one.
"""

from __future__ import annotations

import argparse

import numpy as np

import dhg
from dhg.core.session import DrillingSession
from dhg.learning.torchscript import load_model
from dhg.learning.weights import default_model_path
from dhg.operators.episodes import run_episode
from dhg.operators.models import cue_meaning, operator_style
from dhg.operators.styles import sample_style


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--modes", default="shaped,brake,corridor")
    p.add_argument("--seeds", default="3..12", help="first..last, or a comma-separated list")
    p.add_argument("--operator", default="instructed", choices=("instructed", "impedance"))
    args = p.parse_args()
    first, _, last = args.seeds.partition("..")
    seeds = range(int(first), int(last) + 1) if last else [int(s) for s in args.seeds.split(",")]
    phantom = dhg.default_phantom()
    model = load_model(default_model_path())
    session = DrillingSession(phantom.volume, phantom.path)
    session.set_corridor_profile(model.profiles.bin_m, model.profiles.corridor_n_per_m)
    for mode in args.modes.split(","):
        felt, peaks = [], []
        for seed in seeds:
            rng = np.random.default_rng(seed)
            style = operator_style(sample_style("novice", rng), args.operator, rng)
            session.set_guidance(mode, 1.0)
            ep = run_episode(session, style, rng, predictor=model.predict, cue_meaning=cue_meaning(args.operator, mode))
            felt.append(ep.extra["buzz_felt_s"])
            peaks.append(ep.metrics["peak_temperature_c"])
        buzzed = sum(f > 0 for f in felt)
        print(
            f"{mode}: buzz felt {np.round(felt, 3).tolist()} s; in {buzzed} of {len(felt)} attempts; "
            f"hottest tip {max(peaks):.1f} °C",
            flush=True,
        )


if __name__ == "__main__":
    main()
