"""Where a server's CPU goes, thread by thread: ``dhg-serve --role sim`` (the engine, no model
service; with ``--role all`` the engine and the model service in one process, the model on CPU)
and the bare Zenoh echo (``crates/bone_sim/examples/echo.rs``) under the same load tool,
alternated, with each thread's CPU and voluntary context switches (its wake-ups) read from
``/proc`` over the middle of the run. Prints one line per run and a table of medians.

``--other PYTHONPATH`` adds a second engine build as the variant ``other``: a checkout of another
commit whose ``python/dhg`` holds its own extension (``cargo build --release -p bone_sim --features
python --lib``, then copy ``libbone_sim.so`` to ``python/dhg/_bone_sim.cpython-*.so``), so that two
builds are compared in one alternating run (issue 24). ``--echo-work-us US`` adds the echo spinning
US microseconds in each pose's callback (``echo --work-us``) as ``echo-work``: the floor for a
server that computes something per pose, so a tick's own cost and the engine's cost around it
part. ``--echo-router`` adds the echo in Zenoh's router mode, the engine's, as ``echo-router``.

``--perf`` also samples the server with ``perf record`` over the same middle of the run and
splits its CPU by what runs (the engine's own code and libm; Zenoh and tokio; the server's glue
around them; the kernel's scheduling; the rest of the kernel; libc), in cores: where a server's CPU
beyond the echo's goes, without call graphs (the build has no frame pointers).

With ``--role all`` the column ``model`` is the model service's worker thread (its forward passes
and its Python) with the idle main thread: both carry the process's name. The Python Zenoh
session's threads share the engine's names and cost next to nothing.

    cargo build --release -p bone_sim --example load --example echo
    python tests/benchmarks/bench_threads.py --clients 1,4,16 --rounds 2 [--other /tmp/old/python] [--echo-work-us 5]
        [--echo-router] [--role all] [--perf]
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import tempfile
import time
from pathlib import Path
from typing import Any

from bench_server import EXAMPLES, _wait_for_echo, serve_from  # this folder: the echo's start; a server of either build

from dhg.live.process import free_port


def threads(pid: int) -> dict[str, tuple[str, float, int]]:
    """Thread id → (name, CPU s, voluntary context switches) of process ``pid`` now."""
    tick = os.sysconf("SC_CLK_TCK")
    out = {}
    for tid in os.listdir(f"/proc/{pid}/task"):
        try:
            stat = Path(f"/proc/{pid}/task/{tid}/stat").read_text()
            status = Path(f"/proc/{pid}/task/{tid}/status").read_text()
        except FileNotFoundError:  # the thread ended
            continue
        name = stat[stat.index("(") + 1 : stat.rindex(")")]
        f = stat.rsplit(")", 1)[1].split()
        switches = int(status.split("\nvoluntary_ctxt_switches:")[1].split()[0])
        out[tid] = (name, (int(f[11]) + int(f[12])) / tick, switches)
    return out


PERF_HZ = 999
"""perf's sampling rate (Hz) with ``--perf``."""

LIBM = {"ceil", "floor", "round", "trunc", "pow", "exp", "log", "sqrt", "fmod"}
"""Math functions that the extension links in itself (a tick's: the engine's)."""

# What a sample's symbol belongs to, first match wins (``--perf``): the kernel's entries are those
# where a switched-in thread's samples land (the switch itself and the wake-up before it).
PARTS = (
    ("scheduling", lambda dso, sym: dso == "[kernel.kallsyms]" and (
        sym.startswith(("finish_task_switch", "_raw_spin_unlock_irq", "schedule", "__schedule", "try_to_wake_up"))
        or "futex" in sym)),
    ("kernel", lambda dso, sym: dso == "[kernel.kallsyms]"),
    ("engine", lambda dso, sym: dso.startswith("libm") or sym in LIBM or (
        sym.startswith("bone_sim::") and not sym.startswith("bone_sim::transport"))),
    ("glue", lambda dso, sym: sym.startswith("bone_sim::transport") or "bone_sim" in sym),
    ("zenoh", lambda dso, sym: any(w in sym for w in ("zenoh", "tokio", "event_listener", "flume", "future"))),
    ("libc", lambda dso, sym: dso.startswith("libc")),
)  # fmt: skip


