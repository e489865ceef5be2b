"""The fault matrix: hostile peers, frozen subscribers, floods of puts and of queries, oversized
payloads, a model worker killed or stopped, a server killed while recording, each against a live
``dhg-serve`` on loopback. For every fault it prints what was expected, what happened, the
measured loss and recovery, and PASS or FAIL; it exits 1 if any fault failed.

    python tests/benchmarks/fault_matrix.py [--only NAME,NAME] [--json FILE]

About two minutes on 2 cores. ``docs/reliability.md`` holds its output.
"""

from __future__ import annotations

import argparse
import json
import os
import select
import signal
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from dhg.core import protocol
from dhg.core.errors import EngineError
from dhg.live.client import TraineeClient
from dhg.live.process import ServerProcess, free_port

PEAK_N = 3.3


@dataclass
class Outcome:
    fault: str
    expected: str
    happened: str
    ok: bool


def serve(*args: str) -> tuple[ServerProcess, str]:
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    return ServerProcess(["--listen", endpoint, "--voxel-mm", "1.0", *args], echo=False), endpoint


def entry(c: TraineeClient) -> tuple[np.ndarray, np.ndarray]:
    info = c.create()
    a, b = np.array(info["entry_m"]), np.array(info["target_m"])
    return a, (b - a) / np.linalg.norm(b - a)


def stream(c: TraineeClient, seconds: float, depth_m: float = 0.0) -> None:
    """1 kHz poses on absolute deadlines, the drill on, moving from 3 mm before A to ``depth_m``."""
    a, d = entry(c)
    n = int(seconds * 1000)
    t0 = time.monotonic_ns()
    for k in range(n):
        s = -3e-3 + (depth_m + 3e-3) * k / n
        c.send_pose(a + d * s, (1.0, 0.0, 0.0, 0.0), True, 1200.0)
        pause = t0 + (k + 1) * 1_000_000 - time.monotonic_ns()
        if pause > 0:
            time.sleep(pause * 1e-9)


def record(endpoint: str, *args: str) -> subprocess.Popen[str]:
    """``dhg record --connect endpoint ARGS --status-every 0`` in its own process, output on one pipe."""
    return subprocess.Popen(
        [sys.executable, "-m", "dhg.cli.main", "record", "--connect", endpoint, *args, "--status-every", "0"],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        env=dict(os.environ, PYTHONUNBUFFERED="1"),
    )


def wait_for(cond: Callable[[], bool], timeout_s: float, what: str) -> None:
    """Polls ``cond`` until it holds; a fault whose precondition never comes fails, saying which."""
    deadline = time.monotonic() + timeout_s
    while not cond():
        if time.monotonic() > deadline:
            raise TimeoutError(f"{what}: not within {timeout_s:g} s")
        time.sleep(0.01)


def gaps(times: list[float], t0: float) -> float:
    t = np.array([x for x in times if x >= t0])
    return float(np.diff(t).max()) if len(t) > 1 else float("inf")


def forged_forces(endpoint: str) -> Outcome:
    handed: list[tuple] = []
    with (
        TraineeClient(endpoint, "victim", on_force=lambda m: handed.append(m["force_n"])) as v,
        TraineeClient(endpoint, "rogue") as r,
    ):
        th = threading.Thread(target=stream, args=(v, 2.0))
        th.start()
        for payload in (
            protocol.encode("force", force_n=(float("nan"), 0.0, 0.0)),
            protocol.encode("force", force_n=(1e6, 0.0, 0.0)),
            protocol.encode("force", force_n=(0.0, 0.0, 3.2)),
        ) * 100:
            r._z.put(v.keys["force"], payload)
        th.join()
        rej = dict(v.guard.rejected)
    f = np.array(handed)
    worst = float(np.linalg.norm(f, axis=1).max())
    finite = bool(np.all(np.isfinite(f)))
    return Outcome(
        "forged forces on another session's key (100 NaN, 100 × 1e6 N, 100 × 3.2 N jolts)",
        "the client hands on no NaN and nothing above 3.3 N; refusals counted",
        f"handed {len(f)} forces, all finite: {finite}, largest {worst:.2f} N; refused {rej}",
        finite and worst <= PEAK_N and rej["non_finite"] > 0 and rej["over_limit"] > 0,
    )


