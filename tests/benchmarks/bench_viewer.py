"""The live view's cost to the server (issue 23): the load tool's pose -> force latency and the
server's CPU with ``dhg view`` attached (the instructor's page and the trainee's page of the load's
session) and without, alternated over fresh servers, and the drill updates a second the trainee
page sent. The viewer is its own process, as ``dhg-serve --view`` runs it.

    CARGO_TARGET_DIR=~/.cache/dhg/target cargo build --release -p bone_sim --example load
    python tests/benchmarks/bench_viewer.py --seconds 20 --rounds 3 [--browser]

(the Makefile's target folder, where the script looks for the load tool; ``--load`` names another)

A page draws only while someone watches it, so each run holds the instructor's page and the first
trainee page open with a :class:`dhg.view.browser.PageWatcher` (a WebSocket client that reads what
a browser tab would, without drawing it); ``--unwatched`` leaves every page closed. ``--browser``
keeps a headless Chromium on the trainee page instead (the whole screen a trainee has).
``--device auto|cpu|cuda`` passes on to ``dhg-serve`` (where the model's passes run).
``--viewer-nice 0`` adds a variant, the viewer at that nice value instead of ``dhg view``'s default
(decision 0027); ``--other PYTHONPATH`` one more, ``dhg view`` from another build (a checkout's
``python/`` folder with its extension built), the server staying this build's; ``--viewer-runtime
RON`` one more, ``dhg view`` with that ``ZENOH_RUNTIME`` (Zenoh's runtime threads, decision 0031). ``--clients N`` runs
N load-tool trainees (the viewer serves every session's page). Prints one JSON line per run, then
the medians and the ratios (with / without).
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

from bench_server import EXAMPLES  # this folder: where make builds the load tool

from dhg.live.process import ServerProcess, free_port


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seconds", type=float, default=20.0)
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--clients", type=int, default=1, help="load-tool trainees (default 1); the viewer shows the first")
    ap.add_argument("--browser", action="store_true")
    ap.add_argument("--load", default=str(EXAMPLES / "load"), help="the load tool binary")
    ap.add_argument("--device", choices=("auto", "cpu", "cuda"), help="dhg-serve --device (default auto)")
    ap.add_argument("--viewer-nice", type=int, metavar="N", help="also a viewer at nice N (dhg view --nice N)")
    ap.add_argument("--other", metavar="PYTHONPATH", help="also dhg view from the build this python/ folder holds")
    ap.add_argument(
        "--viewer-runtime",
        metavar="RON",
        help="also dhg view with this ZENOH_RUNTIME (e.g. '(rx: (worker_threads: 1))'), as the variant 'runtime'",
    )
    ap.add_argument("--unwatched", action="store_true", help="no watcher on the pages (nobody looks at them)")
    ap.add_argument("--out", help="also append the JSON lines to this file")
    args = ap.parse_args()
    # None: no viewer; "with": dhg view as it starts by default; an int: dhg view --nice N;
    # "other": dhg view from the build --other names.
    variants: list[Any] = [None, "with"] + ([args.viewer_nice] if args.viewer_nice is not None else [])
    variants += ["other"] if args.other else []
    variants += ["runtime"] if args.viewer_runtime else []
    runs = []
    for _ in range(args.rounds):
        for variant in variants:
            r = _one(args, variant)
            _emit(args, r)
            runs.append(r)

    def med(variant: Any, key: str) -> float:
        return statistics.median(r[key] for r in runs if r["viewer"] == _name(variant))

    for variant in variants[1:]:
        summary: dict[str, Any] = {"viewer": _name(variant)}
        for k in ("p50_ms", "p99_ms", "cpu_cores", "guidance_p50_ms", "guidance_p99_ms"):
            if any(r[k] is None for r in runs if r["viewer"] in ("none", _name(variant))):
                continue  # a run with no guidance at all (the load tool's null): nothing to set beside
            summary[k] = {"without": med(None, k), "with": med(variant, k)}
            summary[k]["ratio"] = summary[k]["with"] / summary[k]["without"]
        summary["viewer_updates_per_s"] = med(variant, "updates_per_s")
        summary["server_cpu_per_viewer_cores"] = summary["cpu_cores"]["with"] - summary["cpu_cores"]["without"]
        summary["viewer_cpu_cores"] = med(variant, "viewer_cpu_cores")
        summary["viewer_steady_cpu_cores"] = med(variant, "viewer_steady_cpu_cores")
        _emit(args, summary)


def _name(variant: Any) -> str:
    """A variant's name in the JSON lines: ``none``, ``with`` (``dhg view`` as it starts by
    default), ``nice-N``, ``other`` (another build's) or ``runtime`` (``--viewer-runtime``)."""
    return "none" if variant is None else variant if variant in ("with", "other", "runtime") else f"nice-{variant}"


def _emit(args: argparse.Namespace, line: dict[str, Any]) -> None:
    print(json.dumps(line), flush=True)
    if args.out:
        with open(args.out, "a") as fh:
            fh.write(json.dumps(line) + "\n")


def _one(args: argparse.Namespace, variant: Any) -> dict[str, Any]:
    with_viewer = variant is not None
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    serve_args = ["--listen", endpoint, "--status-every", "30", "--max-sessions", str(max(args.clients, 16))]
    server = ServerProcess(serve_args + (["--device", args.device] if args.device else []), echo=False)
    viewer = None
    out: list[str] = []
    done = threading.Event()
    try:
        viewer_cpu = 0.0
        if with_viewer:
            port = free_port()
            cmd = [sys.executable, "-m", "dhg.cli.main", "view", "--connect", endpoint, "--port", str(port)]
            env = dict(os.environ)
            if isinstance(variant, int):
                cmd += ["--nice", str(variant)]
            elif variant == "other":
                env["PYTHONPATH"] = args.other
            elif variant == "runtime":
                env["ZENOH_RUNTIME"] = args.viewer_runtime
            viewer = subprocess.Popen(cmd, stdout=subprocess.PIPE, text=True, env=env)
            assert viewer.stdout is not None
            out.append(viewer.stdout.readline())  # ready
            if "dhg view:" not in out[-1]:
                raise SystemExit(f"dhg view ({_name(variant)}) did not start (exit {viewer.wait(timeout=30)})")
            threading.Thread(target=lambda: out.extend(viewer.stdout), daemon=True).start()
            if args.browser:
                threading.Thread(target=_browse, args=(f"http://127.0.0.1:{port}", done), daemon=True).start()
            elif not args.unwatched:
                threading.Thread(target=_watch, args=(port, done), daemon=True).start()
        load_run = subprocess.Popen(
            [args.load, "--connect", endpoint, "--clients", str(args.clients), "--seconds", f"{args.seconds:g}",
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
    rates = [float(m.group(1)) for line in out if (m := re.search(r"\(([\d.]+)/s", line))]
    return {
        "viewer": _name(variant),
        "clients": args.clients,
        "seconds": args.seconds,
        **({"zenoh_runtime": args.viewer_runtime} if variant == "runtime" else {}),
        "p50_ms": load["pose_to_force_ms"]["p50"],
        "p99_ms": load["pose_to_force_ms"]["p99"],
        # What the model's guidance takes to come back (pose -> guidance: the window's model query).
        "guidance_p50_ms": load["pose_to_guidance_ms"]["p50"],
        "guidance_p99_ms": load["pose_to_guidance_ms"]["p99"],
        "cpu_cores": load["server_cpu_cores"],
        "updates_per_s": max(rates) if rates else 0.0,
        "viewer_cpu_cores": viewer_cpu,  # its start (meshing the bone) included
        "viewer_steady_cpu_cores": viewer_steady,  # the middle half of the load
    }


def _cpu_s(pid: int) -> float:
    """User + system CPU seconds of a process so far (Linux ``/proc``)."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def _watch(port: int, done: threading.Event) -> None:
    """Watchers on the instructor's page (``port``) and the first trainee page (the next port, once
    the instructor's page has started it) until the run is ``done``."""
    from dhg.view.browser import PageWatcher

    watchers = []
    try:
        for url in (f"http://127.0.0.1:{port}", f"http://127.0.0.1:{port + 1}"):
            while not done.is_set():
                try:
                    watchers.append(PageWatcher(url, timeout_s=2.0))
                    break
                except Exception:  # the page is not up yet (refused, or a handshake it could not answer)
                    done.wait(0.2)
        done.wait()
    finally:
        for w in watchers:
            w.close()


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
