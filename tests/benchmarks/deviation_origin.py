"""Where a first guided attempt's largest deviation comes from: for each novice seed, the
impedance operator drills once unguided and once with ``shaped`` guidance (as the first training
attempt of ``dhg study``, offline, bundled model), and this prints the largest distance from the
segment A→B (``max_deviation_m``), the largest offset across the path (``max_lateral_deviation_m``)
and the depth (mm from A; the path is 85.8 mm long) at which the first peaked.

    python tests/benchmarks/deviation_origin.py 3,4,5,6,7,8
"""

from __future__ import annotations

import sys

import numpy as np
import torch

from dhg import default_phantom
from dhg.core.path import TaskRules
from dhg.learning.torchscript import load_model
from dhg.operators.episodes import run_episode
from dhg.operators.models import Learner, operator_style
from dhg.operators.styles import sample_style
from dhg.study.runner import _LocalStation


def main() -> None:
    from importlib.resources import files

    torch.set_num_threads(1)
    model = load_model(str(files("dhg.learning.weights") / "default.ts"))
    phantom = default_phantom()
    print(f"path length {phantom.path.length_m * 1e3:.1f} mm")
    for seed in (int(s) for s in sys.argv[1].split(",")):
        style = operator_style(
            sample_style("novice", np.random.default_rng([seed, 1])), "impedance", np.random.default_rng([seed, 2])
        )
        cells = []
        for mode in (None, "shaped"):
            station = _LocalStation(phantom, model.profiles)
            station.guide(mode, 1.0)
            ep = run_episode(
                station.session,
                Learner().style(style),
                np.random.default_rng([seed, 1, 1, 1]),
                rules=TaskRules(max_duration_s=150),
                predictor=model.predict if mode else None,
                cue_meaning="felt",
            )
            records = ep.records
            inside = records[:, 8] > 0
            at = np.argmax(np.where(inside, phantom.path.lateral_deviation(records[:, 4:7]), -1.0))
            m = ep.metrics
            cells.append(
                f"{mode or 'none'}: segment {m['max_deviation_m'] * 1e3:.2f} mm at depth {records[at, 8] * 1e3:.1f}, "
                f"across {m['max_lateral_deviation_m'] * 1e3:.2f} mm"
            )
        print(seed, " | ".join(cells), flush=True)


if __name__ == "__main__":
    main()
