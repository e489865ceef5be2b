"""What ``dhg record --raw`` costs, and how much of the 1 kHz stream it keeps. Starts ``dhg-serve``
(phantom femur, bundled model) on a free loopback port, records one session in this process
(:class:`dhg.live.recorder.SessionRecorder` with the 1 kHz stream) while a virtual novice
(``dhg trainee``, its own process) drills it for ``--seconds``, then stops the recorder cleanly.
Prints the recorder's CPU use, its flush times, the ticks it kept against the ticks the session
ran, and the size of the files.

    python tests/benchmarks/bench_record.py --seconds 90
    python tests/benchmarks/bench_record.py --seconds 90 --no-record   # the trainee alone, to compare

Parts hold 10,000 ticks (10 s), so every run sees parts closed and then linked. The trainee's
own pose → force figures are printed too: the recorder is a second subscriber to its forces.
"""

from __future__ import annotations

import argparse
import json
import resource
import shutil
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

from dhg.data.dataset import load_dataset, load_raw
from dhg.live.process import ServerProcess, free_port
from dhg.live.recorder import SessionRecorder


def _cpu_s() -> float:
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime


def _trainee(endpoint: str, args: argparse.Namespace) -> subprocess.CompletedProcess[str]:
    trainee = subprocess.run(
        [sys.executable, "-m", "dhg.cli.main", "trainee", "--connect", endpoint, "--session", "bench-rec"]
        + ["--skill", "novice", "--duration", str(args.seconds), "--seed", str(args.seed)],
        capture_output=True,
        text=True,
    )
    if trainee.returncode != 0:
        sys.exit(f"dhg trainee failed:\n{trainee.stdout}{trainee.stderr}")
    return trainee


def _latency(stdout: str) -> list[str]:
    """The trainee's pose → force and pose → guidance lines."""
    return [" ".join(line.split()) for line in stdout.splitlines() if "pose→" in line]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seconds", type=float, default=60.0, help="how long the novice drills (default 60)")
    ap.add_argument("--seed", type=int, default=7, help="the novice's hand (default 7)")
    ap.add_argument("--no-record", action="store_true", help="run the trainee without a recorder")
    args = ap.parse_args()
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    server = ServerProcess(["--listen", endpoint, "--status-every", "1000"], echo=False)
    out = Path(tempfile.mkdtemp(prefix="dhg-bench-record-")) / "rec"
    if args.no_record:
        try:
            trainee = _trainee(endpoint, args)
        finally:
            server.stop()
        print(json.dumps({"seconds": args.seconds, "trainee": _latency(trainee.stdout)}, indent=1))
        shutil.rmtree(out.parent, ignore_errors=True)
        return
    try:
        rec = SessionRecorder(endpoint, "bench-rec", out, skill="novice", raw=True)
        flush_s: list[float] = []
        parts_seen: set[str] = set()
        plain_flush = rec.flush

        def timed_flush(final: bool = False) -> bool:
            t0 = time.perf_counter()
            wrote = plain_flush(final)
            if wrote:
                flush_s.append(time.perf_counter() - t0)
                parts_seen.update(p.name for p in out.glob("raw*.parquet"))
            return wrote

        rec.flush = timed_flush  # type: ignore[method-assign]
        stop = threading.Event()
        worker = threading.Thread(target=rec.run, args=(stop,))
        cpu0, wall0 = _cpu_s(), time.perf_counter()
        worker.start()
        trainee = _trainee(endpoint, args)
        time.sleep(0.5)
        stop.set()
        worker.join()
        cpu, wall = _cpu_s() - cpu0, time.perf_counter() - wall0
        rec.close()
    finally:
        server.stop()
    ds = load_dataset(out)
    raw = load_raw(ds)
    ticks = raw.column("tick").to_numpy()
    ran = int(ticks[-1] - ticks[0] + 1)
    sizes = {p.name: p.stat().st_size for p in sorted(out.iterdir())}
    fl = np.array(flush_s[:-1]) * 1e3  # the last one joins the parts
    result = {
        "seconds": args.seconds,
        "recorder_cpu_cores": round(cpu / wall, 3),
        "flushes": len(flush_s),
        "flush_ms_p50_p99_max": [round(float(np.percentile(fl, q)), 1) for q in (50, 99, 100)],
        "final_join_ms": round(flush_s[-1] * 1e3, 1),
        "raw_parts_seen": sorted(parts_seen),
        "raw_rows": raw.num_rows,
        "ticks_ran": ran,
        "ticks_kept": round(raw.num_rows / ran, 5),
        "card_raw": ds.card["generator"]["raw"],
        "records": ds.n_records,
        "bytes": sizes,
        "raw_mb_per_min": round(sizes["raw.parquet"] / 1e6 / (ran / 60e3), 2),
        "trainee": _latency(trainee.stdout),
    }
    print(json.dumps(result, indent=1))
    shutil.rmtree(out.parent, ignore_errors=True)


if __name__ == "__main__":
    main()
