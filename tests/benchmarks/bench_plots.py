"""What drawing an attempt's timeline PNG costs (``dhg.data.plots.plot_timeline``: ``dhg inspect
--plot``, ``make demo``'s plot, a trainee page's attempt summary), for ten minutes of 10 Hz
records crossing five layer runs. With ``--other PYTHONPATH`` (another build's ``python`` folder,
e.g. from ``git archive``) each round times that build too, alternating, each in a fresh process.

Usage: python tests/benchmarks/bench_plots.py [--records 6000] [--rounds 3] [--other DIR]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
from pathlib import Path

_CHILD = """
import json, sys, tempfile, time
import numpy as np
from dhg.core.features import FEATURE_INDEX
from dhg.data.plots import plot_timeline
n = int(sys.argv[1])
t = np.arange(1, n + 1) * 0.1
feats = np.zeros((n, 9))
feats[:, FEATURE_INDEX["layer"]] = np.repeat([0, 1, 2, 1, 0], -(-n // 5))[:n]
feats[:, FEATURE_INDEX["temperature_c"]] = 37.0
with tempfile.TemporaryDirectory() as d:
    t0 = time.perf_counter()
    plot_timeline(t, feats[:, 0:3], t, feats, f"{d}/a.png", "bench")
    print(json.dumps({"seconds": time.perf_counter() - t0}))
"""


def run(pythonpath: str | None, records: int) -> float:
    env = dict(os.environ)
    if pythonpath is not None:
        env["PYTHONPATH"] = pythonpath
    out = subprocess.run(
        [sys.executable, "-c", _CHILD, str(records)], env=env, capture_output=True, text=True, check=True
    )
    return float(json.loads(out.stdout.strip().splitlines()[-1])["seconds"])


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--records", type=int, default=6000, help="10 Hz records (default 6000: ten minutes)")
    p.add_argument("--rounds", type=int, default=3)
    p.add_argument("--other", metavar="DIR", help="another build's python folder, timed alternately")
    args = p.parse_args()
    builds = {"this": None} | ({"other": str(Path(args.other).resolve())} if args.other else {})
    for r in range(args.rounds):
        for name, path in builds.items():
            print(json.dumps({"round": r, "build": name, "records": args.records, "seconds": run(path, args.records)}))


if __name__ == "__main__":
    main()
