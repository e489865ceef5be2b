"""The guidance server: the Rust haptic engine on Zenoh plus the model service, as ``dhg-serve`` runs them.

Roles (``--role``):

- ``sim``: the haptic engine (``dhg._bone_sim.Server``: its own Zenoh session, the 1 kHz tick thread,
  the comm thread) and the X-ray queryable. It queries ``<prefix>/model/predict`` for guidance.
- ``model``: the model service alone (:class:`ModelService`): a queryable that batches the windows
  of concurrent queries into one forward pass of the TorchScript model. Run it on a GPU machine
  next to an engine elsewhere with ``--connect``.
- ``all`` (default): both in one process.

Several model workers may serve one engine for redundancy; a Zenoh query goes to one of them (the
nearest complete queryable), so they do not share load.
"""

from __future__ import annotations

import json
import logging
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from dhg.core.errors import InvalidInputError, TransportError
from dhg.core.server import Server, ServerSettings, start_engine
from dhg.core.session import SessionConfig
from dhg.live.services import MODEL_NICE, AboutService, BoneService, ModelService, XRayService
from dhg.live.zenoh_config import (
    SERVER_MAX_MESSAGE_BYTES,
    open_zenoh,
    zenoh_config_json5,
    zenoh_user,
)

__all__ = [
    "DEFAULT_ENDPOINT",
    "ROLES",
    "SPIN_MIN_CORES",
    "RunningServer",
    "ServeOptions",
    "scheduling_hint",
    "start",
]

log = logging.getLogger("dhg.live.runner")

DEFAULT_ENDPOINT = "tcp/127.0.0.1:7447"
"""Where ``dhg-serve`` listens unless told otherwise (loopback; use ``tcp/0.0.0.0:7447`` for a lab)."""


# -- dhg-serve: one process running the roles ---------------------------------------------------
ROLES = ("all", "sim", "model")


SPIN_MIN_CORES = 8
"""Fewest cores on which ``scheduling_hint`` suggests ``--wait spin`` (it keeps two busy)."""


def scheduling_hint(health: dict[str, Any], cores: int) -> str | None:
    """What to tell the operator about the tick thread's scheduling, from an engine ``health()``
    report and the machine's core count; ``None`` when nothing needs saying (real-time priority
    granted, already spinning, or not asked for: where the poses' threads run the ticks, the
    default ``--tick-on pose``, the tick thread keeps normal scheduling on purpose,
    ``docs/decisions/0033-the-tick-thread-yields-to-the-poses.md``)."""
    if health.get("tick_realtime") or health.get("tick_wait") == "spin" or health.get("tick_on") == "pose":
        return None
    # Without SCHED_FIFO the engine still asks the kernel (Linux 6.12+) for a short time slice.
    meanwhile = (
        " Meanwhile it runs on the kernel's 0.1 ms slice, which halved missed ticks on a 2-core VM."
        if health.get("short_slices", {}).get("tick")
        else ""
    )
    if cores >= SPIN_MIN_CORES:
        return (
            f"the tick thread has no real-time priority (SCHED_FIFO refused). On this {cores}-core machine, "
            "'--wait spin' keeps the host's wake-up latency out of every force (two cores busy while a session "
            "is open); or grant CAP_SYS_NICE." + meanwhile
        )
    return (
        "the tick thread has no real-time priority (SCHED_FIFO refused): forces pay the host's wake-up "
        "latency. Grant CAP_SYS_NICE (e.g. 'setcap cap_sys_nice+ep' on the Python binary) or an rtprio limit."
        + meanwhile
    )


def _loopback(endpoint: str) -> str:
    """The endpoint a process on the same host connects to (wildcard hosts become 127.0.0.1)."""
    proto, _, rest = endpoint.partition("/")
    host, _, port = rest.rpartition(":")
    if host in ("0.0.0.0", "[::]", "::", ""):
        host = "127.0.0.1"
    return f"{proto}/{host}:{port}"


