"""The live view's cost to the server (issue 23): the load tool's pose -> force latency and the
server's CPU with ``dhg view`` attached (the instructor's page and the trainee's page of the load's
session) and without, alternated over fresh servers, and the drill updates a second the trainee
page sent. The viewer is its own process, as ``dhg-serve --view`` runs it.

    cargo build --release -p bone_sim --example load
    python tests/benchmarks/bench_viewer.py --seconds 20 --rounds 3 [--browser]

``--browser`` also keeps a headless Chromium on the trainee page (the whole screen a trainee has).
Prints one JSON line per run, then the medians and the ratios (with / without).
"""

from __future__ import annotations

import argparse
import json
import os
import re
import signal
import statistics
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

from dhg.live.process import ServerProcess, free_port


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seconds", type=float, default=20.0)
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--browser", action="store_true")
    target = os.environ.get("CARGO_TARGET_DIR", "target")
    ap.add_argument("--load", default=str(Path(target) / "release" / "examples" / "load"))
    args = ap.parse_args()
    runs = []
    for _ in range(args.rounds):
        for viewer in (False, True):
            r = _one(args, viewer)
            print(json.dumps(r), flush=True)
            runs.append(r)

    def med(viewer: bool, key: str) -> float:
        return statistics.median(r[key] for r in runs if r["viewer"] == viewer)

    summary = {k: {"without": med(False, k), "with": med(True, k)} for k in ("p50_ms", "p99_ms", "cpu_cores")}
    for v in summary.values():
        v["ratio"] = v["with"] / v["without"]
    summary["viewer_updates_per_s"] = statistics.median(r["updates_per_s"] for r in runs if r["viewer"])
    summary["server_cpu_per_viewer_cores"] = summary["cpu_cores"]["with"] - summary["cpu_cores"]["without"]
    summary["viewer_cpu_cores"] = statistics.median(r["viewer_cpu_cores"] for r in runs if r["viewer"])
    summary["viewer_steady_cpu_cores"] = statistics.median(r["viewer_steady_cpu_cores"] for r in runs if r["viewer"])
    print(json.dumps(summary), flush=True)


def _one(args: argparse.Namespace, with_viewer: bool) -> dict[str, Any]:
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    server = ServerProcess(["--listen", endpoint, "--status-every", "30"], echo=False)
    viewer = None
    out: list[str] = []
    done = threading.Event()
    try:
        viewer_cpu = 0.0
        if with_viewer:
            port = free_port()
            cmd = [sys.executable, "-m", "dhg.cli.main", "view", "--connect", endpoint, "--port", str(port)]
            viewer = subprocess.Popen(cmd, stdout=subprocess.PIPE, text=True)
            assert viewer.stdout is not None
            out.append(viewer.stdout.readline())  # ready
            threading.Thread(target=lambda: out.extend(viewer.stdout), daemon=True).start()
            if args.browser:
                threading.Thread(target=_browse, args=(f"http://127.0.0.1:{port}", done), daemon=True).start()
        load_run = subprocess.Popen(
            [args.load, "--connect", endpoint, "--clients", "1", "--seconds", f"{args.seconds:g}",
             "--server-pid", str(server.proc.pid)],
            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
        )  # fmt: skip
        # The viewer's steady cost: over the middle of the load, its start and first meshing over.
        time.sleep(2.0 + 0.25 * args.seconds)
        steady0, t0 = (_cpu_s(viewer.pid) if viewer is not None else 0.0), time.monotonic()
        time.sleep(0.5 * args.seconds)
        viewer_steady = (_cpu_s(viewer.pid) - steady0) / (time.monotonic() - t0) if viewer is not None else 0.0
        stdout, stderr = load_run.communicate(timeout=args.seconds + 120)
        r = subprocess.CompletedProcess(load_run.args, load_run.returncode, stdout, stderr)
        viewer_cpu = _cpu_s(viewer.pid) / args.seconds if viewer is not None else 0.0
    finally:
        done.set()
        if viewer is not None:
            viewer.send_signal(signal.SIGINT)
            viewer.wait(timeout=30)
        server.stop()
    if r.returncode != 0:
        raise SystemExit(f"load tool failed ({r.returncode}): {r.stderr}")
    load = json.loads(r.stdout)
    rates = [float(m.group(1)) for line in out if (m := re.search(r"\(([\d.]+)/s\)", line))]
    return {
        "viewer": with_viewer,
        "p50_ms": load["pose_to_force_ms"]["p50"],
        "p99_ms": load["pose_to_force_ms"]["p99"],
        "cpu_cores": load["server_cpu_cores"],
        "updates_per_s": max(rates) if rates else 0.0,
        "viewer_cpu_cores": viewer_cpu,  # its start (meshing the bone) included
        "viewer_steady_cpu_cores": viewer_steady,  # the middle half of the load
    }


def _cpu_s(pid: int) -> float:
    """User + system CPU seconds of a process so far (Linux ``/proc``)."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def _browse(instructor_url: str, done: threading.Event) -> None:
    """A headless Chromium on the load session's page until the run is ``done``."""
    from selenium.webdriver.common.by import By

    from dhg.view.browser import chromium, wait_for

    with chromium() as driver:
        driver.get(instructor_url)
        link = wait_for(lambda: driver.find_element(By.CSS_SELECTOR, ".dhg-session a").get_attribute("href"), 60, "a")
        driver.get(link)
        done.wait()


if __name__ == "__main__":
    main()
