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

import io
import json
import logging
import queue
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

from dhg import _bone_sim, protocol
from dhg.errors import InvalidInputError, TransportError
from dhg.protocol import check_session_id
from dhg.zenoh_config import (
    SERVER_MAX_MESSAGE_BYTES,
    open_zenoh,
    zenoh_config_json5,
    zenoh_user,
)

__all__ = [
    "ROLES",
    "ModelService",
    "RunningServer",
    "Server",
    "ServeOptions",
    "ServerSettings",
    "XRayService",
    "open_zenoh",
    "scheduling_hint",
    "start",
    "start_engine",
    "zenoh_config_json5",
]

log = logging.getLogger("dhg.serve")

DEFAULT_ENDPOINT = "tcp/127.0.0.1:7447"
"""Where ``dhg-serve`` listens unless told otherwise (loopback; use ``tcp/0.0.0.0:7447`` for a lab)."""


_SERVER: dict[str, Any] = _bone_sim.defaults()["server"]
"""The core's ``ServerSettings::default()``: the one place the defaults below are defined."""


@dataclass(frozen=True)
class ServerSettings:
    """Engine and transport settings (SI units)."""

    max_sessions: int = _SERVER["max_sessions"]
    """Session slots, allocated at start (each reserves 1024 drilled bricks of 1 KiB plus a brick table)."""
    idle_timeout_s: float = _SERVER["idle_timeout_s"]
    """A session without poses or control requests for this long is freed (s)."""
    model_timeout_s: float = _SERVER["model_timeout_s"]
    """Timeout of one model query (s)."""
    guidance_mode: str = _SERVER["guidance_mode"]
    """Guidance mode of new sessions: ``paper``, ``corridor``, ``brake`` or ``shaped`` (the default:
    corridor + brake + a warning before the planned breakthrough; ``docs/protocol.md``)."""
    guidance_gain: float = _SERVER["guidance_gain"]
    """Guidance gain of new sessions (0 = computed and published, not rendered)."""
    guidance_max_n: float = _SERVER["guidance_max_n"]
    """Largest guidance share of the rendered force (N; the Touch's continuous force)."""
    guidance_max_rate_n_per_s: float = _SERVER["guidance_max_rate_n_per_s"]
    """Fastest change of the guidance share (N/s): a lost model fades out over ~0.1 s."""
    guidance_timeout_s: float = _SERVER["guidance_timeout_s"]
    """A model answer older than this is dropped and guidance fades out (s)."""
    corridor_profile: tuple[float, tuple[float, ...]] | None = None
    """The corridor's stiffness along A→B: (bin width (m), stiffness per bin (N/m)), from a model's
    demonstration profiles (:mod:`dhg.profiles`); None: the fixed 400 N/m."""
    session_owners: tuple[str, ...] = ()
    """Stations whose sessions (``S`` or ``S-<anything>``) are capped at ``max_sessions_per_owner``
    each (``dhg-serve --lab`` reads them from the lab file)."""
    max_sessions_per_owner: int = _SERVER["max_sessions_per_owner"]
    """Most sessions one station may hold at once (0: no cap)."""
    wait: str = _SERVER["wait"]
    """How the 1 kHz tick thread and the force publisher wait: ``"sleep"`` (idle cores stay idle),
    or ``"spin"`` (while a session is open each keeps a core at 100 %, so no wake-up latency is added
    to a force; for hosts with cores to spare and no real-time scheduling)."""

    def native(self) -> dict[str, Any]:
        """The dict ``dhg._bone_sim.Server`` takes (the core's ``ServerSettings``)."""
        return asdict(self)


