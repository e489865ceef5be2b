"""A Python client of the DHG server, for trainee programs, recorders and tools.

:class:`TraineeClient` opens its own Zenoh session to a server endpoint, publishes stylus poses for
one session id, and receives that session's forces (1 kHz), guidance (10 Hz) and state (10 Hz). It
also wraps the JSON queries (control, metrics, health) and the X-ray PNGs. Every message follows
``docs/protocol.md``; latencies are measured on the client's own clock (``time.monotonic_ns``),
which the server echoes.
"""

from __future__ import annotations

import json
import math
import threading
import time
import uuid
from collections import deque
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np
import numpy.typing as npt

from dhg.core import protocol
from dhg.core.errors import ERROR_KINDS, DhgError, EngineError, TransportError
from dhg.core.layers import Layer

__all__ = ["ForceGuard", "TraineeClient", "all_finite", "feedback_tuple", "get_json", "get_replies"]

_FORCE_FLOATS = ("force_n", "guidance_n", "tip_m", "depth_m", "deviation_m", "temperature_c", "plunge_depth_m")
_LAYER_IDS = frozenset(int(layer) for layer in Layer)


class ForceGuard:
    """What a client hands on to a haptic device, checked: every force message must be finite in
    every field, name a known layer, and keep its force (and guidance share) within the device's
    peak, or it is rejected and counted, and the last good message stands; an accepted force changes no faster than the
    device's rate limit (a token bucket of ``max_force_rate_n_per_s``, holding at most
    ``burst_s`` of it), the excess slewed away and counted. The server's own forces pass (its
    limiter is the same profile), unless this process stalls for longer than ``burst_s`` and they
    arrive bunched: then a change the device would feel at once is slewed too. A peer that puts a
    NaN, 1e6 N or a jolt on this session's force key cannot get it to the device. Not thread-safe:
    one guard per stream."""

    def __init__(self, device: Any = None, burst_s: float = 0.005) -> None:
        from dhg.core.session import DeviceProfile

        device = device or DeviceProfile()
        self.peak_n = float(device.peak_force_n)
        self.rate_n_per_s = float(device.max_force_rate_n_per_s)
        self.burst_n = self.rate_n_per_s * burst_s
        self.rejected = {"non_finite": 0, "bad_layer": 0, "over_limit": 0, "rate_limited": 0}
        """Messages refused for a NaN or infinite field, for a layer id no layer has (the server
        sends none: a virtual surgeon would read it), for a force above the peak, and forces
        slewed down to the rate limit."""
        self._last: tuple[float, float, float] | None = None
        self._budget = self.burst_n
        self._t_ns = 0

    def check(self, m: dict[str, Any], now_ns: int) -> dict[str, Any] | None:
        """``m`` (a decoded force message) as it may reach the device, or ``None`` when refused."""
        for key in _FORCE_FLOATS:
            v = m[key]
            if not all(math.isfinite(x) for x in v) if isinstance(v, tuple) else not math.isfinite(v):
                self.rejected["non_finite"] += 1
                return None
        if m["layer"] not in _LAYER_IDS:
            self.rejected["bad_layer"] += 1
            return None
        f, g = m["force_n"], m["guidance_n"]
        if math.hypot(*f) > self.peak_n or math.hypot(*g) > self.peak_n:
            self.rejected["over_limit"] += 1
            return None
        if self._last is None:
            self._last, self._t_ns = f, now_ns
            return m
        self._budget = min(self.burst_n, self._budget + self.rate_n_per_s * max(now_ns - self._t_ns, 0) * 1e-9)
        self._t_ns = now_ns
        d = (f[0] - self._last[0], f[1] - self._last[1], f[2] - self._last[2])
        step = math.hypot(*d)
        if step > self._budget + 1e-6:  # the wire's float32 rounds a full-rate step up by ~1e-8 N
            k = self._budget / step
            f = (self._last[0] + d[0] * k, self._last[1] + d[1] * k, self._last[2] + d[2] * k)
            m = dict(m, force_n=f)
            self.rejected["rate_limited"] += 1
            step = self._budget
        self._budget = max(self._budget - step, 0.0)
        self._last = f
        return m


def feedback_tuple(force_msg: dict[str, Any]) -> tuple:
    """The session feedback tuple the virtual surgeons read (tip x, y, z, depth, deviation,
    temperature, layer, cutting, breakthroughs, plunging, plunge depth) from a force message."""
    fl = force_msg["flags"]
    tip = force_msg["tip_m"]
    return (
        tip[0],
        tip[1],
        tip[2],
        force_msg["depth_m"],
        force_msg["deviation_m"],
        force_msg["temperature_c"],
        force_msg["layer"],
        bool(fl & protocol.FLAGS["cutting"]),
        force_msg["breakthroughs"],
        bool(fl & protocol.FLAGS["plunging"]),
        force_msg["plunge_depth_m"],
    )