def fake_ids_and_impossible_states(endpoint: str, root: Path) -> Outcome:
    out = root / "class"
    rec = record(endpoint, "--all", "--out", str(out))
    assert rec.stdout is not None
    rec.stdout.readline()
    with TraineeClient(endpoint, "real") as c, TraineeClient(endpoint, "rogue2") as r:
        for k in range(2000):
            r._z.put(f"dhg/session/fake-{k}/state", protocol.encode("state", time_s=0.5))
        for sid in (".", ".."):
            r._z.put(f"dhg/session/{sid}/state", protocol.encode("state", time_s=0.5))
        th = threading.Thread(target=stream, args=(c, 3.0))
        th.start()
        wait_for(lambda: len(c.states) >= 5, 10.0, "the real session's first states")
        for bad in (float("nan"), 1e30):
            r._z.put("dhg/session/real/state", protocol.encode("state", time_s=bad))
        th.join()
    wait_for(lambda: (out / "real" / "card.json").exists(), 10.0, "the recorder's first flush of the real session")
    rec.send_signal(signal.SIGINT)
    text, _ = rec.communicate(timeout=30)
    folders = sorted(p.name for p in out.iterdir()) if out.exists() else []
    fake = [f for f in folders if f.startswith(("fake-", "."))]
    return Outcome(
        "2,000 fake session ids and '.', '..' put on state; a NaN and a 1e30 s state in a real session",
        "dhg record --all records only sessions the server has (none of the fakes), counts the rest, exits 0",
        f"exit {rec.returncode}; folders {folders}; last line: {text.strip().splitlines()[-1]!r}",
        rec.returncode == 0 and "real" in folders and not fake,
    )


FROZEN = """
import json, sys, zenoh
conf = {"mode": "client", "connect": {"endpoints": ["%s"]}, "scouting": {"multicast": {"enabled": False}}}
z = zenoh.open(zenoh.Config.from_json5(json.dumps(conf)))
sub = z.declare_subscriber("dhg/**", lambda s: None)
print("ready", flush=True)
sys.stdin.read()  # until the harness closes the pipe (or kills it)
"""


def frozen_subscriber(endpoint: str) -> Outcome:
    frozen = subprocess.Popen(
        [sys.executable, "-c", FROZEN % endpoint], stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True
    )
    assert frozen.stdout is not None
    frozen.stdout.readline()
    os.kill(frozen.pid, signal.SIGSTOP)
    arrivals: list[float] = []
    stop = threading.Event()
    try:
        with (
            TraineeClient(endpoint, "flow", on_force=lambda m: arrivals.append(time.monotonic())) as c,
            TraineeClient(endpoint, "flooder") as fl,
        ):
            blob = b"x" * 60_000
            th = threading.Thread(target=lambda: [fl._z.put("dhg/flood/x", blob) for _ in iter(stop.is_set, True)])
            th.start()
            t0 = time.monotonic()
            stream(c, 5.0)
            stop.set()
            th.join()
    finally:
        os.kill(frozen.pid, signal.SIGCONT)
        frozen.kill()
        frozen.wait()
        frozen.stdout.close()
        frozen.stdin.close()
    gap = gaps(arrivals, t0)
    return Outcome(
        "a subscriber to dhg/** frozen (SIGSTOP), its link flooded with 60 KB puts, while a trainee drills 5 s",
        "the trainee's forces flow on (largest gap well under 0.5 s)",
        f"largest gap between forces {gap * 1e3:.1f} ms over {len([a for a in arrivals if a >= t0])} forces",
        gap < 0.5,
    )


