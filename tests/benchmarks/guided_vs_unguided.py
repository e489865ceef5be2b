"""Does the bundled model's guidance change how a virtual novice drills? Starts ``dhg-serve``
(phantom femur, bundled model unless ``--model``) on a free loopback port and, for each seed,
runs the same novice hand (same seed) with guidance at ``--gain`` and without, for
``--duration`` seconds each, as ``make demo`` does once. Prints each pair's distance to B (mm),
plunge (mm), peak temperature (°C) and time above 47 °C (s), then the means.

    python tests/benchmarks/guided_vs_unguided.py --seeds 0,1,2,3,4,5,6,7,11 [--passive]

``--passive`` gives the hand no response to the cue beyond feeling it (``cue_follow_per_s`` 0),
the operator model before the trainee was taught what the cue means. Real time: each run takes
``--duration`` seconds.
"""

from __future__ import annotations

import argparse

import numpy as np

from dhg.client import TraineeClient
from dhg.live_demo import ServerProcess, free_port
from dhg.trainee import run_trainee

COLUMNS = (
    ("target_distance_m", "to B (mm)", 1e3),
    ("plunge_depth_m", "plunge (mm)", 1e3),
    ("peak_temperature_c", "peak (°C)", 1.0),
    ("time_above_47_s", ">47 °C (s)", 1.0),
)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seeds", default="0,1,2,3,4,5,6,7,11", help="novice seeds, comma-separated")
    ap.add_argument("--duration", type=float, default=20.0, help="seconds per run (default 20)")
    ap.add_argument("--gain", type=float, default=1.0, help="guidance gain of the guided run (default 1)")
    ap.add_argument("--model", help="TorchScript model (default: the bundled one)")
    ap.add_argument("--passive", action="store_true", help="the hand only feels the cue (cue_follow_per_s 0)")
    args = ap.parse_args()
    port = free_port()
    serve = ["--listen", f"tcp/127.0.0.1:{port}", "--status-every", "1000"]
    if args.model:
        serve += ["--model", args.model]
    server = ServerProcess(serve, echo=False)
    follow = 0.0 if args.passive else None
    results: dict[float, list[list[float]]] = {args.gain: [], 0.0: []}
    header = "seed  gain  " + "  ".join(f"{label:>11}" for _, label, _ in COLUMNS)
    print(header)
    try:
        for seed in [int(s) for s in args.seeds.split(",")]:
            for gain in (args.gain, 0.0):
                with TraineeClient(f"tcp/127.0.0.1:{port}", session_id=f"eval-{seed}-{gain:g}") as client:
                    run = run_trainee(
                        client,
                        "novice",
                        guidance_gain=gain,
                        duration_s=args.duration,
                        seed=seed,
                        cue_follow_per_s=follow,
                    )
                row = [run.metrics[key] * scale for key, _, scale in COLUMNS]
                results[gain].append(row)
                print(f"{seed:>4}  {gain:>4g}  " + "  ".join(f"{v:>11.2f}" for v in row), flush=True)
    finally:
        server.stop()
    for gain, rows in results.items():
        mean = np.mean(rows, axis=0)
        print(f"mean  {gain:>4g}  " + "  ".join(f"{v:>11.2f}" for v in mean))


if __name__ == "__main__":
    main()