def all_finite(m: dict[str, Any]) -> bool:
    """Whether every float (and every float of a vector) in a decoded message is finite."""
    for v in m.values():
        if isinstance(v, float):
            if not math.isfinite(v):
                return False
        elif isinstance(v, tuple) and not all(math.isfinite(x) for x in v):
            return False
    return True


def _refusal(key: str, body: str) -> DhgError:
    """The exception for an error reply ``{"error": ..., "kind": ...}``: the class of its kind
    (:data:`dhg.core.errors.ERROR_KINDS`; ``invalid_input`` is an :class:`InvalidInputError`). A
    kind this client does not know (a newer server) or a reply that is not one is an
    :class:`EngineError` that says so."""
    try:
        reply = json.loads(body)
    except json.JSONDecodeError:
        reply = None
    if not isinstance(reply, dict):
        return EngineError(f"{key}: {body}")
    kind = str(reply.get("kind"))
    if kind not in ERROR_KINDS:
        return EngineError(f"{key}: {reply.get('error', body)} (error kind {kind!r}, unknown to this client)")
    return ERROR_KINDS[kind](f"{key}: {reply.get('error', body)}")


def get_replies(z: Any, key: str, payload: bytes | None = None, timeout_s: float = 2.0) -> list[tuple[str, bytes]]:
    """The (key, payload) of every good reply to a query on Zenoh session ``z``. Only error
    replies raise the class of their ``kind`` with the server's reason; none at all raises
    :class:`TransportError`."""
    replies = z.get(key, payload=payload, timeout=timeout_s)
    out, errors = [], []
    for r in replies:
        if r.ok is not None:
            out.append((str(r.ok.key_expr), r.ok.payload.to_bytes()))
        else:
            errors.append(r.err.payload.to_string())
    if errors and not out:
        raise _refusal(key, errors[0])
    if not out:
        raise TransportError(f"{key}: no reply within {timeout_s} s (is the server running and reachable?)")
    return out


def get_json(z: Any, key: str, request: dict[str, Any] | None = None, timeout_s: float = 2.0) -> dict[str, Any]:
    """The first good reply to a JSON query (``request`` as its body), decoded."""
    payload = json.dumps(request).encode() if request is not None else None
    ((_, body),) = get_replies(z, key, payload, timeout_s)[:1]
    return json.loads(body)


