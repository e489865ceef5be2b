"""Load benchmark of ``dhg-serve``: for each client count, a fresh server (phantom, bundled model)
and the Rust load tool (``crates/bone_sim/examples/load.rs``) streaming 1 kHz poses from that
many trainees. Prints one JSON line per run (latencies in ms, server CPU in cores).

    cargo build --release -p bone_sim --example load
    python tests/benchmarks/bench_server.py --seconds 60 --clients 1,16,64 [--load PATH] [--wait spin]
        [--device cpu] [--lowlatency] [--client-slices] [--record-all]

``--record-all`` also runs ``dhg record --all --raw`` (in this process) over the load and adds what
it kept: each session's 1 kHz ticks written against the ticks it ran, and the recorder's CPU.

``--against-echo`` sets the server beside the transport's floor (issue 24): for each client count it
alternates, ``--rounds`` times, a fresh ``dhg-serve`` (ticking each session on its pose's thread),
a fresh ``dhg-serve --tick-on thread`` (every pose handed to the tick thread: the design before) and
a fresh bare Zenoh echo with the same key space and QoS (``crates/bone_sim/examples/echo.rs``),
runs the same load against each, and prints the medians and their ratios (server / echo) of pose →
force p50 and p99 and of server CPU per session. On a shared VM the absolute figures move from run
to run; the ratios far less.

    cargo build --release -p bone_sim --example load --example echo
    python tests/benchmarks/bench_server.py --against-echo --seconds 20 --clients 1,4,16 --rounds 2
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import re
import select
import statistics
import subprocess
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from dhg.live.process import ServerProcess, free_port

CACHE = Path(os.environ.get("DHG_CACHE", Path.home() / ".cache/dhg"))
"""Where ``make`` keeps the build (the Makefile's ``DHG_CACHE``, which the environment may set)."""
EXAMPLES = Path(os.environ.get("CARGO_TARGET_DIR", CACHE / "target")) / "release/examples"
"""The load tool and the echo, as ``cargo build --release -p bone_sim --example load --example echo``
builds them (the Makefile's ``CARGO_TARGET_DIR``, unless the environment names another)."""

# The `transport` section of Zenoh's low-latency mode (it excludes QoS; both ends must ask for it).
LOWLATENCY = {"unicast": {"lowlatency": True, "qos": {"enabled": False}}}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--seconds", type=float, default=60.0)
    p.add_argument("--clients", default="1,16,64")
    p.add_argument("--load", default=str(EXAMPLES / "load"), help="the load tool binary")
    p.add_argument("--out", help="also append the JSON lines to this file")
    p.add_argument("--wait", default="sleep", choices=("sleep", "spin"), help="dhg-serve --wait (default sleep)")
    p.add_argument("--device", choices=("auto", "cpu", "cuda"), help="dhg-serve --device (default auto)")
    p.add_argument(
        "--client-slices",
        action="store_true",
        help="the load tool's sending thread and Zenoh threads also ask for the 0.1 ms slice, as the server's do",
    )
    p.add_argument(
        "--lowlatency",
        action="store_true",
        help="Zenoh's low-latency transport (no QoS) on both sides: a put is written by the calling thread",
    )
    p.add_argument("--record-all", action="store_true", help="record every session with its 1 kHz stream meanwhile")
    p.add_argument("--against-echo", action="store_true", help="alternate dhg-serve with the bare echo; print ratios")
    p.add_argument("--rounds", type=int, default=2, help="with --against-echo: rounds of each (default 2)")
    p.add_argument("--echo", default=str(EXAMPLES / "echo"), help="the echo binary")
    p.add_argument(
        "--variants",
        default="dhg,dhg-thread,dhg-sim,echo",
        help="with --against-echo, alternated in this order: dhg (dhg-serve, ticks on the pose's thread), "
        "dhg-thread (dhg-serve --tick-on thread: the tick thread ticks every pose), dhg-sim (dhg-serve --role "
        "sim, the model service in a process of its own, its CPU reported apart), dhg-engine (dhg-serve --role "
        "sim and no model service), dhg-niceN (dhg-serve --model-nice N, 0 to 19: dhg-nice0 puts the model's "
        "worker thread at the engine's priority, as before decision 0026), dhg-ts (dhg-serve --executor "
        "torchscript: the passes by TorchScript, as before decision 0030), other (dhg-serve from the build "
        "--other names), echo (must be included). A variant may end in +rx1 (Zenoh's receive runtime on one "
        "worker thread, ZENOH_RUNTIME); a server variant with a tag is set against echo+TAG where the run has it",
    )
    p.add_argument(
        "--other",
        metavar="PYTHONPATH",
        help="with --against-echo: a second build (a checkout's python/ folder with its extension built), run as "
        "the variant 'other' (dhg-serve as the variant dhg runs it)",
    )
    args = p.parse_args()
    if args.against_echo:
        _against_echo(args)
        return
    conf_dir = tempfile.TemporaryDirectory()
    conf = Path(conf_dir.name) / "lowlatency.json5"
    conf.write_text(json.dumps({"scouting": {"multicast": {"enabled": False}}, "transport": LOWLATENCY}))
    for n in (int(c) for c in args.clients.split(",")):
        endpoint = f"tcp/127.0.0.1:{free_port()}"
        serve_args = ["--listen", endpoint, "--max-sessions", str(max(n, 16)), "--status-every", "30",
                      "--wait", args.wait]  # fmt: skip
        if args.device:
            serve_args += ["--device", args.device]
        load_args = ["--lowlatency"] if args.lowlatency else []
        if args.client_slices:
            load_args.append("--short-slices")
        if args.lowlatency:
            serve_args += ["--zenoh-config", str(conf)]
        server = ServerProcess(serve_args, echo=False)
        recording = _Recording(endpoint) if args.record_all else None
        try:
            r = subprocess.run(
                [args.load, "--connect", endpoint, "--clients", str(n), "--seconds", str(args.seconds),
                 "--server-pid", str(server.proc.pid), *load_args],
                capture_output=True, text=True, timeout=args.seconds + 120,
            )  # fmt: skip
            kept = recording.finish() if recording else None
        finally:
            server.stop()
        if r.returncode != 0:
            raise SystemExit(f"load tool failed ({r.returncode}): {r.stderr}")
        line = json.dumps(
            {
                "cpus": os.cpu_count(),
                "wait": args.wait,
                "device": args.device or "auto",
                "lowlatency": args.lowlatency,
                **json.loads(r.stdout),
                **({"recorder": kept} if kept else {}),
            }
        )
        print(line, flush=True)
        if args.out:
            with open(args.out, "a") as fh:
                fh.write(line + "\n")
    conf_dir.cleanup()


def serve_from(pythonpath: str | None, args: list[str]) -> ServerProcess:
    """``dhg-serve ARGS`` (returns once it says it is ready), from the build whose ``python/``
    folder ``pythonpath`` names, or from this one."""
    saved = os.environ.get("PYTHONPATH")
    if pythonpath is not None:
        os.environ["PYTHONPATH"] = pythonpath
    try:
        return ServerProcess(args, echo=False)
    finally:
        if saved is None:
            os.environ.pop("PYTHONPATH", None)
        else:
            os.environ["PYTHONPATH"] = saved


def _wait_for_echo(proc: subprocess.Popen[Any], deadline_s: float = 60.0) -> None:
    """Waits for the echo (started with ``stderr=PIPE``) to say it is ready: it does so once its
    keys are declared, which in router mode comes after it listens."""
    end = time.monotonic() + deadline_s
    while (left := end - time.monotonic()) > 0:
        if proc.poll() is not None:
            raise SystemExit(f"the echo exited ({proc.returncode}): {proc.stderr.read() if proc.stderr else ''}")
        if proc.stderr and select.select([proc.stderr], [], [], min(left, 0.5))[0]:
            if "echo listening" in proc.stderr.readline():
                return
    raise SystemExit(f"the echo did not say it was ready within {deadline_s} s")


def _context_switches(pid: int) -> int:
    """Context switches (voluntary and not) of every thread of ``pid`` so far (Linux ``/proc``)."""
    total = 0
    for status in Path(f"/proc/{pid}/task").glob("*/status"):
        try:
            for line in status.read_text().splitlines():
                if "ctxt_switches:" in line:
                    total += int(line.split()[1])
        except (OSError, ValueError):  # a thread that ended meanwhile
            continue
    return total


def _one_load(args: argparse.Namespace, target: str, n: int) -> dict[str, Any]:
    """One round: a fresh ``target`` and the load tool with ``n`` clients. Targets: ``dhg``
    (``dhg-serve``: engine and model service in one process), ``dhg-thread`` (``dhg-serve --tick-on
    thread``), ``dhg-sim`` (``dhg-serve --role sim``, the engine, with the model service in a second
    process, ``--role model``, whose CPU is reported apart as ``model_cpu_per_session``),
    ``dhg-engine`` (``--role sim`` with no model service: the sessions tick, their model queries go
    unanswered; what the engine costs without the model's forward passes on the same cores),
    ``dhg-niceN`` (``dhg-serve --model-nice N``), ``dhg-ts`` (``dhg-serve --executor torchscript``:
    the forward passes by TorchScript, as before decision 0030), ``other`` (``dhg-serve`` from the build
    ``--other`` names), ``echo``."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    server: Any = None
    model: Any = None
    echo: subprocess.Popen[str] | None = None
    target, _, tag = target.partition("+")
    with _zenoh_runtime(tag):
        if target.startswith("dhg") or target == "other":
            tick_on = "thread" if target == "dhg-thread" else "pose"
            role = "sim" if target in ("dhg-sim", "dhg-engine") else "all"
            nice = ["--model-nice", target.removeprefix("dhg-nice")] if target.startswith("dhg-nice") else []
            nice += ["--executor", "torchscript"] if target == "dhg-ts" else []
            device = ["--device", args.device] if args.device else []
            server = serve_from(
                args.other if target == "other" else None,
                ["--listen", endpoint, "--max-sessions", str(max(n, 16)), "--status-every", "5", "--tick-on", tick_on,
                 "--role", role, *nice, *device],
            )  # fmt: skip
            if target == "dhg-sim":
                try:
                    model = ServerProcess(
                        ["--role", "model", "--connect", endpoint, "--status-every", "30", *device], echo=False
                    )
                except BaseException:
                    server.stop()
                    raise
            pid = server.proc.pid
        else:
            echo = subprocess.Popen([args.echo, "--listen", endpoint], stderr=subprocess.PIPE, text=True)
            try:
                _wait_for_echo(echo)
            except BaseException:
                echo.kill()
                raise
            pid = echo.pid
    try:
        switches0 = _context_switches(pid)
        model_cpu0 = _cpu_s(model.proc.pid) if model is not None else 0.0
        t0 = time.perf_counter()
        with _zenoh_runtime(""):  # the load tool on Zenoh's defaults, whatever the variant
            r = subprocess.run(
                [args.load, "--connect", endpoint, "--clients", str(n), "--seconds", str(args.seconds),
                 "--server-pid", str(pid)],
                capture_output=True, text=True, timeout=args.seconds + 120,
            )  # fmt: skip
        switches = _context_switches(pid) - switches0
        # The model service's queries per forward pass, from dhg-serve's newest status line.
        said = [m for line in (server.lines if server is not None else []) if (m := _BATCHES.search(line))]
        per_pass = int(said[-1][1]) / max(int(said[-1][2]), 1) if said else None
        model_cores = (_cpu_s(model.proc.pid) - model_cpu0) / (time.perf_counter() - t0) if model is not None else 0.0
    finally:
        if model is not None:
            model.stop()
        if server is not None:
            server.stop()
        if echo is not None:
            echo.terminate()
            echo.wait(timeout=30)
    if r.returncode != 0:
        raise SystemExit(f"load tool against {target} failed ({r.returncode}): {r.stderr}")
    out = json.loads(r.stdout)
    return {
        "target": f"{target}+{tag}" if tag else target,
        "clients": n,
        **({"device": args.device} if args.device and target != "echo" else {}),
        "p50_ms": out["pose_to_force_ms"]["p50"],
        "p99_ms": out["pose_to_force_ms"]["p99"],
        "cpu_cores": out["server_cpu_cores"],
        "cpu_per_session": out["server_cpu_cores"] / n,
        "forces_per_pose": out["forces_per_pose"],
        "guidance_p50_ms": out["pose_to_guidance_ms"]["p50"],
        "guidance_p99_ms": out["pose_to_guidance_ms"]["p99"],
        # Over the whole load run (its 2 s warm-up and the connects included): per pose sent.
        "context_switches_per_pose": switches / (n * (args.seconds + 2.0) * 1000.0),
        # The model service's process (dhg-sim only), over the whole load run.
        "model_cpu_per_session": model_cores / n,
        "model_queries_per_pass": per_pass,
    }


# Zenoh runtime settings a variant can name after a "+" (dhg-engine+rx1, echo+rx1): ZENOH_RUNTIME for
# the server's process (and the model service's in it). rx1: one receive worker thread instead of two.
RUNTIMES = {"rx1": "(rx: (worker_threads: 1))"}


@contextlib.contextmanager
def _zenoh_runtime(tag: str) -> Iterator[None]:
    """``ZENOH_RUNTIME`` for the processes started inside: ``RUNTIMES[tag]``, or unset without a
    tag (Zenoh's defaults, whatever this shell has); put back as it was on every path."""
    saved = os.environ.pop("ZENOH_RUNTIME", None)
    if tag:
        os.environ["ZENOH_RUNTIME"] = RUNTIMES[tag]
    try:
        yield
    finally:
        os.environ.pop("ZENOH_RUNTIME", None)
        if saved is not None:
            os.environ["ZENOH_RUNTIME"] = saved


SERVERS = ("dhg", "dhg-thread", "dhg-sim", "dhg-engine", *(f"dhg-nice{n}" for n in range(20)), "dhg-ts", "other")


def _check_variants(args: argparse.Namespace, variants: list[str]) -> None:
    """Refuses, before the first round, a variant this script does not know."""
    for v in variants:
        base, _, tag = v.partition("+")
        if base not in (*SERVERS, "echo") or (tag and tag not in RUNTIMES):
            raise SystemExit(
                f"--variants: unknown {v!r}; {', '.join(SERVERS)}, echo, each optionally +{'|+'.join(RUNTIMES)}"
            )
        if base == "other" and not args.other:
            raise SystemExit("the variant 'other' needs --other PYTHONPATH")
    if "echo" not in variants:
        raise SystemExit("--variants must include echo (the ratios' denominator)")


_BATCHES = re.compile(r"model service answered (\d+) in (\d+) batches")


def _cpu_s(pid: int) -> float:
    """CPU time (user + system, s) of process ``pid`` so far (Linux ``/proc``)."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def _against_echo(args: argparse.Namespace) -> None:
    rows = []
    variants = args.variants.split(",")
    _check_variants(args, variants)
    servers = [v for v in variants if not v.startswith("echo")]
    for n in (int(c) for c in args.clients.split(",")):
        runs: dict[str, list[dict[str, Any]]] = {v: [] for v in variants}
        for _ in range(args.rounds):
            for target in variants:
                run = _one_load(args, target, n)
                runs[target].append(run)
                print(json.dumps({"cpus": os.cpu_count(), "seconds": args.seconds, **run}), flush=True)
                if args.out:
                    with open(args.out, "a") as fh:
                        fh.write(json.dumps({"cpus": os.cpu_count(), "seconds": args.seconds, **run}) + "\n")

        def med(target: str, key: str, runs: dict[str, list[dict[str, Any]]] = runs) -> float:
            return statistics.median(r[key] for r in runs[target])

        for s in servers:
            # Each server against the echo with the same runtime tag where the run has one.
            e = f"echo+{s.partition('+')[2]}" if f"echo+{s.partition('+')[2]}" in runs else "echo"
            rows.append(
                (n, s, e, *(med(t, k) for k in ("p50_ms", "p99_ms", "cpu_per_session", "context_switches_per_pose")
                         for t in (s, e)), med(s, "forces_per_pose"), med(s, "model_cpu_per_session"),
                 statistics.median([r["guidance_p99_ms"] or 0.0 for r in runs[s]]),
                 statistics.median([r["model_queries_per_pass"] or 0.0 for r in runs[s]]))
            )  # fmt: skip
    print(f"\n{args.rounds} rounds of {args.seconds:g} s each, alternating; medians; {os.cpu_count()} CPUs\n")
    print("| clients | server | against | pose → force p50, server / echo (ms) | ratio "
          "| p99, server / echo (ms) | ratio "
          "| server CPU per session, server / echo (cores) | ratio | context switches per pose, server / echo "
          "| forces per pose | model service's process, CPU per session (cores) "
          "| pose → guidance p99 (ms) | model queries per forward pass |")  # fmt: skip
    print("|---:|---|---|---|---:|---|---:|---|---:|---|---:|---:|---:|---:|")
    for n, s, e, p50d, p50e, p99d, p99e, cpud, cpue, swd, swe, fpp, mcpu, gp99, qpp in rows:
        model = f"{mcpu:.4f}" if s.partition("+")[0] == "dhg-sim" else "(in the server)"
        print(
            f"| {n} | {s} | {e} | {p50d:.3f} / {p50e:.3f} | {p50d / p50e:.2f} | {p99d:.3f} / {p99e:.3f} "
            f"| {p99d / p99e:.2f} | {cpud:.4f} / {cpue:.4f} | {cpud / cpue:.2f} | {swd:.2f} / {swe:.2f} | {fpp:.3f} "
            f"| {model} | {f'{gp99:.2f}' if gp99 else '—'} | {f'{qpp:.2f}' if qpp else '—'} |"
        )


class _Recording:
    """``dhg record --all --raw`` in a thread of this process, into a temporary folder."""

    def __init__(self, endpoint: str) -> None:
        import resource
        import threading
        import time

        from dhg.live.recorder import AllSessionsRecorder

        self._dir = tempfile.TemporaryDirectory()
        self.rec = AllSessionsRecorder(endpoint, self._dir.name, raw=True)
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self.rec.run, args=(self.stop,))
        usage = resource.getrusage(resource.RUSAGE_SELF)
        self.cpu0, self.wall0 = usage.ru_utime + usage.ru_stime, time.perf_counter()
        self.thread.start()

    def finish(self) -> dict:
        """Stops it; the ticks each session kept and the recorder's CPU (cores)."""
        import resource
        import time

        from dhg.data.dataset import load_raw

        self.stop.set()
        self.thread.join()
        usage = resource.getrusage(resource.RUSAGE_SELF)
        cpu = (usage.ru_utime + usage.ru_stime - self.cpu0) / (time.perf_counter() - self.wall0)
        self.rec.close()
        fractions = []
        for session_id in self.rec.sessions:
            raw = load_raw(Path(self._dir.name) / session_id)
            ticks = raw.column("tick").to_numpy() if raw is not None else []
            fractions.append(len(ticks) / (ticks[-1] - ticks[0] + 1) if len(ticks) else 0.0)
        self._dir.cleanup()
        return {
            "sessions": len(fractions),
            "ticks_kept_min": round(min(fractions), 5) if fractions else None,
            "ticks_kept_mean": round(sum(fractions) / len(fractions), 5) if fractions else None,
            "cpu_cores": round(cpu, 3),
        }


if __name__ == "__main__":
    main()