class ModelService:
    """Answers the engine's model queries with the model's predicted expert force.

    The service joins the engine's worker pool: it serves ``<prefix>/model/workers/<id>/predict``
    and holds the liveliness token ``<prefix>/model/workers/<id>``, and the engine sends each
    window to one worker of the pool (the one with the fewest queries in flight; see
    ``docs/protocol.md``). ``worker_id`` names it (a session id's characters; default: the Zenoh
    session's id; in the secure lab mode the worker's user name, the one key its access control
    lets it hold). It also serves the shared ``<prefix>/model/predict``, which the engine queries
    while its pool is empty.

    Queries are queued by the Zenoh callback; one worker thread takes everything that arrived
    within ``max_wait_s`` of the first query (up to ``max_batch`` windows), runs one forward pass,
    and replies to each query. With the default ``max_wait_s = 0`` it waits for nothing: queries
    that arrive during a forward pass form the next batch, so batches grow with the load and a
    lone query pays no waiting. Bad queries get an error reply and are counted. The queue holds at
    most ``max_queue`` queries (more are refused at once, as ``busy``), and a query that waited
    longer than ``max_age_s`` (the engine's 0.25 s query timeout by default: its asker has given up)
    is refused as ``stale`` instead of computed. Why no batching wait: ``docs/decisions/0010-model-service.md``.
    """

    def __init__(
        self,
        session: Any,
        model: Any,
        prefix: str = "dhg",
        max_batch: int = 64,
        max_wait_s: float = 0.0,
        max_queue: int = 256,
        max_age_s: float = 0.25,
        clock: Callable[[], float] = time.perf_counter,
        worker_id: str | None = None,
    ):
        if model.window != protocol.WINDOW_RECORDS:
            raise InvalidInputError(
                f"the model takes windows of {model.window} records, but the engine sends "
                f"{protocol.WINDOW_RECORDS} (docs/protocol.md, predict): train it with window {protocol.WINDOW_RECORDS}"
            )
        self.model = model
        self.model_id = str(model.meta.get("id") or model.meta.get("preset") or model.path.name)
        self.key = f"{prefix}/model/predict"
        self.max_batch = max_batch
        self.max_wait_s = max_wait_s
        self.max_age_s = max_age_s
        self._clock = clock  # what a query's age is measured with (s)
        self.answered = 0
        self.refused = 0
        self.busy = 0
        self.stale = 0
        self.batches = 0
        self.inference_s: list[float] = []
        self._queue: queue.Queue[tuple[float, Any]] = queue.Queue(maxsize=max_queue)
        self._stop = threading.Event()
        # TorchScript's profiling executor optimises on the first calls (100s of ms): do them now,
        # not on a trainee's first windows.
        for batch in (1, 2, 1):
            model.predict(np.zeros((batch, model.window, 9), dtype=np.float32))
        self._worker = threading.Thread(target=self._run, name="dhg-model", daemon=True)
        self._worker.start()
        self.worker_id = check_session_id(worker_id if worker_id is not None else str(session.info.zid()))
        self.worker_key = f"{prefix}/model/workers/{self.worker_id}"
        self._queryables = [
            session.declare_queryable(key, self._on_query, complete=True)
            for key in (self.key, f"{self.worker_key}/predict")
        ]
        # Declared last: the engine sends this worker queries once it sees the token.
        self._token = session.liveliness().declare_token(self.worker_key)

    def _on_query(self, query: Any) -> None:
        try:
            self._queue.put_nowait((self._clock(), query))
        except queue.Full:
            self.busy += 1
            self._reply_error(query, "busy: the model service's queue is full")

    def _reply_error(self, query: Any, message: str) -> None:
        self.refused += 1
        try:
            query.reply_err(json.dumps({"error": message}))
        finally:
            query.drop()

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                first = self._queue.get(timeout=0.1)
            except queue.Empty:
                continue
            batch = [first]
            deadline = time.perf_counter() + self.max_wait_s
            while len(batch) < self.max_batch:
                left = deadline - time.perf_counter()
                try:
                    batch.append(self._queue.get(timeout=left) if left > 0 else self._queue.get_nowait())
                except queue.Empty:
                    break
            now = self._clock()
            fresh = []
            for arrived, q in batch:
                if now - arrived > self.max_age_s:
                    self.stale += 1
                    self._reply_error(q, f"stale: queued {now - arrived:.3f} s, longer than {self.max_age_s} s")
                else:
                    fresh.append(q)
            if fresh:
                self._answer(fresh)

    def _answer(self, batch: list[Any]) -> None:
        good, windows = [], []
        for q in batch:
            try:
                payload = q.payload.to_bytes() if q.payload is not None else b""
                seq, window = protocol.decode_predict(payload)
                if window.shape != (self.model.window, 9) or not np.all(np.isfinite(window)):
                    raise InvalidInputError(f"window of shape {window.shape} or non-finite values")
            except (InvalidInputError, ValueError) as exc:
                self._reply_error(q, str(exc))
                continue
            good.append((q, seq))
            windows.append(window)
        if not good:
            return
        t0 = time.perf_counter()
        try:
            forces = self.model.predict(np.stack(windows), check_output=False)
        except Exception as exc:  # a model failure must not kill the worker
            log.exception("model forward failed")
            for q, _ in good:
                self._reply_error(q, f"model failed: {exc}")
            return
        dt = time.perf_counter() - t0
        self.batches += 1
        self.inference_s.append(dt)
        del self.inference_s[:-1000]
        for (q, seq), f in zip(good, forces, strict=True):
            if not np.all(np.isfinite(f)):  # a window far outside the training ranges overflows the model
                self._reply_error(
                    q, "the prediction is not finite: the window's values lie far outside the model's ranges"
                )
                continue
            try:
                q.reply(q.key_expr, protocol.encode_prediction(seq, f, dt, self.model_id))
                self.answered += 1
            finally:
                q.drop()

    def stats(self) -> dict[str, float]:
        """Answered and refused queries (of them: busy, stale), batches, and inference time p50/p99 (s)."""
        t = np.array(self.inference_s) if self.inference_s else np.zeros(1)
        return {
            "answered": self.answered,
            "refused": self.refused,
            "busy": self.busy,
            "stale": self.stale,
            "batches": self.batches,
            "inference_p50_s": float(np.percentile(t, 50)),
            "inference_p99_s": float(np.percentile(t, 99)),
        }

    def close(self) -> None:
        """Leaves the pool (the token first, so the engine stops choosing it), undeclares the
        queryables and stops the worker thread."""
        self._stop.set()
        for entity in (self._token, *self._queryables):
            try:
                entity.undeclare()
            except Exception:  # the session may already be closed
                pass
        self._worker.join(timeout=2.0)


