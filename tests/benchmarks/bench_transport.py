"""What Zenoh's own transport options do to the transport's floor (issue 24): the bare echo
(``crates/bone_sim/examples/echo.rs``: the server's keys and QoS, a force put from the pose's
callback, no engine) under the load tool, with each option on and off, alternating in one run.
Prints one JSON line per round and a table of medians with ratios to ``default``.

Variants (``--variants``, in this order each round):

- ``default``: Zenoh's defaults, as ``dhg-serve`` runs;
- ``shm``: shared memory on both sides, every message through it (``transport.shared_memory``,
  ``message_size_threshold`` 1 byte; binaries built with the ``shm`` feature);
- ``shm-off``: the same binaries with shared memory turned off (what compiling it in costs);
- ``lowlatency``: Zenoh's low-latency transport on both sides (QoS off; decision 0011);
- ``rx1``: the echo's receive runtime on one worker thread instead of two (``ZENOH_RUNTIME``).

Also counts the files each variant left in ``/dev/shm`` once its echo and load tool had stopped
(new files only; another program's made meanwhile would count too), and removes them.

    cargo build --release -p bone_sim --example load --example echo
    CARGO_TARGET_DIR=~/.cache/dhg/shm-target \
        cargo build --release -p bone_sim --features shm --example load --example echo
    python tests/benchmarks/bench_transport.py --clients 1,4,16 --rounds 2 --seconds 10
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
from pathlib import Path
from typing import Any

from bench_server import CACHE, EXAMPLES, LOWLATENCY, RUNTIMES, _context_switches, _wait_for_echo, _zenoh_runtime

from dhg.live.process import free_port

SHM_ON = {"shared_memory": {"enabled": True, "mode": "init",
                            "transport_optimization": {"enabled": True, "message_size_threshold": 1}}}  # fmt: skip
SHM_OFF = {"shared_memory": {"enabled": False}}
# variant: (binaries built with shm, the transport section both sides use, the echo's runtime tag:
# a key of bench_server.RUNTIMES, or "" for Zenoh's defaults)
VARIANTS: dict[str, tuple[bool, dict[str, Any], str]] = {
    "default": (False, {}, ""),
    "shm": (True, SHM_ON, ""),
    "shm-off": (True, SHM_OFF, ""),
    "lowlatency": (False, LOWLATENCY, ""),
    "rx1": (False, {}, "rx1"),
}
assert all(tag in ("", *RUNTIMES) for _, _, tag in VARIANTS.values())


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--seconds", type=float, default=10.0)
    p.add_argument("--clients", default="1,4,16")
    p.add_argument("--rounds", type=int, default=2)
    p.add_argument("--variants", default=",".join(VARIANTS), help=f"alternated in this order; of {', '.join(VARIANTS)}")
    p.add_argument("--build", default=str(EXAMPLES), help="folder of the load and echo binaries")
    p.add_argument(
        "--shm-build",
        default=str(CACHE / "shm-target/release/examples"),
        help="folder of the load and echo binaries built with --features shm",
    )
    p.add_argument("--out", help="also append the JSON lines to this file")
    args = p.parse_args()
    variants = args.variants.split(",")
    unknown = [v for v in variants if v not in VARIANTS]
    if unknown or "default" not in variants:
        raise SystemExit(f"--variants: unknown {unknown}; 'default' must be among them")
    rows = []
    for n in (int(c) for c in args.clients.split(",")):
        runs: dict[str, list[dict[str, Any]]] = {v: [] for v in variants}
        for round_ in range(args.rounds):
            for v in variants:
                run = {"variant": v, "round": round_, "clients": n, "seconds": args.seconds, "cpus": os.cpu_count(),
                       **_one(args, v, n)}  # fmt: skip
                runs[v].append(run)
                print(json.dumps(run), flush=True)
                if args.out:
                    with open(args.out, "a") as fh:
                        fh.write(json.dumps(run) + "\n")
        base = {k: statistics.median(r[k] for r in runs["default"]) for k in ("cpu_per_session", "p50_ms", "p99_ms")}
        for v in variants:
            med = {k: statistics.median(r[k] for r in runs[v]) for k in runs[v][0] if isinstance(runs[v][0][k], float)}
            left = max(r["shm_files_left"] for r in runs[v])
            rows.append((n, v, med, base, left))
    print(f"\n{args.rounds} rounds of {args.seconds:g} s, alternating; medians; {os.cpu_count()} CPUs\n")
    print("| clients | variant | echo CPU per session (cores) | / default | pose → force p50 (ms) | / default "
          "| p99 (ms) | / default | context switches per pose | files left in /dev/shm |")  # fmt: skip
    print("|---:|---|---:|---:|---:|---:|---:|---:|---:|---:|")
    for n, v, m, b, left in rows:
        print(
            f"| {n} | {v} | {m['cpu_per_session']:.4f} | {m['cpu_per_session'] / b['cpu_per_session']:.2f} "
            f"| {m['p50_ms']:.3f} | {m['p50_ms'] / b['p50_ms']:.2f} "
            f"| {m['p99_ms']:.3f} | {m['p99_ms'] / b['p99_ms']:.2f} "
            f"| {m['context_switches_per_pose']:.2f} | {left} |"
        )


def _shm_files() -> set[str]:
    try:
        return set(os.listdir("/dev/shm"))
    except OSError:
        return set()


def _one(args: argparse.Namespace, variant: str, n: int) -> dict[str, Any]:
    shm_build, transport, tag = VARIANTS[variant]
    build = Path(args.shm_build if shm_build else args.build)
    for tool in ("load", "echo"):
        if not (build / tool).exists():
            raise SystemExit(f"no {build / tool}: build it first (see --help)")
    before = _shm_files()
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    section = json.dumps(transport)
    with _zenoh_runtime(tag):
        echo = subprocess.Popen(
            [str(build / "echo"), "--listen", endpoint, "--transport", section], stderr=subprocess.PIPE, text=True
        )
    try:
        _wait_for_echo(echo)
        switches0 = _context_switches(echo.pid)
        with _zenoh_runtime(""):  # the load tool on Zenoh's defaults, whatever the variant
            r = subprocess.run(
                [str(build / "load"), "--connect", endpoint, "--clients", str(n), "--seconds", str(args.seconds),
                 "--server-pid", str(echo.pid), "--transport", section],
                capture_output=True, text=True, timeout=args.seconds + 120,
            )  # fmt: skip
        switches = _context_switches(echo.pid) - switches0
    finally:
        echo.terminate()
        echo.wait(timeout=30)
    if r.returncode != 0:
        raise SystemExit(f"load tool against the echo ({variant}) failed ({r.returncode}): {r.stderr}")
    out = json.loads(r.stdout)
    left = _shm_files() - before
    for name in left:  # counted, then cleared so that the next rounds start from the same /dev/shm
        Path("/dev/shm", name).unlink(missing_ok=True)
    return {
        "p50_ms": out["pose_to_force_ms"]["p50"],
        "p99_ms": out["pose_to_force_ms"]["p99"],
        "cpu_per_session": out["server_cpu_cores"] / n,
        "forces_per_pose": out["forces_per_pose"],
        "context_switches_per_pose": switches / (n * (args.seconds + 2.0) * 1000.0),
        "shm_files_left": len(left),
    }


if __name__ == "__main__":
    sys.exit(main())