QUERY_FLOOD = """
import json, sys, threading, time, zenoh
conf = {"mode": "client", "connect": {"endpoints": ["%s"]}, "scouting": {"multicast": {"enabled": False}}}
z = zenoh.open(zenoh.Config.from_json5(json.dumps(conf)))
keys, seconds = %r, %r
# Per key, queries: answered (a reply, no error), refused (an error reply) and unanswered (none
# within the timeout). An X-ray query of * has three replies, one a view: it counts once.
counts = [[0, 0, 0] for _ in keys]
print("ready", flush=True)
end = time.monotonic() + seconds
def loop(i):
    while time.monotonic() < end:
        try:
            replies = list(z.get(keys[i], timeout=5.0))
        except Exception:
            replies = []
        if not replies:
            counts[i][2] += 1
        elif all(r.ok for r in replies):
            counts[i][0] += 1
        else:
            counts[i][1] += 1
threads = [threading.Thread(target=loop, args=(i,)) for i in range(len(keys))]
[t.start() for t in threads]
[t.join() for t in threads]
print(json.dumps({"answered": [c[0] for c in counts], "refused": [c[1] for c in counts],
                  "unanswered": [c[2] for c in counts]}), flush=True)
z.close()
"""


def query_flood(endpoint: str) -> Outcome:
    """Another client floods the queries that do work on the server (its health, the victim's
    metrics, bricks and X-rays), back to back, from four threads, while the victim drills."""
    seconds = 6.0
    keys = [
        "dhg/server/health",
        "dhg/session/victim-q/metrics",
        "dhg/session/victim-q/bone",
        "dhg/session/victim-q/xray/*",
    ]
    arrivals: list[float] = []
    with TraineeClient(endpoint, "victim-q", on_force=lambda m: arrivals.append(time.monotonic())) as c:
        # Without the flood first: the guidance latency to compare with.
        stream(c, 3.0, depth_m=0.005)
        quiet = np.array(list(c.guidance_latencies_s)[-20:]) * 1e3
        flood = subprocess.Popen(
            [sys.executable, "-c", QUERY_FLOOD % (endpoint, keys, seconds + 1.0)], stdout=subprocess.PIPE, text=True
        )
        try:
            assert flood.stdout is not None
            if not select.select([flood.stdout], [], [], 30.0)[0] or flood.stdout.readline().strip() != "ready":
                raise TimeoutError("the flooder did not connect within 30 s")
            t0, g0, l0 = time.monotonic(), len(c.guidance), len(c.guidance_latencies_s)
            stream(c, seconds, depth_m=0.02)
            t1, g = time.monotonic(), len(c.guidance) - g0
            # The guidance latencies heard during the flood (the deque keeps 100,000: none dropped).
            latencies = np.array(list(c.guidance_latencies_s)[l0:]) * 1e3
            out, _ = flood.communicate(timeout=60)
        finally:
            if flood.poll() is None:
                flood.kill()
                flood.wait()
    lines = out.strip().splitlines()
    if flood.returncode != 0 or not lines:
        raise RuntimeError(f"the flooder failed (exit {flood.returncode})")
    counts = json.loads(lines[-1])
    gap = gaps([a for a in arrivals if a <= t1], t0)
    rate = g / (t1 - t0)
    per_s = [round(n / (seconds + 1.0)) for n in counts["answered"]]
    return Outcome(
        "another client floods queries (health, the victim's metrics, bricks and X-rays, 4 threads back to back) "
        f"while a trainee drills {seconds:g} s",
        "the trainee's forces flow on (gap < 0.1 s) and its guidance keeps 10 Hz (at least 9 a second); every "
        "query is answered",
        f"largest force gap {gap * 1e3:.1f} ms; guidance {rate:.1f} a second, latency p50 "
        f"{np.median(latencies):.1f} ms, max {latencies.max():.1f} ms (without the flood {np.median(quiet):.1f}, "
        f"{quiet.max():.1f} ms); queries answered a second (health, metrics, bone, xray) {per_s}, refused "
        f"{counts['refused']}, unanswered {counts['unanswered']}",
        gap < 0.1
        and rate >= 9.0
        and all(n > 0 for n in counts["answered"])
        and not any(counts["refused"])
        and not any(counts["unanswered"]),
    )


