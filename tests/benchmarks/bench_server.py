"""Load benchmark of ``dhg-serve``: for each client count, a fresh server (phantom, bundled model)
and the Rust load tool (``crates/bone_sim/examples/load.rs``) streaming 1 kHz poses from that
many trainees. Prints one JSON line per run (latencies in ms, server CPU in cores).

    cargo build --release -p bone_sim --example load
    python tests/benchmarks/bench_server.py --seconds 60 --clients 1,16,64 [--load PATH] [--wait spin]
        [--device cpu] [--lowlatency] [--client-slices] [--record-all]

``--record-all`` also runs ``dhg record --all --raw`` (in this process) over the load and adds what
it kept: each session's 1 kHz ticks written against the ticks it ran, and the recorder's CPU.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import tempfile
from pathlib import Path

from dhg.live_demo import ServerProcess, free_port

# The `transport` section of Zenoh's low-latency mode (it excludes QoS; both ends must ask for it).
LOWLATENCY = {"unicast": {"lowlatency": True, "qos": {"enabled": False}}}


def main() -> None:
    target = Path(os.environ.get("CARGO_TARGET_DIR", Path.home() / ".cache/dhg/target"))
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--seconds", type=float, default=60.0)
    p.add_argument("--clients", default="1,16,64")
    p.add_argument("--load", default=str(target / "release/examples/load"), help="the load tool binary")
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
    args = p.parse_args()
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


class _Recording:
    """``dhg record --all --raw`` in a thread of this process, into a temporary folder."""

    def __init__(self, endpoint: str) -> None:
        import resource
        import threading
        import time

        from dhg.recorder import AllSessionsRecorder

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

        from dhg.dataset import load_raw

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