class TraineeClient:
    """One trainee's connection: poses out, forces/guidance/state in.

    ``connect`` is one or more Zenoh endpoints (``tcp/127.0.0.1:7447``). The session on the server
    is created by the first pose, or explicitly with :meth:`create`. Received messages are decoded
    into dicts (field names of ``docs/protocol.md``); the newest force is :attr:`force`, guidance
    and state messages are kept in :attr:`guidance` and :attr:`states` (up to ``keep`` each).
    ``on_force`` / ``on_state`` callbacks run on Zenoh's threads and must be quick.

    Every force passes :class:`ForceGuard` (limits of ``device``, a
    :class:`dhg.core.session.DeviceProfile`; the Touch's by default) before it becomes :attr:`force` or
    reaches ``on_force``: in open mode any peer can put on this session's keys. Guidance and state
    messages with a NaN or infinite value are dropped and counted in :attr:`decode_errors`.
    """

    def __init__(
        self,
        connect: str | Sequence[str],
        session_id: str | None = None,
        prefix: str = "dhg",
        keep: int = 100_000,
        on_force: Callable[[dict[str, Any]], None] | None = None,
        on_state: Callable[[dict[str, Any]], None] | None = None,
        zenoh_config_file: str | None = None,
        device: Any = None,
    ) -> None:
        from dhg.live.zenoh_config import open_zenoh, zenoh_config_json5

        endpoints = [connect] if isinstance(connect, str) else list(connect)
        self.session_id = protocol.check_session_id(session_id or f"trainee-{uuid.uuid4().hex[:8]}")
        self.prefix = prefix
        self.keys = protocol.keys(prefix, self.session_id)
        self._z = open_zenoh(zenoh_config_json5(connect=endpoints, config_file=zenoh_config_file, mode="client"))
        import zenoh

        self._lock = threading.Lock()
        self.force: dict[str, Any] | None = None
        self.forces_received = 0
        self.force_latencies_s: deque[float] = deque(maxlen=keep)
        self.guidance: deque[dict[str, Any]] = deque(maxlen=keep)
        self.guidance_latencies_s: deque[float] = deque(maxlen=keep)
        self.states: deque[dict[str, Any]] = deque(maxlen=keep)
        self.decode_errors = 0
        self.guard = ForceGuard(device)
        """Checks every force before it becomes :attr:`force`; its ``rejected`` counts refusals."""
        self._on_force, self._on_state = on_force, on_state
        self._seq = 0
        self.last_pose: tuple[npt.ArrayLike, npt.ArrayLike] | None = None
        """The position (m) and orientation of the last pose sent (None before the first)."""
        self._last_force_seq = -1
        self._last_guidance_pose_ns = -1
        self._pub = self._z.declare_publisher(
            self.keys["pose"],
            encoding=zenoh.Encoding.APPLICATION_OCTET_STREAM.with_schema(f"dhg.pose.v{protocol.VERSION}"),
            congestion_control=zenoh.CongestionControl.DROP,
            priority=zenoh.Priority.REAL_TIME,
            express=True,
        )
        self._subs = [
            self._z.declare_subscriber(self.keys["force"], self._force_cb),
            self._z.declare_subscriber(self.keys["guidance"], self._guidance_cb),
            self._z.declare_subscriber(self.keys["state"], self._state_cb),
        ]

    # -- receiving -------------------------------------------------------------------------
    def _decode(self, name: str, sample: Any) -> dict[str, Any] | None:
        try:
            m = protocol.decode(name, sample.payload.to_bytes())
        except ValueError:
            self.decode_errors += 1
            return None
        if name != "force" and not all_finite(m):  # forces: the guard counts them
            self.decode_errors += 1
            return None
        return m

    def _force_cb(self, sample: Any) -> None:
        m = self._decode("force", sample)
        if m is None:
            return
        now = time.monotonic_ns()
        with self._lock:
            m = self.guard.check(m, now)
            if m is None:
                return
            self.force = m
            self.forces_received += 1
            # A pose's latency is that of the first force that used it: later forces (no newer
            # pose yet, or the client stopped) echo the same pose and would count its age.
            if m["pose_client_time_ns"] and m["pose_seq"] != self._last_force_seq:
                self.force_latencies_s.append((now - m["pose_client_time_ns"]) * 1e-9)
            self._last_force_seq = m["pose_seq"]
        if self._on_force is not None:
            self._on_force(m)

    def _guidance_cb(self, sample: Any) -> None:
        m = self._decode("guidance", sample)
        if m is None:
            return
        m["received_ns"] = now = time.monotonic_ns()
        with self._lock:
            self.guidance.append(m)
            if m["pose_client_time_ns"] and m["pose_client_time_ns"] != self._last_guidance_pose_ns:
                self.guidance_latencies_s.append((now - m["pose_client_time_ns"]) * 1e-9)
            self._last_guidance_pose_ns = m["pose_client_time_ns"]

    def _state_cb(self, sample: Any) -> None:
        m = self._decode("state", sample)
        if m is None:
            return
        with self._lock:
            self.states.append(m)
        if self._on_state is not None:
            self._on_state(m)

    # -- sending ---------------------------------------------------------------------------
    def send_pose(
        self,
        position_m: npt.ArrayLike,
        orientation_wxyz: npt.ArrayLike = (1.0, 0.0, 0.0, 0.0),
        drill_on: bool = False,
        spindle_rpm: float = 0.0,
    ) -> int:
        """Publishes one stylus pose (burr centre in m, world frame; quaternion w, x, y, z with the
        drill along the tool's +z; spindle speed in rpm). Returns its sequence number."""
        self._seq += 1
        self._pub.put(
            protocol.encode_pose(self._seq, time.monotonic_ns(), position_m, orientation_wxyz, drill_on, spindle_rpm)
        )
        self.last_pose = (position_m, orientation_wxyz)
        return self._seq

    @property
    def sent_seq(self) -> int:
        """The sequence number of the last pose sent (0: none yet)."""
        return self._seq

    def send_row(self, row: Sequence[float]) -> int:
        """Publishes a pose row (x, y, z, qw, qx, qy, qz, drill_on, spindle_rpm), as the virtual
        surgeons produce them."""
        return self.send_pose(row[0:3], row[3:7], row[7] > 0.5, row[8])

    def put_raw(self, leaf: str, payload: bytes) -> None:
        """Publishes raw bytes on ``<prefix>/session/<id>/<leaf>`` (for protocol tests)."""
        self._z.put(protocol.session_key(self.prefix, self.session_id, leaf), payload)

    # -- queries ---------------------------------------------------------------------------
    def _get(self, key: str, payload: bytes | None = None, timeout_s: float = 2.0) -> list[tuple[str, bytes]]:
        return get_replies(self._z, key, payload, timeout_s)

    def _json(self, key: str, request: dict[str, Any] | None = None, timeout_s: float = 2.0) -> dict[str, Any]:
        return get_json(self._z, key, request, timeout_s)

    def control(self, op: str, timeout_s: float = 2.0, **fields: Any) -> dict[str, Any]:
        """Sends a control request (``op``: create, reset, set_path, set_guidance, set_fading, set_drill, close,
        info) and returns the session info. A refusal raises with the server's reason: a bad value
        as :class:`InvalidInputError`, an unknown session or a full server as :class:`EngineError`."""
        return self._json(self.keys["control"], {"op": op, **fields}, timeout_s)

    def create(
        self,
        path: Any = None,
        guidance_gain: float | None = None,
        burr_radius_m: float | None = None,
        guidance_mode: str | None = None,
    ) -> dict[str, Any]:
        """Creates (or finds) this session, optionally with its own planned path, guidance gain and
        mode (``paper``, ``corridor``, ``brake``, ``shaped``; the server's default otherwise), and
        burr radius (m)."""
        fields: dict[str, Any] = {}
        if guidance_mode is not None:
            fields["guidance_mode"] = str(guidance_mode)
        if path is not None:
            fields |= {"entry_m": [float(v) for v in path.entry_m], "target_m": [float(v) for v in path.target_m]}
        if guidance_gain is not None:
            fields["guidance_gain"] = float(guidance_gain)
        if burr_radius_m is not None:
            fields["burr_radius_m"] = float(burr_radius_m)
        return self.control("create", **fields)

    def set_guidance(self, gain: float | None = None, mode: str | None = None) -> dict[str, Any]:
        """Sets the guidance gain (0 = guidance computed and published, not felt), the mode
        (``paper``, ``corridor``, ``brake``, ``shaped``), or both; what is not given stays."""
        fields: dict[str, Any] = {}
        if gain is not None:
            fields["gain"] = float(gain)
        if mode is not None:
            fields["mode"] = str(mode)
        return self.control("set_guidance", **fields)

    def set_fading(self, params: dict[str, Any] | None = None, *, enabled: bool = True) -> dict[str, Any]:
        """Fades this session's guidance gain over its attempts (each ``reset`` after a drilled
        attempt sets the next gain from its plunge and deviation; every ``probe_every``-th
        attempt is guidance-free); ``params`` overrides the server's defaults, ``enabled=False``
        stops fading. The reply's ``fading`` holds the schedule (``docs/protocol.md``)."""
        return self.control("set_fading", fading=(params or {}) if enabled else None)

    def set_drill(self, burr_radius_m: float) -> dict[str, Any]:
        """Swaps this session's burr for one of ``burr_radius_m`` (m, at most 0.02), as a surgeon
        changes bits: the bone drilled so far stays, the new burr cuts from the next tick on."""
        return self.control("set_drill", burr_radius_m=float(burr_radius_m))

    def metrics(self) -> dict[str, Any]:
        """The server's metrics of this session (SI units)."""
        return self._json(self.keys["metrics"])

    def health(self, window_s: float = 10.0) -> dict[str, Any]:
        """The server's health report, tick statistics over the last ``window_s`` s."""
        return self._json(f"{self.keys['health']}?window={window_s:g}")

    def xray(self, view: str = "*", timeout_s: float = 5.0) -> dict[str, bytes]:
        """PNG radiographs of this session's bone as drilled now: {view: PNG bytes}."""
        return {k.rsplit("/", 1)[-1]: v for k, v in self._get(f"{self.keys['xray']}/{view}", None, timeout_s)}

    # -- helpers ---------------------------------------------------------------------------
    def wait_for_force(self, timeout_s: float = 5.0) -> dict[str, Any]:
        """Blocks until a force has arrived (the server has picked up this session)."""
        t0 = time.monotonic()
        while self.force is None:
            if time.monotonic() - t0 > timeout_s:
                raise TransportError(f"no force from the server within {timeout_s} s")
            time.sleep(0.002)
        return self.force

    def latency_summary(self) -> dict[str, float]:
        """Pose → force and pose → guidance latency p50/p99 (s), and message counts."""

        def q(values: Sequence[float], p: float) -> float:
            return float(np.percentile(np.asarray(values), p)) if len(values) else float("nan")

        with self._lock:
            f, g = list(self.force_latencies_s), list(self.guidance_latencies_s)
        return {
            "forces": self.forces_received,
            "guidance": len(self.guidance),
            "pose_to_force_p50_s": q(f, 50),
            "pose_to_force_p99_s": q(f, 99),
            "pose_to_guidance_p50_s": q(g, 50),
            "pose_to_guidance_p99_s": q(g, 99),
        }

    def close(self) -> None:
        """Closes the Zenoh session (the server frees the session after its idle timeout)."""
        try:
            self._z.close()
        except Exception:
            pass

    def __enter__(self) -> TraineeClient:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