def perf_start(pid: int, seconds: float, data: str) -> subprocess.Popen[str]:
    """Starts ``perf record`` of process ``pid`` for ``seconds``, into ``data``."""
    try:
        return subprocess.Popen(
            ["perf", "record", "-F", str(PERF_HZ), "-p", str(pid), "-o", data, "--", "sleep", f"{seconds:g}"],
            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
        )  # fmt: skip
    except FileNotFoundError:
        raise SystemExit("--perf needs perf (Debian: linux-perf)") from None


def perf_parts(record: subprocess.Popen[str], data: str, seconds: float) -> dict[str, float]:
    """Waits for ``record`` (:func:`perf_start`); the sampled CPU (cores) by part."""
    _, err = record.communicate(timeout=seconds + 60)
    if record.returncode != 0:
        raise SystemExit(f"perf record failed (kernel.perf_event_paranoid?): {err.strip()}")
    report = subprocess.run(
        ["perf", "report", "-i", data, "--no-children", "--sort", "dso,sym", "-n", "-q", "--stdio"],
        capture_output=True, text=True, check=True,
    ).stdout  # fmt: skip
    parts = dict.fromkeys([name for name, _ in PARTS] + ["other"], 0.0)
    for line in report.splitlines():
        cols = line.split(None, 4)  # percent, samples, dso, [k] or [.], symbol
        if len(cols) < 5 or not cols[1].isdigit():
            continue
        dso, sym = cols[2], cols[4].strip()
        part = next((name for name, match in PARTS if match(dso, sym)), "other")
        parts[part] += int(cols[1]) / (PERF_HZ * seconds)
    return {k: round(v, 4) for k, v in parts.items()}