@dataclass
class ServeOptions:
    """What ``dhg-serve`` runs (see :func:`start`)."""

    role: str = "all"
    """``all`` (engine + model), ``sim`` (engine, X-ray), ``model`` (model service alone)."""
    listen: Sequence[str] = ()
    """Endpoints to listen on. Default: :data:`DEFAULT_ENDPOINT` for ``all``/``sim``, none for ``model``."""
    connect: Sequence[str] = ()
    """Endpoints to connect to (for ``model``: the engine; default :data:`DEFAULT_ENDPOINT`)."""
    zenoh_config: str | Path | None = None
    """A Zenoh JSON5 config file; listen/connect still override its endpoints."""
    prefix: str = "dhg"
    """First chunk of every key expression."""
    settings: ServerSettings = ServerSettings()
    model_device: str = "auto"
    """``cpu``, ``cuda`` or ``auto`` (CUDA when present)."""
    worker_id: str | None = None
    """The model service's name in the engine's worker pool (default: the Zenoh user name of
    ``zenoh_config`` when it has one, else the Zenoh session id)."""
    model_nice: int = MODEL_NICE
    """Linux nice value of the model's worker thread (0 to 19; see :class:`ModelService`)."""


class RunningServer:
    """The parts ``dhg-serve`` started; :meth:`close` stops them in order (engine last)."""

    def __init__(self, options: ServeOptions):
        self.options = options
        self.engine: Server | None = None
        self.zenoh: Any = None
        self.model_service: ModelService | None = None
        self.xray_service: XRayService | None = None
        self.bone_service: BoneService | None = None
        self.about_service: AboutService | None = None
        self.endpoints: list[str] = []
        self.started = time.monotonic()

    def status(self) -> dict[str, Any]:
        """Sessions, tick p99 and missed ticks (engine), model latency and answers (service)."""
        out: dict[str, Any] = {"uptime_s": time.monotonic() - self.started}
        if self.engine is not None:
            out["engine"] = self.engine.health(5.0)
        if self.model_service is not None:
            out["model_service"] = self.model_service.stats()
        return out

    def status_line(self) -> str:
        """The one-line status ``dhg-serve`` logs every few seconds."""
        s = self.status()
        parts = []
        if "engine" in s:
            h = s["engine"]
            m = h["model"]
            model = (
                f"model {'up' if m['available'] else 'DOWN'} p50/p99 {m['latency_p50_s'] * 1e3:.1f}/"
                f"{m['latency_p99_s'] * 1e3:.1f} ms"
                if m["queries"]
                else "model idle"
            )
            if h.get("tick_thread_failed"):
                parts.append("TICK THREAD STOPPED by an error (a bug, printed above): restart dhg-serve")
            parts.append(
                f"sessions {h['sessions']}/{h['max_sessions']} | tick{' (rt)' if h['tick_realtime'] else ''}"
                f"{' (spin)' if h['tick_wait'] == 'spin' else ''} "
                f"p99 {h['tick_lateness_p99_s'] * 1e6:.0f} µs "
                f"late, busy p99 {h['tick_busy_p99_s'] * 1e6:.0f} µs | pose→put p50/p99 "
                f"{h['pose_to_put_p50_s'] * 1e6:.0f}/{h['pose_to_put_p99_s'] * 1e6:.0f} µs "
                f"| missed {h['missed_ticks']} (total {h['missed_ticks_total']}) | {model} | poses {h['poses']}"
            )
        if "model_service" in s:
            ms = s["model_service"]
            parts.append(
                f"model service answered {ms['answered']} in {ms['batches']} batches, "
                f"refused {ms['refused']}, inference p50/p99 {ms['inference_p50_s'] * 1e3:.1f}/"
                f"{ms['inference_p99_s'] * 1e3:.1f} ms"
            )
        return " || ".join(parts)

    def close(self) -> None:
        """Stops the services, closes the Python Zenoh session, then stops the engine (which closes
        its sessions and its own Zenoh session). Safe to call twice."""
        for svc in (self.about_service, self.bone_service, self.xray_service, self.model_service):
            if svc is not None:
                svc.close()
        self.about_service = self.bone_service = self.xray_service = self.model_service = None
        if self.zenoh is not None:
            try:
                self.zenoh.close()
            except Exception:
                pass
            self.zenoh = None
        if self.engine is not None:
            self.engine.stop()
            self.engine = None

    def __enter__(self) -> RunningServer:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def _without_access_control(config_json: str) -> str:
    """The server's own Python client (the X-ray, bone and model services) in lab mode: the
    router's access-control list is in the same file, but it is the router's to enforce. Applied
    by the client to itself, it would drop every query the router forwards to the services (the
    router's rules allow the server identity to answer queries, not to receive them)."""
    conf = json.loads(config_json)
    if "access_control" in conf:
        conf["access_control"] = {"enabled": False}
    return json.dumps(conf)


