"""Does the bundled model's guidance change how a virtual novice drills? Starts ``dhg-serve``
(phantom femur, bundled model unless ``--model``) on a free loopback port and, for each seed,
runs the same novice hand (same seed) with guidance at ``--gain`` and without, for
``--duration`` seconds each, as ``make demo`` does once. Prints each pair's distance to B (mm),
plunge (mm), peak temperature (°C), time above 47 °C (s) and whether it reached B, then the means and the paired
difference (guided − unguided) with its standard error.

    python tests/benchmarks/guided_vs_unguided.py --seeds 0,1,2,3,4,5,6,7,11 [--passive]

``--passive`` gives the hand no response to the cue beyond feeling it (``cue_follow_per_s`` 0),
the operator model before the trainee was taught what the cue means. Real time: each run takes
``--duration`` seconds; ``--parallel N`` drills N runs at once, as N sessions of one server (each
trainee paces itself at 1 kHz, so keep N within what the machine's cores sustain).
"""

from __future__ import annotations

import argparse
from concurrent.futures import ThreadPoolExecutor

import numpy as np

from dhg.live.client import TraineeClient
from dhg.live.process import ServerProcess, free_port
from dhg.live.trainee import run_trainee

COLUMNS = (
    ("target_distance_m", "to B (mm)", 1e3),
    ("plunge_depth_m", "plunge (mm)", 1e3),
    ("peak_temperature_c", "peak (°C)", 1.0),
    ("time_above_47_s", ">47 °C (s)", 1.0),
    ("reached_target", "reached B", 1.0),
)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seeds", default="0,1,2,3,4,5,6,7,11", help="novice seeds, comma-separated")
    ap.add_argument("--duration", type=float, default=20.0, help="seconds per run (default 20)")
    ap.add_argument("--gain", type=float, default=1.0, help="guidance gain of the guided run (default 1)")
    ap.add_argument("--model", help="TorchScript model (default: the bundled one)")
    ap.add_argument("--passive", action="store_true", help="the hand only feels the cue (cue_follow_per_s 0)")
    ap.add_argument("--parallel", type=int, default=1, help="trainees drilling at once (default 1; each is a session)")
    args = ap.parse_args()
    seeds = [int(s) for s in args.seeds.split(",")]
    port = free_port()
    sessions = str(max(16, args.parallel))
    serve = ["--listen", f"tcp/127.0.0.1:{port}", "--status-every", "1000", "--max-sessions", sessions]
    if args.model:
        serve += ["--model", args.model]
    server = ServerProcess(serve, echo=False)
    follow = 0.0 if args.passive else None

    def one(job: tuple[int, float]) -> tuple[int, float, list[float]]:
        seed, gain = job
        with TraineeClient(f"tcp/127.0.0.1:{port}", session_id=f"eval-{seed}-{gain:g}") as client:
            run = run_trainee(
                client,
                "novice",
                guidance_gain=gain,
                duration_s=args.duration,
                seed=seed,
                cue_follow_per_s=follow,
            )
        # A trainee that could not keep its 1 kHz pace (too many at once for the cores) is flagged.
        pace = run.poses_sent / max(run.wall_s * 1000.0, 1.0)
        if pace < 0.95:
            print(f"warning: seed {seed} gain {gain:g} sent {pace:.0%} of its 1 kHz poses", flush=True)
        return seed, gain, [float(run.metrics[key]) * scale for key, _, scale in COLUMNS]

    results: dict[tuple[int, float], list[float]] = {}
    print("seed  gain  " + "  ".join(f"{label:>11}" for _, label, _ in COLUMNS))
    try:
        jobs = [(seed, gain) for seed in seeds for gain in (args.gain, 0.0)]
        with ThreadPoolExecutor(max_workers=max(1, args.parallel)) as pool:
            for seed, gain, row in pool.map(one, jobs):
                results[seed, gain] = row
                print(f"{seed:>4}  {gain:>4g}  " + "  ".join(f"{v:>11.2f}" for v in row), flush=True)
    finally:
        server.stop()
    for gain in (args.gain, 0.0):
        mean = np.mean([results[seed, gain] for seed in seeds], axis=0)
        print(f"mean  {gain:>4g}  " + "  ".join(f"{v:>11.2f}" for v in mean))
    # Paired differences (guided - unguided, same hand): mean and its standard error.
    diff = np.array([np.subtract(results[seed, args.gain], results[seed, 0.0]) for seed in seeds])
    se = diff.std(axis=0, ddof=1) / np.sqrt(len(seeds)) if len(seeds) > 1 else np.full(diff.shape[1], np.nan)
    print("diff  ± SE  " + "  ".join(f"{m:>+6.2f}±{e:<4.2f}" for m, e in zip(diff.mean(axis=0), se, strict=True)))


if __name__ == "__main__":
    main()
