"""What an executor costs ``dhg-serve`` at start (decision 0030): its resident memory once ready
(0.5 mm phantom, bundled model) and the seconds it takes to say so, alternating the executors over
fresh servers. Prints one JSON line per start, then the medians.

    python tests/benchmarks/bench_serve_start.py [--rounds 2] [--executors auto,torchscript]
"""

from __future__ import annotations

import argparse
import json
import statistics
import time
from pathlib import Path

from dhg.live.process import ServerProcess, free_port


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--rounds", type=int, default=2)
    p.add_argument("--executors", default="auto,torchscript", help="dhg-serve --executor values, alternated")
    args = p.parse_args()
    rows = []
    for _ in range(args.rounds):
        for executor in args.executors.split(","):
            t0 = time.perf_counter()
            server = ServerProcess(["--listen", f"tcp/127.0.0.1:{free_port()}", "--executor", executor], echo=False)
            ready_s = time.perf_counter() - t0
            try:
                status = Path(f"/proc/{server.proc.pid}/status").read_text().splitlines()
                rss_mb = int(next(line for line in status if line.startswith("VmRSS")).split()[1]) / 1024
                said = next((line for line in server.lines if "ready" in line), "")
            finally:
                server.stop()
            row = {"executor": executor, "rss_mb": round(rss_mb, 1), "ready_s": round(ready_s, 2), "said": said[-160:]}
            rows.append(row)
            print(json.dumps(row), flush=True)
    for executor in args.executors.split(","):
        mine = [r for r in rows if r["executor"] == executor]
        print(json.dumps({
            "executor": executor,
            "rss_mb_median": statistics.median(r["rss_mb"] for r in mine),
            "ready_s_median": statistics.median(r["ready_s"] for r in mine),
        }))  # fmt: skip


if __name__ == "__main__":
    main()