def rogue_worker(endpoint: str) -> Outcome:
    """Two rogues. One serves the shared <p>/model/predict, outside the worker pool; the other
    joins the pool (open mode lets anyone; the lab mode's ACL does not) and answers each of its
    queries 200 times, 150 ms late, with 3 N: by then a newer window is applied."""
    rogue_n = (0.0, 0.0, 3.0)
    late: list = []
    outside: list = []
    lock = threading.Lock()
    stop = threading.Event()
    with TraineeClient(endpoint, "guided") as c, TraineeClient(endpoint, "rogue3") as r:
        before = c.health(1.0)["model"]

        def on_query(q):
            seqs, _ = protocol.decode_predict(q.payload.to_bytes())
            with lock:
                late.append((time.monotonic() + 0.15, q, seqs))

        shared = r._z.declare_queryable("dhg/model/predict", outside.append, complete=True)
        qa = r._z.declare_queryable("dhg/model/workers/rogue3/predict", on_query, complete=True)
        token = r._z.liveliness().declare_token("dhg/model/workers/rogue3")
        wait_for(lambda: len(c.health(1.0)["model"]["workers"]) >= 2, 10.0, "the rogue in the pool")

        def answer():
            while not stop.is_set():
                now = time.monotonic()
                with lock:
                    due = [x for x in late if x[0] <= now]
                    late[:] = [x for x in late if x[0] > now]
                for _, q, seqs in due:
                    answers = b"".join(
                        protocol.encode_prediction(int(s), rogue_n, 0.0, "rogue", entry=i) for i, s in enumerate(seqs)
                    )
                    for _ in range(200):
                        q.reply(q.key_expr, answers)
                    q.drop()
                time.sleep(0.002)

        th = threading.Thread(target=answer)
        th.start()
        stream(c, 3.0)

        def answered() -> bool:
            with lock:
                return not late

        wait_for(answered, 10.0, "the rogue's late replies to the last queries")
        stop.set()
        th.join()
        wait_for(lambda: all(w["in_flight"] == 0 for w in c.health(1.0)["model"]["workers"]), 5.0, "queries ended")
        after = c.health(1.0)["model"]
        token.undeclare()
        qa.undeclare()
        shared.undeclare()
        predicted = np.array([g["predicted_force_n"] for g in c.guidance])
    rogue = next((w for w in after["workers"] if w["id"] == "rogue3"), None)
    applied = int(np.sum(np.all(np.isclose(predicted, rogue_n, atol=1e-6), axis=1))) if len(predicted) else 0
    ignored = after["ignored"] - before["ignored"]
    asked = rogue["failed"] if rogue else -1
    return Outcome(
        "rogue model workers: one outside the pool, one in it answering 200 times, 150 ms late, with 3 N",
        "the outside one is never asked; no rogue reply is applied, each is ignored and counted, and the "
        "pool leaves the rogue out",
        f"{len(predicted)} guidance messages, {applied} from a rogue; outside one asked {len(outside)} times; "
        f"pool rogue asked {asked} times in 3 s; {ignored} replies ignored",
        applied == 0 and not outside and ignored > 0 and 1 <= asked <= 6 and len(predicted) > 20,
    )