def _listening_nowhere(config_json: str) -> str:
    """A model worker that connects to its engines: a peer (it keeps every engine it is given,
    reached or retried in the background, where a client keeps one and fails if its engine is not
    up yet) that opens no port. Left to Zenoh's default, a peer listens on a random TCP port of
    every interface, in the clear and around the router's TLS, passwords and access control, even
    with a lab's file (whose client files name no listen endpoint); and it learns other peers from
    the router's gossip and connects to them. Listen endpoints that a config file names are kept."""
    conf = json.loads(config_json)
    listen = conf.setdefault("listen", {})
    if not isinstance(listen.get("endpoints"), list):  # unset: Zenoh's per-mode default
        listen["endpoints"] = []
    scouting = conf.setdefault("scouting", {})
    scouting["gossip"] = {**(scouting.get("gossip") or {}), "enabled": False}
    return json.dumps(conf)


def _friendly(exc: Exception, endpoints: Sequence[str]) -> TransportError:
    text = str(exc)
    if "Address already in use" in text:
        return TransportError(
            f"cannot listen on {', '.join(endpoints)}: the address is already in use "
            "(another dhg-serve? pick a free port with --listen tcp/127.0.0.1:PORT)"
        )
    return TransportError(text.split(" at /")[0])


def start(options: ServeOptions, volume: Any = None, path: Any = None, model: Any = None) -> RunningServer:
    """Starts the roles of ``options``. ``volume``/``path`` (``sim``, ``all``) and ``model``
    (``model``, ``all``) must be given for the roles that need them. On any failure, what was
    started is stopped again before the error propagates."""
    if options.role not in ROLES:
        raise InvalidInputError(f"unknown role {options.role!r}: use one of {', '.join(ROLES)}")
    run = RunningServer(options)
    try:
        engine_role = options.role in ("all", "sim")
        session_config = SessionConfig()  # what every session runs with, as the engine and the card see it
        if engine_role:
            if volume is None or path is None:
                raise InvalidInputError("the engine needs a volume and a planned path")
            listen = list(options.listen) or [DEFAULT_ENDPOINT]
            run.endpoints = listen
            # The engine is the router: trainees, recorders and model workers connect to it.
            conf = zenoh_config_json5(
                listen, options.connect, options.zenoh_config, mode="router", max_message_bytes=SERVER_MAX_MESSAGE_BYTES
            )
            try:
                run.engine = engine = start_engine(volume, path, conf, options.settings, options.prefix, session_config)
            except TransportError as exc:
                raise _friendly(exc, listen) from None
            guidance = engine.new_session_guidance
            py_conf = _without_access_control(
                zenoh_config_json5(
                    (),
                    [_loopback(e) for e in listen],
                    options.zenoh_config,
                    mode="client",
                    max_message_bytes=SERVER_MAX_MESSAGE_BYTES,
                )
            )
        else:
            connect = list(options.connect) or ([] if options.listen else [DEFAULT_ENDPOINT])
            run.endpoints = list(options.listen) or connect
            py_conf = zenoh_config_json5(
                options.listen, connect, options.zenoh_config, mode="peer", max_message_bytes=SERVER_MAX_MESSAGE_BYTES
            )
            if not options.listen:
                py_conf = _listening_nowhere(py_conf)
        try:
            run.zenoh = open_zenoh(py_conf)
        except TransportError as exc:
            raise _friendly(exc, options.listen) from None
        if options.role in ("all", "model"):
            if model is None:
                raise InvalidInputError("the model service needs a model")
            run.model_service = ModelService(
                run.zenoh,
                model,
                options.prefix,
                max_age_s=options.settings.model_timeout_s,
                worker_id=options.worker_id or zenoh_user(options.zenoh_config),
                nice=options.model_nice,
            )
        if engine_role:
            run.xray_service = XRayService(run.zenoh, run.engine, volume, options.prefix)
            run.bone_service = BoneService(run.zenoh, run.engine, volume, options.prefix)
            served = model if options.role == "all" else None  # with --role sim, the workers run theirs
            run.about_service = AboutService(
                run.zenoh, volume, path, session_config, guidance=guidance, model=served, prefix=options.prefix
            )
    except BaseException:
        run.close()
        raise
    return run
