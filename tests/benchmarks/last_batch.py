"""How long after a session's last tick its last batch of ticks reaches a recorder: a trainee
streams poses for a while and closes its session (the ``close`` op), and a subscriber on the
session's ``ticks`` key times the batch that holds the last tick whose force the trainee got. A
full batch leaves at once; the last one is partial, and leaves when the comm thread finds it
older than its maximum age (``BATCH_MAX_AGE`` in ``transport/outlet.rs``).

``--other PYTHONPATH`` adds another build (a checkout whose ``python/dhg`` holds its own
extension) as the variant ``other``, alternated with this one in each round. Prints one JSON line
per trial and the medians per variant.

    python tests/benchmarks/last_batch.py --rounds 3 --trials 5 [--other /tmp/old/python]
"""

from __future__ import annotations

import argparse
import json
import statistics
import threading
import time

import numpy as np
from bench_server import serve_from  # this folder: a server of either build

from dhg.core import protocol
from dhg.live.client import TraineeClient
from dhg.live.process import free_port
from dhg.live.zenoh_config import open_zenoh, zenoh_config_json5


def trial(endpoint: str, n: int, poses: int) -> dict[str, float]:
    """One session: ``poses`` poses at 1 kHz before the bone, then ``close``. Returns the time from
    the session's last force reaching the client to the arrival of the batch with its tick."""
    sid = f"last-batch-{n}"
    arrivals: list[tuple[float, int]] = []  # (arrival s, last tick of the batch)
    lock = threading.Lock()
    z = open_zenoh(zenoh_config_json5(connect=[endpoint], mode="client"))

    def on_ticks(sample: object) -> None:
        rows = protocol.decode_ticks(sample.payload.to_bytes())  # type: ignore[attr-defined]
        with lock:
            arrivals.append((time.monotonic(), int(rows["tick"][-1])))

    sub = z.declare_subscriber(protocol.keys("dhg", sid)["ticks"], on_ticks)
    last_force: list[tuple[float, int]] = []
    try:
        with TraineeClient(endpoint, sid, on_force=lambda m: last_force.append((time.monotonic(), m["tick"]))) as c:
            a = np.array(c.create()["entry_m"])
            t = time.monotonic()
            for _ in range(poses):
                c.send_pose(a - [0.0, 0.0, 5e-3], (1.0, 0.0, 0.0, 0.0), False, 0.0)
                t += 1e-3
                time.sleep(max(0.0, t - time.monotonic()))
            c.control("close")
            # No more forces come: wait (up to 5 s) for the batch holding the last one's tick.
            last_tick = max(tick for _, tick in last_force)
            deadline = time.monotonic() + 5.0
            while True:
                with lock:
                    hit = [at for at, tick in arrivals if tick >= last_tick]
                if hit or time.monotonic() > deadline:
                    break
                time.sleep(0.005)
            forced = max(at for at, _ in last_force)
            return {
                "last_tick": last_tick,
                "batches": len(arrivals),
                "last_batch_after_last_force_s": (min(hit) - forced) if hit else float("nan"),
            }
    finally:
        sub.undeclare()
        z.close()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--trials", type=int, default=5, help="sessions per variant and round")
    ap.add_argument("--poses", type=int, default=1050, help="poses a session (at 1 kHz)")
    ap.add_argument("--other", help="PYTHONPATH of another build, as the variant 'other'")
    args = ap.parse_args()
    variants = ["dhg", "other"] if args.other else ["dhg"]
    got: dict[str, list[float]] = {v: [] for v in variants}
    for r in range(args.rounds):
        for v in variants if r % 2 == 0 else variants[::-1]:
            endpoint = f"tcp/127.0.0.1:{free_port()}"
            server = serve_from(args.other if v == "other" else None, ["--listen", endpoint, "--role", "sim"])
            try:
                for k in range(args.trials):
                    out = trial(endpoint, k, args.poses)
                    print(json.dumps({"variant": v, "round": r, "trial": k, **out}), flush=True)
                    got[v].append(out["last_batch_after_last_force_s"])
            finally:
                server.stop()
    for v, xs in got.items():
        ok = [x for x in xs if x == x]
        print(
            f"{v}: last batch after the last force, median {statistics.median(ok) * 1e3:.0f} ms, "
            f"range {min(ok) * 1e3:.0f}–{max(ok) * 1e3:.0f} ms over {len(ok)} sessions ({len(xs) - len(ok)} never came)"
        )


if __name__ == "__main__":
    main()