def oversized(endpoint: str, server: ServerProcess) -> Outcome:
    def hwm() -> float:
        with open(f"/proc/{server.proc.pid}/status") as fh:
            return next(int(x.split()[1]) for x in fh if x.startswith("VmHWM")) / 1024

    # The sender is its own process: a 500 MB put holds the sending interpreter for a while, and
    # the trainee's forces must be timed by a process that is not busy with it.
    conf = {"mode": "client", "connect": {"endpoints": [endpoint]}, "scouting": {"multicast": {"enabled": False}}}
    sender = (
        f"import json, zenoh\nz = zenoh.open(zenoh.Config.from_json5({json.dumps(json.dumps(conf))}))\n"
        "for size in (100, 500):\n    z.put('dhg/session/big/pose', bytes(size * 1024 * 1024))\nz.close()\n"
    )
    arrivals: list[float] = []
    with TraineeClient(endpoint, "other", on_force=lambda m: arrivals.append(time.monotonic())) as c:
        before = hwm()
        th = threading.Thread(target=stream, args=(c, 6.0))
        th.start()
        wait_for(lambda: len(arrivals) > 500, 10.0, "the other trainee's forces")
        t0 = time.monotonic()
        subprocess.run([sys.executable, "-c", sender], check=True, timeout=120)
        th.join()
        grown = hwm() - before
    gap = gaps(arrivals, t0)
    return Outcome(
        "100 MB and 500 MB puts on a pose key while another trainee drills",
        "dropped at the transport: the server's peak memory grows far less than the payload; forces flow (gap < 0.1 s)",
        f"peak memory +{grown:.0f} MB; the other trainee's largest force gap {gap * 1e3:.1f} ms",
        grown < 50 and gap < 0.1,
    )


def squatter(endpoint_args: tuple[str, ...] = ("--max-sessions", "4", "--idle-timeout", "2.0")) -> Outcome:
    server, endpoint = serve(*endpoint_args)
    stop = threading.Event()
    try:
        squat = [TraineeClient(endpoint, f"squat-{k}") for k in range(4)]

        def hold():
            while not stop.is_set():
                for c in squat:
                    c.send_pose((0.0, 0.0, 0.0))
                stop.wait(1.0)

        th = threading.Thread(target=hold)
        th.start()
        with TraineeClient(endpoint, "real-trainee") as real:
            wait_for(lambda: real.health(1.0)["sessions"] == 4, 10.0, "the squatters holding every slot")
            t0 = time.monotonic()
            got, refused = None, 0
            while got is None and time.monotonic() - t0 < 20:
                try:
                    got = real.create()
                except EngineError:
                    refused += 1
                    time.sleep(0.05)
        waited = time.monotonic() - t0
    finally:
        stop.set()
        th.join()
        for c in squat:
            c.close()
        server.stop()
    return Outcome(
        "one pose a second to each of 4 ids on a 4-slot server (idle timeout 2 s)",
        "the squatters' sessions are freed; a real trainee gets a slot",
        f"slot after {waited:.1f} s ({refused} refusals)" if got else f"no slot in 20 s ({refused} refusals)",
        got is not None,
    )


def model_worker_lost(how: str) -> Outcome:
    server, endpoint = serve("--role", "sim")
    worker = ServerProcess(["--role", "model", "--connect", endpoint], echo=False)
    arrivals: list[float] = []
    try:
        with TraineeClient(endpoint, "w", on_force=lambda m: arrivals.append(time.monotonic())) as c:
            th = threading.Thread(target=stream, args=(c, 6.0))
            th.start()
            wait_for(lambda: len(c.guidance) >= 10, 10.0, "guidance from the worker")
            t0 = time.monotonic()
            if how == "killed":
                worker.proc.kill()
            else:
                os.kill(worker.proc.pid, signal.SIGSTOP)
            th.join()
            after = [g for g in c.guidance if g["received_ns"] * 1e-9 > t0 + 1.0]
            flag = protocol.FLAGS["model_available"]
            still = sum(1 for g in after if g["flags"] & flag)
            health = c.health(2.0)["model"]
    finally:
        if how != "killed":
            os.kill(worker.proc.pid, signal.SIGCONT)
        worker.stop()
        server.stop()
    gap = gaps(arrivals, t0)
    return Outcome(
        f"the model worker {how} {'(SIGKILL)' if how == 'killed' else '(SIGSTOP)'} mid-attempt",
        "no gap in the forces; guidance fades out; health says the model is unavailable",
        f"largest force gap {gap * 1e3:.1f} ms; guidance messages flagged available after +1 s: {still}; "
        f"health available: {health['available']}",
        gap < 0.5 and not health["available"],
    )


