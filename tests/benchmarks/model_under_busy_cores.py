"""Guidance on a host whose cores something else keeps busy: one trainee's 1 kHz stream (drilling
5 mm into the phantom's cortex) against ``dhg-serve --model-nice N``, while ``--hogs`` processes at
nice 0 spin (another program on the server's machine: a browser, a build). The nice values
alternate, a fresh server each; one JSON line per (round, nice): guidance messages received of
the 10 a second the stream asks for, pose → guidance and pose → force p50/p99, and the model's
queries, replies and errors from the server's health.

    python tests/benchmarks/model_under_busy_cores.py --nices 19,10,0 --hogs 2 --rounds 3 --seconds 5

Decision 0038 (the model's worker at nice 10, not 19) is from this script.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # tests/support.py

from dhg.live.client import TraineeClient  # noqa: E402
from support import entry, serve, stream  # noqa: E402


def one(nice: int, hogs: int, seconds: float, name: str) -> dict:
    proc, endpoint = serve("--model-nice", str(nice))
    busy = [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(hogs)]
    try:
        with TraineeClient(endpoint, name) as c:
            a, d, q = entry(c)
            stream(c, a + d * np.linspace(-3e-3, -1e-3, 1000)[:, None], q)  # 1 s in air: the model warms up
            c.guidance.clear()
            wall = stream(c, a + d * np.linspace(-1e-3, 4e-3, int(seconds * 1000))[:, None], q)
            got = len(c.guidance)
            s = c.latency_summary()
            model = c.health(seconds)["model"]
    finally:
        for b in busy:
            b.kill()
            b.wait()
        proc.stop()

    def ms(key: str) -> float:
        return round(s[key] * 1e3, 2)

    return {
        "nice": nice,
        "hogs": hogs,
        "wall_s": round(wall, 2),
        "guidance": got,
        "guidance_asked": round(wall * 10),
        "guidance_p50_ms": ms("pose_to_guidance_p50_s"),
        "guidance_p99_ms": ms("pose_to_guidance_p99_s"),
        "force_p50_ms": ms("pose_to_force_p50_s"),
        "force_p99_ms": ms("pose_to_force_p99_s"),
        "model": {k: model.get(k) for k in ("queries", "replies", "errors")},
    }


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--nices", default="19,10,0", help="dhg-serve --model-nice values, alternated")
    p.add_argument("--hogs", type=int, default=2, help="busy processes at nice 0 beside the server")
    p.add_argument("--rounds", type=int, default=3)
    p.add_argument("--seconds", type=float, default=5.0, help="the measured stream (s)")
    p.add_argument("--out", help="also append the JSON lines to this file")
    args = p.parse_args()
    for r in range(args.rounds):
        for nice in (int(n) for n in args.nices.split(",")):
            line = json.dumps({"round": r, **one(nice, args.hogs, args.seconds, f"busy-{r}-{nice}")})
            print(line, flush=True)
            if args.out:
                with open(args.out, "a") as f:
                    f.write(line + "\n")


if __name__ == "__main__":
    main()
