"""Helpers the end-to-end tests share: servers and recorders in their own process, a session's entry
pose, 1 kHz pose streams, waits on conditions (never on fixed times) and the fields of JSON replies."""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from dhg.live.client import TraineeClient
from dhg.live.process import ServerProcess, free_port

PEAK_FORCE_N = 3.3
"""The Touch's published peak (3D Systems), written here on purpose rather than read from the
core: the tests check the core against the device's rating, not against itself."""


def serve(*args: str, endpoint: str | None = None) -> tuple[ServerProcess, str]:
    """``dhg-serve ARGS`` on the 1 mm phantom in its own process, listening on ``endpoint`` (or,
    for ``--role model``, connecting to it); a free loopback port by default."""
    endpoint = endpoint or f"tcp/127.0.0.1:{free_port()}"
    flag = "--connect" if "model" in args else "--listen"
    return ServerProcess([flag, endpoint, "--voxel-mm", "1.0", "--status-every", "1", *args], echo=False), endpoint


def tool_quaternion(d: np.ndarray) -> tuple[float, float, float, float]:
    """The quaternion (w, x, y, z) that turns the tool's +z onto the unit direction ``d`` (the
    half-way rotation; a half turn about x when ``d`` is -z)."""
    z = np.array([0.0, 0.0, 1.0])
    q = np.array([1.0 + z @ d, *np.cross(z, d)])
    n = np.linalg.norm(q)
    q = q / n if n > 1e-9 else np.array([0.0, 1.0, 0.0, 0.0])
    return (float(q[0]), float(q[1]), float(q[2]), float(q[3]))


def entry(client: TraineeClient) -> tuple[np.ndarray, np.ndarray, tuple[float, float, float, float]]:
    """Creates the client's session; returns its entry point A (m), its unit drill direction, and
    the quaternion that puts the burr in line with the path."""
    info = client.create()
    a, b = np.array(info["entry_m"]), np.array(info["target_m"])
    d = (b - a) / np.linalg.norm(b - a)
    return a, d, tool_quaternion(d)


def stream(client: TraineeClient, positions: np.ndarray, q: tuple, drill_on: bool = True) -> float:
    """Publishes one pose per 1 ms on absolute deadlines; returns the wall time it took (s)."""
    t0 = time.monotonic_ns()
    for k, p in enumerate(positions):
        client.send_pose(p, q, drill_on, 1250.0)
        pause = t0 + (k + 1) * 1_000_000 - time.monotonic_ns()
        if pause > 0:
            time.sleep(pause * 1e-9)
    return (time.monotonic_ns() - t0) * 1e-9


def hold(
    client: TraineeClient,
    position: np.ndarray,
    q: tuple,
    until: Callable[[], object],
    timeout_s: float,
    what: str = "condition",
) -> None:
    """Holds the stylus at ``position`` (a pose a millisecond, 100 ms at a time; a held stylus keeps
    its session alive) until ``until()`` is true. For what the model's answers bring: on a loaded
    machine they come later than on an idle one."""
    held = np.repeat(np.asarray(position, dtype=float)[None, :], 100, axis=0)

    def met() -> object:
        stream(client, held, q)
        return until()

    wait_until(met, timeout_s, what)


def hold_until(
    client: TraineeClient,
    position: np.ndarray,
    q: tuple,
    cond: Callable[[dict], object],
    timeout_s: float,
    what: str = "condition",
) -> dict:
    """Holds the stylus at ``position`` (see :func:`hold`) until the latest force message meets
    ``cond``; returns that message."""
    found: list[dict] = []

    def met() -> bool:
        m = client.force
        if m is not None and cond(m):
            found.append(m)
        return bool(found)

    hold(client, position, q, met, timeout_s, what)
    return found[0]