def server_killed_while_recording(root: Path) -> Outcome:
    from dhg.data.dataset import load_dataset

    server, endpoint = serve()
    out = root / "rec"
    rec = record(endpoint, "--session", "rec-1", "--out", str(out))
    assert rec.stdout is not None
    rec.stdout.readline()  # "recording session rec-1 ...": it is subscribed
    with TraineeClient(endpoint, "rec-1") as c:
        th = threading.Thread(target=stream, args=(c, 4.0))
        th.start()
        th.join()
        sent_records = len(c.states)
    server.proc.kill()
    server.proc.wait()

    def kept_on_disk() -> int:  # what the recorder's flushes have written so far
        try:
            return len(load_dataset(out).episodes[0].times_s)
        except Exception:  # not written yet, or between two atomic rewrites
            return 0

    try:  # the recorder flushes every second: wait for everything it had, or give up (a loss)
        wait_for(lambda: kept_on_disk() >= sent_records, 10.0, "the recorder's flush")
    except TimeoutError:
        pass
    rec.send_signal(signal.SIGINT)
    rec.communicate(timeout=30)
    kept = kept_on_disk()
    lost_s = (sent_records - kept) / 10
    return Outcome(
        "the server killed (SIGKILL) just after a 4 s attempt, dhg record running",
        "the dataset keeps every record up to the last flush (at most 1 s lost)",
        f"{kept} of {sent_records} records kept ({lost_s:.1f} s lost); recorder exit {rec.returncode}",
        rec.returncode == 0 and lost_s <= 1.0,
    )


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--only", help="comma-separated fault names")
    ap.add_argument("--json", metavar="FILE", help="also write the outcomes as JSON")
    args = ap.parse_args()
    root = Path(tempfile.mkdtemp(prefix="dhg-faults-"))
    server, endpoint = serve("--idle-timeout", "3.0")
    faults: dict[str, Callable[[], Outcome]] = {
        "forged-forces": lambda: forged_forces(endpoint),
        "fake-ids": lambda: fake_ids_and_impossible_states(endpoint, root),
        "frozen-subscriber": lambda: frozen_subscriber(endpoint),
        "query-flood": lambda: query_flood(endpoint),
        "rogue-worker": lambda: rogue_worker(endpoint),
        "oversized": lambda: oversized(endpoint, server),
        "squatter": squatter,
        "worker-killed": lambda: model_worker_lost("killed"),
        "worker-stopped": lambda: model_worker_lost("stopped"),
        "server-killed": lambda: server_killed_while_recording(root),
    }
    chosen = args.only.split(",") if args.only else list(faults)
    outcomes = []
    try:
        for name in chosen:
            try:
                o = faults[name]()
            except Exception as exc:  # a fault that breaks the harness is a failure, said plainly
                o = Outcome(name, "the fault runs", f"{type(exc).__name__}: {exc}", False)
            outcomes.append(o)
            print(f"{'PASS' if o.ok else 'FAIL'}  {name}\n  fault:    {o.fault}\n  expected: {o.expected}\n"
                  f"  happened: {o.happened}", flush=True)  # fmt: skip
    finally:
        server.stop()
    if args.json:
        Path(args.json).write_text(json.dumps([o.__dict__ for o in outcomes], indent=1))
    failed = [o for o in outcomes if not o.ok]
    print(f"{len(outcomes) - len(failed)} of {len(outcomes)} faults handled as expected")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