class XRayService:
    """Answers ``<prefix>/session/<id>/xray/<view>`` (view: top, front, side or ``*``) with PNG
    radiographs of that session's bone as drilled now, with the planned path drawn in."""

    def __init__(self, session: Any, server: Any, volume: Any, prefix: str = "dhg"):
        from dhg.xray import auto_windows

        self.server = server
        self.volume = volume
        self.prefix = prefix
        self.windows = auto_windows(volume.xray())
        self._queryable = session.declare_queryable(f"{prefix}/session/*/xray/*", self._on_query)

    def _on_query(self, query: Any) -> None:
        from dhg.task import PlannedPath
        from dhg.volume import XRayViews
        from dhg.xray import render_views

        try:
            parts = str(query.key_expr).split("/")
            sid, view = parts[-3], parts[-1]
            if view not in ("top", "front", "side", "*"):
                raise InvalidInputError(f"unknown view {view!r}: use top, front, side or *")
            info = self.server.control(sid, {"op": "info"})
            top, front, side = self.server.xray(sid)
            path = PlannedPath(np.array(info["entry_m"]), np.array(info["target_m"]))
            images = render_views(self.volume, XRayViews(top, front, side), path, windows=self.windows)
            for name, img in images.items():
                if view in ("*", name):
                    buf = io.BytesIO()
                    img.save(buf, format="PNG")
                    query.reply(f"{self.prefix}/session/{sid}/xray/{name}", buf.getvalue(), encoding="image/png")
        except Exception as exc:  # every failure becomes an error reply, never a dead callback
            query.reply_err(json.dumps({"error": str(exc)}))
        finally:
            query.drop()

    def close(self) -> None:
        """Undeclares the queryable."""
        try:
            self._queryable.undeclare()
        except Exception:
            pass