def settle_until(cond: Callable[[], object], timeout_s: float) -> bool:
    """Polls ``cond`` every 5 ms until it is true or ``timeout_s`` (a generous deadline, not a
    speed target) has passed; returns whether it came true. For waits whose test asserts less
    than the condition (most of a stream's messages waited for, one required)."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if cond():
            return True
        time.sleep(0.005)
    return False


def wait_until(cond: Callable[[], object], timeout_s: float, what: str = "condition") -> None:
    """Polls ``cond`` every 5 ms until it is true; fails the test after ``timeout_s`` (a generous
    deadline, not a speed target)."""
    if not settle_until(cond, timeout_s):
        raise AssertionError(f"{what} not met within {timeout_s} s")


def schema_fields(schema: dict) -> set[str]:
    """Every property name a JSON schema (as ``schemars`` writes it) declares, nested objects and
    ``$defs`` included."""
    names: set[str] = set()

    def walk(node: object) -> None:
        if isinstance(node, dict):
            names.update(node.get("properties", {}))
            for value in node.values():
                walk(value)
        elif isinstance(node, list):
            for value in node:
                walk(value)

    walk(schema)
    return names


def reply_fields(reply: object) -> set[str]:
    """Every key of a JSON reply, nested objects and objects in lists included."""
    names: set[str] = set()
    if isinstance(reply, dict):
        for key, value in reply.items():
            names.add(key)
            names |= reply_fields(value)
    elif isinstance(reply, list):
        for value in reply:
            names |= reply_fields(value)
    return names


def record_process(endpoint: str, *args: str) -> subprocess.Popen[str]:
    """``dhg record --connect endpoint ARGS`` in its own process, output unbuffered on one pipe."""
    return subprocess.Popen(
        [sys.executable, "-m", "dhg.cli.main", "record", "--connect", endpoint, *args],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        env=dict(os.environ, PYTHONUNBUFFERED="1"),
    )


def read_until(
    proc: subprocess.Popen[str], text: str, max_lines: int = 100, line_timeout_s: float = 120.0
) -> list[str]:
    """Reads ``proc``'s output line by line until a line holds ``text``; returns the lines read.
    Fails if the process ends, or says nothing for ``line_timeout_s``, before saying it."""
    lines: list[str] = []
    while len(lines) < max_lines:
        line = readline_within(proc, line_timeout_s, f"waiting for {text!r} after {''.join(lines)!r}")
        lines.append(line)
        if text in line:
            return lines
    raise AssertionError(f"{text!r} not in the first {max_lines} lines: {''.join(lines)}")


def readline_within(proc: subprocess.Popen[str], timeout_s: float, what: str = "a line") -> str:
    """The next line of ``proc``'s output, or an AssertionError naming ``what`` if none comes
    within ``timeout_s`` (a generous deadline: a helper that never answers fails, not hangs)."""
    assert proc.stdout is not None
    out: list[str] = []
    reader = threading.Thread(target=lambda: out.append(proc.stdout.readline()), daemon=True)  # type: ignore[union-attr]
    reader.start()
    reader.join(timeout_s)
    assert out and out[0], f"{what}: no line from the process within {timeout_s:g} s (exit code {proc.poll()})"
    return out[0]


def ctrl_c(rec: subprocess.Popen[str]) -> str:
    """Stops a recorder as Ctrl-C does; asserts it exits 0 and returns its output."""
    rec.send_signal(signal.SIGINT)
    output, _ = rec.communicate(timeout=30)
    assert rec.returncode == 0, output
    return output


def rewrite_dataset_file(
    folder: Path, name: str, table: Any, card_change: Callable[[dict], None] | None = None
) -> None:
    """Writes ``table`` (pyarrow) as the dataset file ``name`` in ``folder`` and updates the card's
    hash (and row count, where the card keeps one) so that only the change a test makes is
    checked, not a stale hash; ``card_change`` edits the card before it is written back."""
    import hashlib
    import json

    import pyarrow.parquet as pq

    path = folder / name
    pq.write_table(table, path)
    card = json.loads((folder / "card.json").read_text())
    entry = card["files"][name]
    entry["sha256"] = hashlib.sha256(path.read_bytes()).hexdigest()
    if "rows" in entry:
        entry["rows"] = table.num_rows
    if card_change:
        card_change(card)
    (folder / "card.json").write_text(json.dumps(card))


def said(proc: ServerProcess, last: int = 40) -> str:
    """The server's last ``last`` output lines without the frames of a Rust backtrace, so a panic
    or abort message is in what a failed assertion prints (CI shows only part of it)."""
    frames = re.compile(r"\s*(\d+: |at /)")
    return "\n".join([line for line in proc.lines if not frames.match(line)][-last:])


def stops_cleanly(proc: ServerProcess) -> None:
    """Asserts that a server still runs, then stops with exit 0 and says so as its last line."""
    assert proc.proc.poll() is None, f"the shared server died:\n{said(proc)}"
    assert proc.stop() == 0, said(proc)
    wait_until(lambda: proc.lines and "dhg-serve stopped" in proc.lines[-1], 10.0, "dhg-serve's last line")


class Stylus:
    """A virtual trainee's hand: streams poses at 1 kHz along ``positions`` (m), then holds the
    last one (a stylus held still keeps its session alive) until :meth:`stop`."""

    def __init__(self, client: TraineeClient, q: tuple) -> None:
        self.client, self.q = client, q
        self._path: list[np.ndarray] = []
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self.sent = 0
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def move(self, positions: np.ndarray) -> None:
        with self._lock:
            self._path.extend(positions)

    def idle(self) -> bool:
        with self._lock:
            return not self._path

    def _run(self) -> None:
        last = None
        t0 = time.monotonic_ns()
        while not self._stop.is_set():
            with self._lock:
                p = self._path.pop(0) if self._path else last
            if p is not None:
                self.client.send_pose(p, self.q, True, 1250.0)
                last = p
            self.sent += 1
            pause = t0 + self.sent * 1_000_000 - time.monotonic_ns()
            if pause > 0:
                time.sleep(pause * 1e-9)

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(timeout=5)


def thread_nices(pid: int) -> set[int]:
    """The nice values of process ``pid``'s threads (Linux)."""
    nices = set()
    for tid in os.listdir(f"/proc/{pid}/task"):
        try:
            nices.add(os.getpriority(os.PRIO_PROCESS, int(tid)))
        except OSError:  # the thread ended meanwhile
            continue
    return nices


