"""Do live virtual experts plunge less when they plan the breakthrough from the session's planned
layers (``path_layers`` in the session info) than with the generic 2.2 mm? Starts ``dhg-serve``
(phantom, bundled model) on a free loopback port and, for each seed, drills the same expert hand
unguided twice: once with the plan, once with the generic depth. Prints each run's plunge (mm),
its pace (share of 1 kHz poses sent) and distance to B (mm), then the paired difference ± SE.

    python tests/benchmarks/expert_plan_live.py --seeds 0,1,2,3,4,5 --duration 70

Real time: the runs go two at a time, each ``--duration`` seconds.
"""

from __future__ import annotations

import argparse
from concurrent.futures import ThreadPoolExecutor

import numpy as np

from dhg.core.surgeon import GENERIC_BREAKTHROUGH_DEPTH_M
from dhg.live.client import TraineeClient
from dhg.live.process import ServerProcess, free_port
from dhg.live.trainee import run_trainee


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seeds", default="0,1,2,3,4,5", help="expert seeds, comma-separated")
    ap.add_argument("--duration", type=float, default=70.0, help="seconds per run (default 70)")
    args = ap.parse_args()
    seeds = [int(s) for s in args.seeds.split(",")]
    port = free_port()
    server = ServerProcess(["--listen", f"tcp/127.0.0.1:{port}", "--status-every", "1000"], echo=False)

    def one(job: tuple[int, bool]) -> tuple[int, bool, float, float, float]:
        seed, plan = job
        with TraineeClient(f"tcp/127.0.0.1:{port}", session_id=f"plan-{seed}-{int(plan)}") as client:
            depth = None if plan else GENERIC_BREAKTHROUGH_DEPTH_M  # None: read off path_layers
            run = run_trainee(client, "expert", 0.0, args.duration, seed, breakthrough_depth_m=depth)
        pace = run.poses_sent / max(run.wall_s * 1000.0, 1.0)
        return seed, plan, run.metrics["plunge_depth_m"] * 1e3, pace, run.metrics["target_distance_m"] * 1e3

    try:
        with ThreadPoolExecutor(max_workers=2) as pool:
            rows = list(pool.map(one, [(seed, plan) for seed in seeds for plan in (True, False)]))
    finally:
        server.stop()
    for seed, plan, plunge, pace, to_b in rows:
        print(
            f"seed {seed:>3} {'plan   ' if plan else 'generic'} plunge {plunge:6.2f} mm  "
            f"pace {pace:.3f}  to B {to_b:.1f} mm"
        )
    diff = np.array([a[2] - b[2] for a, b in zip(rows[0::2], rows[1::2], strict=True)])
    se = diff.std(ddof=1) / np.sqrt(len(diff)) if len(diff) > 1 else float("nan")
    print(f"plunge, plan - generic: {diff.mean():+.2f} ± {se:.2f} mm over {len(diff)} seeds")


if __name__ == "__main__":
    main()