class Server:
    """The real-time engine on Zenoh (the native ``dhg._bone_sim.Server``): the 1 kHz tick thread,
    the comm thread, and the keys of ``docs/protocol.md``. Start one with :func:`start_engine`
    (or ``dhg-serve``); every reply is a plain dict in SI units."""

    def __init__(self, native: Any) -> None:
        self._native = native

    def health(self, window_s: float = 10.0) -> dict[str, Any]:
        """The health report (``docs/protocol.md``, health), tick quantiles over the last ``window_s`` s."""
        return self._native.health(window_s)

    def sessions(self) -> list[str]:
        """Ids of the open sessions."""
        return self._native.sessions()

    def metrics(self, session_id: str) -> dict[str, Any]:
        """A session's metrics; an unknown session is an :class:`~dhg.errors.EngineError`."""
        return self._native.metrics(session_id)

    def control(self, session_id: str, request: dict[str, Any]) -> dict[str, Any]:
        """Applies a control request (``{"op": ...}``, ``docs/protocol.md``); returns the session info."""
        return self._native.control(session_id, request)

    def xray(self, session_id: str, timeout_s: float = 1.0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The (top, front, side) X-ray line integrals of a session's bone as drilled now."""
        return self._native.xray(session_id, timeout_s)

    def stop(self) -> None:
        """Stops the threads and closes the engine's Zenoh session (idempotent)."""
        self._native.stop()

    @property
    def running(self) -> bool:
        """Whether the engine runs."""
        return self._native.running


def start_engine(
    volume: Any,
    path: Any,
    config_json5: str,
    settings: ServerSettings | None = None,
    prefix: str = "dhg",
    session_config: Any = None,
) -> Server:
    """Starts the engine on ``volume`` with ``path`` as new sessions' planned path, Zenoh
    configured by ``config_json5`` (:func:`dhg.zenoh_config.zenoh_config_json5`)."""
    s = settings or ServerSettings()
    return Server(
        _bone_sim.Server(
            volume._vol,
            [float(v) for v in path.entry_m],
            [float(v) for v in path.target_m],
            config_json5,
            prefix=prefix,
            settings=s.native(),
            session=session_config.to_native() if session_config is not None else None,
        )
    )


# -- dhg-serve: one process running the roles ---------------------------------------------------
ROLES = ("all", "sim", "model")


SPIN_MIN_CORES = 8
"""Fewest cores on which ``scheduling_hint`` suggests ``--wait spin`` (it keeps two busy)."""


def scheduling_hint(health: dict[str, Any], cores: int) -> str | None:
    """What to tell the operator about the tick thread's scheduling, from an engine ``health()``
    report and the machine's core count; ``None`` when nothing needs saying (real-time priority
    granted, or already spinning)."""
    if health.get("tick_realtime") or health.get("tick_wait") == "spin":
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


class RunningServer:
    """The parts ``dhg-serve`` started; :meth:`close` stops them in order (engine last)."""

    def __init__(self, options: ServeOptions):
        self.options = options
        self.engine: Server | None = None
        self.zenoh: Any = None
        self.model_service: ModelService | None = None
        self.xray_service: XRayService | None = None
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
        for svc in (self.xray_service, self.model_service):
            if svc is not None:
                svc.close()
        self.xray_service = self.model_service = None
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
                run.engine = start_engine(volume, path, conf, options.settings, options.prefix)
            except TransportError as exc:
                raise _friendly(exc, listen) from None
            py_conf = zenoh_config_json5(
                (),
                [_loopback(e) for e in listen],
                options.zenoh_config,
                mode="client",
                max_message_bytes=SERVER_MAX_MESSAGE_BYTES,
            )
        else:
            connect = list(options.connect) or ([] if options.listen else [DEFAULT_ENDPOINT])
            run.endpoints = list(options.listen) or connect
            py_conf = zenoh_config_json5(
                options.listen, connect, options.zenoh_config, mode="peer", max_message_bytes=SERVER_MAX_MESSAGE_BYTES
            )
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
            )
        if engine_role:
            run.xray_service = XRayService(run.zenoh, run.engine, volume, options.prefix)
    except BaseException:
        run.close()
        raise
    return run
