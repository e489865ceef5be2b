"""How a recorder's flush grows with the recording. One :class:`dhg.live.recorder.SessionRecorder`
(10 Hz states only, no ``--raw``) is fed ``--attempts`` attempts of ``--records`` states each,
straight through :meth:`SessionRecorder.on_sample`. A stand-in Zenoh session answers the
recorder's ``about`` and ``info`` queries, so every attempt is measured against a planned path,
as against a server. After each step of attempts it adds one more state (so that the flush has
something new) and times ``flush()``. It prints the recording's length, the median flush, and the
memory the recorder holds per state (tracemalloc).

A flush rewrites the whole dataset folder (``records.parquet`` is one file), so its cost grows
with the recording, not with what came since the last flush; a recorder flushes every second
(``dhg record --flush-every``). ``--other PYTHONPATH`` runs a second build's recorder as well,
alternating, each in a fresh process.

    python tests/benchmarks/bench_recorder_flush.py --attempts 1,9,36 --records 1000 [--other /tmp/old/python]
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import tempfile
import time
import tracemalloc
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # tests/support.py

from support import AnsweringSession, attempt_states, state_sample  # noqa: E402


def _run(steps: list[int], records: int, flushes: int) -> list[str]:
    from dhg.core import protocol
    from dhg.live.recorder import SessionRecorder

    attempt = attempt_states(records)
    features = protocol.decode("state", attempt[-1])["features"]
    lines = []
    with tempfile.TemporaryDirectory() as tmp:
        # A first flush imports pyarrow and fills caches: not the recording's memory.
        warm = SessionRecorder("tcp/127.0.0.1:9", "bench", f"{tmp}/warm", zenoh_session=AnsweringSession("bench"))
        warm.on_sample("state", state_sample(attempt[0]))
        warm.flush()
        warm.close()
        tracemalloc.start()
        rec = SessionRecorder("tcp/127.0.0.1:9", "bench", f"{tmp}/ds", zenoh_session=AnsweringSession("bench"))
        fed = 0
        for step in steps:
            base = tracemalloc.get_traced_memory()[0]
            for _ in range(step - fed):
                for payload in attempt:  # each attempt restarts the clock: the recorder splits them
                    rec.on_sample("state", state_sample(payload))
            added = (step - fed) * records
            fed = step
            times = []
            for i in range(flushes):
                # One more state of the open attempt, so that the flush has something to write.
                extra = protocol.encode("state", time_s=0.1 * (records + 1 + i), features=features)
                rec.on_sample("state", state_sample(extra))
                t0 = time.perf_counter()
                rec.flush()
                times.append(time.perf_counter() - t0)
            held = tracemalloc.get_traced_memory()[0] - base
            lines.append(
                f"{step} | {rec.records} | {1e3 * statistics.median(times):.1f} | {1e3 * max(times):.1f} "
                f"| {held / added:.0f}"
            )
        rec.close()
    return lines


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--attempts", default="1,9,36", help="recording lengths to time, in attempts (default 1,9,36)")
    ap.add_argument("--records", type=int, default=1000, help="states an attempt (default 1000: 100 s)")
    ap.add_argument("--flushes", type=int, default=5, help="flushes timed at each length (default 5)")
    ap.add_argument("--rounds", type=int, default=1, help="alternations of the builds (default 1)")
    ap.add_argument("--other", metavar="PYTHONPATH", help="also a second build's python/ (alternated)")
    ap.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    args = ap.parse_args()
    steps = sorted(int(a) for a in args.attempts.split(","))
    if args.child:
        print("\n".join(_run(steps, args.records, args.flushes)))
        return
    builds = [("this", None)] + ([("other", args.other)] if args.other else [])
    print("| build | round | attempts | states | flush p50 (ms) | flush max (ms) | memory a state (bytes) |")
    print("|---|---:|---:|---:|---:|---:|---:|")
    for r in range(args.rounds):
        for name, path in builds:
            env = dict(os.environ)
            if path:
                env["PYTHONPATH"] = path
            out = subprocess.run(
                [sys.executable, __file__, "--child", "--attempts", args.attempts, "--records", str(args.records),
                 "--flushes", str(args.flushes)],
                env=env, capture_output=True, text=True, check=True,
            )  # fmt: skip
            for line in out.stdout.splitlines():
                print(f"| {name} | {r + 1} | {line} |", flush=True)


if __name__ == "__main__":
    main()