def listening_tcp_ports(pid: int) -> set[int]:
    """The TCP ports process ``pid`` listens on (Linux: its sockets' inodes in ``/proc/PID/fd``
    against the LISTEN rows of ``/proc/net/tcp`` and ``tcp6``)."""
    inodes = set()
    for fd in os.listdir(f"/proc/{pid}/fd"):
        try:
            target = os.readlink(f"/proc/{pid}/fd/{fd}")
        except OSError:  # closed meanwhile
            continue
        if target.startswith("socket:["):
            inodes.add(target[len("socket:[") : -1])
    ports = set()
    for table in ("tcp", "tcp6"):
        try:
            rows = Path(f"/proc/{pid}/net/{table}").read_text().splitlines()[1:]
        except OSError:  # no IPv6
            continue
        for row in rows:
            cols = row.split()
            if cols[3] == "0A" and cols[9] in inodes:  # st 0A: LISTEN
                ports.add(int(cols[1].rsplit(":", 1)[1], 16))
    return ports


def column_encodings(path: str | Path) -> dict[str, tuple[set[str], set[str]]]:
    """Each column's compressions and Parquet encodings, over every row group of the file."""
    import pyarrow.parquet as pq

    md = pq.ParquetFile(path).metadata
    out: dict[str, tuple[set[str], set[str]]] = {}
    for g in range(md.num_row_groups):
        for c in range(md.num_columns):
            col = md.row_group(g).column(c)
            compressions, encodings = out.setdefault(col.path_in_schema, (set(), set()))
            compressions.add(col.compression)
            encodings.update(col.encodings)
    return out


class AnsweringSession:
    """A stand-in for a recorder's Zenoh session (``SessionRecorder(zenoh_session=...)``, which then
    subscribes to nothing): ``get`` answers the server's ``about`` and the session's ``info``
    (entry A at the origin, target B 60 mm along z), as a server would."""

    def __init__(self, session_id: str, prefix: str = "dhg") -> None:
        from dhg.core import protocol

        keys = protocol.keys(prefix, session_id)
        self.replies = {
            keys["about"]: {"dhg_version": "stand-in"},
            keys["info"]: {"entry_m": [0.0, 0.0, 0.0], "target_m": [0.0, 0.0, 0.06]},
        }

    def get(self, key: str, timeout: float = 1.0) -> list[Any]:
        import types

        body = json.dumps(self.replies.get(key, {})).encode()
        payload = types.SimpleNamespace(to_bytes=lambda: body)
        return [types.SimpleNamespace(ok=types.SimpleNamespace(payload=payload))]


def state_sample(payload: bytes) -> Any:
    """A Zenoh sample as a recorder's ``on_sample`` reads it."""
    import types

    return types.SimpleNamespace(payload=types.SimpleNamespace(to_bytes=lambda: payload))


def attempt_states(n: int, seed: int = 0) -> list[bytes]:
    """One attempt's ``state`` payloads (10 Hz, from time 0.1 s): the tip advancing 0.2 mm a record
    along z through cortex with a noisy force; the drill off now and then; plunge, peak
    temperature, time above 47 °C and guidance gain that wander (so a metric taken from the wrong
    state, or the largest where the last is meant, shows)."""
    from dhg.core import protocol
    from dhg.core.layers import Layer

    rng = np.random.default_rng(seed)
    out = []
    for k in range(1, n + 1):
        # force (N), tip (m), layer, depth along A→B (m), temperature (°C)
        features = [*rng.normal(0.0, 1.0, 3), 0.0, 0.0, 2e-4 * k, float(Layer.CORTICAL), 2e-4 * k, 40.0]
        out.append(
            protocol.encode(
                "state",
                flags=protocol.FLAGS["drill_on"] if rng.random() > 0.1 else 0,
                record_seq=k,
                time_s=0.1 * k,
                features=features,
                peak_temperature_c=rng.uniform(40.0, 50.0),
                plunge_depth_m=rng.uniform(0.0, 3e-3),
                time_above_47_s=rng.uniform(0.0, 2.0),
                guidance_gain=rng.uniform(0.0, 2.0),
            )
        )
    return out