def one(
    variant: str,
    n: int,
    seconds: float,
    other: str | None,
    work_us: float = 0.0,
    role: str = "sim",
    perf: bool = False,
) -> dict[str, Any]:
    """One run: a fresh server of ``variant`` and ``n`` load-tool clients (``echo-work``: the echo
    spinning ``work_us`` in each pose's callback; a ``dhg-serve`` variant in ``role``)."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    if variant.startswith("echo"):
        work = ["--work-us", f"{work_us:g}"] if variant == "echo-work" else []
        work += ["--mode", "router"] if variant == "echo-router" else []
        cmd = [str(EXAMPLES / "echo"), "--listen", endpoint, *work]
        server: Any = subprocess.Popen(cmd, stderr=subprocess.PIPE, text=True)
        try:
            _wait_for_echo(server)
        except BaseException:
            server.kill()
            raise
        pid = server.pid
    else:
        model = ["--device", "cpu"] if role == "all" else []
        args = ["--listen", endpoint, "--role", role, *model, "--max-sessions", str(max(n, 16))]
        server = serve_from(str(other) if variant == "other" else None, args)
        pid = server.proc.pid
    perf_dir = tempfile.TemporaryDirectory() if perf else None
    try:
        # Python's threads carry the process's name: with the model service, its worker's.
        own = Path(f"/proc/{pid}/comm").read_text().strip() if role == "all" else None
        load = subprocess.Popen(
            [str(EXAMPLES / "load"), "--connect", endpoint, "--clients", str(n), "--seconds", f"{seconds:g}",
             "--server-pid", str(pid)],
            stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True,
        )  # fmt: skip
        # The middle of the run: after the clients' 2 s warm-up, before their end.
        time.sleep(2.0 + 0.2 * seconds)
        # perf samples the same window as the threads' counters, alongside.
        record = perf_start(pid, 0.6 * seconds, f"{perf_dir.name}/perf.data") if perf_dir else None
        a, t0 = threads(pid), time.monotonic()
        time.sleep(0.6 * seconds)
        b, dt = threads(pid), time.monotonic() - t0
        parts = perf_parts(record, f"{perf_dir.name}/perf.data", 0.6 * seconds) if perf_dir and record else None
        out = json.loads(load.communicate(timeout=seconds + 60)[0])
    finally:
        if variant.startswith("echo"):
            server.terminate()
            server.wait(timeout=30)
        else:
            server.stop()
        if perf_dir is not None:
            perf_dir.cleanup()
    per: dict[str, list[float]] = {}
    for tid, (name, cpu, sw) in b.items():
        if name == own and not variant.startswith("echo"):
            name = "model"
        if tid in a:
            p = per.setdefault(name, [0.0, 0.0])
            p[0] += (cpu - a[tid][1]) / dt
            p[1] += (sw - a[tid][2]) / dt
    return {
        "variant": variant,
        **({"role": role} if not variant.startswith("echo") else {}),
        **({"work_us": work_us} if variant == "echo-work" else {}),
        "clients": n,
        "cpu_cores": out["server_cpu_cores"],
        "p50_ms": out["pose_to_force_ms"]["p50"],
        "forces_per_pose": out["forces_per_pose"],
        "threads": {k: {"cores": round(v[0], 4), "wakeups_per_s": round(v[1])} for k, v in per.items()},
        **({"perf_cores": parts} if parts is not None else {}),
    }


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--clients", default="1,4,16")
    p.add_argument("--rounds", type=int, default=2)
    p.add_argument("--seconds", type=float, default=12.0, help="load per run (s; threads read over its middle 60 %%)")
    p.add_argument("--other", metavar="PYTHONPATH", help="a second engine build, run as the variant 'other'")
    p.add_argument(
        "--echo-work-us",
        type=float,
        metavar="US",
        help="also the echo spinning US microseconds in each pose's callback (echo --work-us), as the variant "
        "'echo-work': what a tick's worth of work on the receive threads costs by itself",
    )
    p.add_argument(
        "--echo-router",
        action="store_true",
        help="also the echo in Zenoh's router mode (echo --mode router), as the variant 'echo-router': the "
        "engine is a router, the echo a peer",
    )
    p.add_argument(
        "--role",
        choices=("sim", "all"),
        default="sim",
        help="dhg-serve's role in the dhg and other variants: sim, the engine alone (default); all, with the "
        "model service in its process (model on CPU)",
    )
    p.add_argument(
        "--perf",
        action="store_true",
        help="also sample each server with perf record over the same window and split its CPU by part "
        "(engine, zenoh, glue, scheduling, kernel, libc, other)",
    )
    p.add_argument("--out", help="also append the JSON lines to this file")
    args = p.parse_args()
    variants = [
        "dhg",
        *(["other"] if args.other else []),
        *(["echo-work"] if args.echo_work_us else []),
        *(["echo-router"] if args.echo_router else []),
        "echo",
    ]
    runs: list[dict[str, Any]] = []
    for _ in range(args.rounds):
        for n in (int(c) for c in args.clients.split(",")):
            for v in variants:
                r = one(v, n, args.seconds, args.other, args.echo_work_us or 0.0, args.role, args.perf)
                print(json.dumps(r), flush=True)
                runs.append(r)
                if args.out:
                    with open(args.out, "a") as f:
                        f.write(json.dumps(r) + "\n")
    print(f"\n{args.rounds} rounds, medians; cores (wake-ups a second)\n")
    names = ["rx", "tx-0", "acc-0", "dhg-tick", "dhg-comm", *(["model"] if args.role == "all" else [])]
    print("| clients | variant | CPU (cores) | / echo | " + " | ".join(names) + " |")
    print("|---:|---|---:|---:|" + "---:|" * len(names))
    for n in sorted({r["clients"] for r in runs}):
        echo = statistics.median(r["cpu_cores"] for r in runs if r["clients"] == n and r["variant"] == "echo")
        for v in variants:
            rs = [r for r in runs if r["clients"] == n and r["variant"] == v]
            cpu = statistics.median(r["cpu_cores"] for r in rs)
            cells = []
            for name in names:
                picked = [
                    [t for k, t in r["threads"].items() if k == name or (name == "rx" and k.startswith("rx-"))]
                    for r in rs
                ]
                cores = statistics.median(sum(t["cores"] for t in ts) for ts in picked)
                wakes = statistics.median(sum(t["wakeups_per_s"] for t in ts) for ts in picked)
                cells.append(f"{cores:.3f} ({wakes:.0f})" if any(picked) else "—")
            print(f"| {n} | {v} | {cpu:.3f} | {cpu / echo:.2f} | " + " | ".join(cells) + " |")
    if args.perf:
        parts = [name for name, _ in PARTS] + ["other"]
        print("\nperf, medians (cores)\n")
        print("| clients | variant | " + " | ".join(parts) + " |")
        print("|---:|---|" + "---:|" * len(parts))
        for n in sorted({r["clients"] for r in runs}):
            for v in variants:
                rs = [r["perf_cores"] for r in runs if r["clients"] == n and r["variant"] == v]
                cells = [f"{statistics.median(r[k] for r in rs):.3f}" for k in parts]
                print(f"| {n} | {v} | " + " | ".join(cells) + " |")


if __name__ == "__main__":
    main()
