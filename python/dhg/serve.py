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
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from dhg import protocol
from dhg.errors import InvalidInputError, TransportError

__all__ = ["ModelService", "ServerSettings", "XRayService", "open_zenoh", "start_engine", "zenoh_config_json5"]

log = logging.getLogger("dhg.serve")

DEFAULT_ENDPOINT = "tcp/127.0.0.1:7447"
"""Where ``dhg-serve`` listens unless told otherwise (loopback; use ``tcp/0.0.0.0:7447`` for a lab)."""


@dataclass(frozen=True)
class ServerSettings:
    """Engine and transport settings (SI units)."""

    max_sessions: int = 16
    """Session slots, allocated at start (each reserves 1024 drilled bricks of 1 KiB plus a brick table)."""
    idle_timeout_s: float = 5.0
    """A session without poses or control requests for this long is freed (s)."""
    model_timeout_s: float = 0.25
    """Timeout of one model query (s)."""
    guidance_gain: float = 1.0
    """Guidance gain of new sessions (0 = computed and published, not rendered)."""
    guidance_max_n: float = 0.88
    """Largest guidance share of the rendered force (N; the Touch's continuous force)."""
    guidance_max_rate_n_per_s: float = 8.0
    """Fastest change of the guidance share (N/s): a lost model fades out over ~0.1 s."""
    guidance_timeout_s: float = 0.35
    """A model answer older than this is dropped and guidance fades out (s)."""

    def native(self) -> dict[str, float]:
        """The flat dict ``dhg._bone_sim.Server`` takes."""
        return {
            "idle_timeout_s": self.idle_timeout_s,
            "model_timeout_s": self.model_timeout_s,
            "guidance_gain": self.guidance_gain,
            "guidance.max_n": self.guidance_max_n,
            "guidance.max_rate_n_per_s": self.guidance_max_rate_n_per_s,
            "guidance.timeout_s": self.guidance_timeout_s,
        }


def zenoh_config_json5(
    listen: Sequence[str] = (),
    connect: Sequence[str] = (),
    config_file: str | Path | None = None,
    mode: str = "peer",
) -> str:
    """A Zenoh configuration (JSON5 text) for both the Rust and the Python sessions.

    Without ``config_file``, multicast scouting is off, so that only the given endpoints connect
    (several servers on one host or network never join each other by accident). Endpoints look like
    ``tcp/127.0.0.1:7447``.
    """
    conf: dict[str, Any] = {}
    if config_file is not None:
        import zenoh

        try:
            conf = json.loads(zenoh.Config.from_file(str(config_file)).get_json(""))
        except Exception as exc:  # zenoh raises its own ZError
            raise InvalidInputError(f"cannot read the zenoh config {config_file}: {exc}") from None
    else:
        conf["scouting"] = {"multicast": {"enabled": False}}
    conf["mode"] = mode
    if listen:
        conf.setdefault("listen", {})["endpoints"] = list(listen)
    if connect:
        conf.setdefault("connect", {})["endpoints"] = list(connect)
    return json.dumps(conf)


def open_zenoh(config_json5: str) -> Any:
    """Opens a Python Zenoh session from :func:`zenoh_config_json5` text."""
    import zenoh

    try:
        return zenoh.open(zenoh.Config.from_json5(config_json5))
    except Exception as exc:  # zenoh.ZError
        raise TransportError(f"cannot open a zenoh session: {exc}") from None


class ModelService:
    """Answers ``<prefix>/model/predict`` queries with the model's predicted expert force.

    Queries are queued by the Zenoh callback; one worker thread takes everything that arrived
    within ``max_wait_s`` of the first query (up to ``max_batch`` windows), runs one forward pass,
    and replies to each query. Bad queries get an error reply and are counted.
    """

    def __init__(self, session: Any, model: Any, prefix: str = "dhg", max_batch: int = 64, max_wait_s: float = 0.002):
        self.model = model
        self.model_id = str(model.meta.get("id") or model.meta.get("preset") or model.path.name)
        self.key = f"{prefix}/model/predict"
        self.max_batch = max_batch
        self.max_wait_s = max_wait_s
        self.answered = 0
        self.refused = 0
        self.batches = 0
        self.inference_s: list[float] = []
        self._queue: queue.Queue[Any] = queue.Queue()
        self._stop = threading.Event()
        self._worker = threading.Thread(target=self._run, name="dhg-model", daemon=True)
        self._worker.start()
        self._queryable = session.declare_queryable(self.key, self._on_query, complete=True)

    def _on_query(self, query: Any) -> None:
        self._queue.put(query)

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
                if left <= 0:
                    break
                try:
                    batch.append(self._queue.get(timeout=left))
                except queue.Empty:
                    break
            self._answer(batch)

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
            forces = self.model.predict(np.stack(windows))
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
            try:
                q.reply(self.key, protocol.encode_prediction(seq, f, dt, self.model_id))
                self.answered += 1
            finally:
                q.drop()

    def stats(self) -> dict[str, float]:
        """Answered and refused queries, batches, and inference time p50/p99 (s)."""
        t = np.array(self.inference_s) if self.inference_s else np.zeros(1)
        return {
            "answered": self.answered,
            "refused": self.refused,
            "batches": self.batches,
            "inference_p50_s": float(np.percentile(t, 50)),
            "inference_p99_s": float(np.percentile(t, 99)),
        }

    def close(self) -> None:
        """Undeclares the queryable and stops the worker."""
        self._stop.set()
        try:
            self._queryable.undeclare()
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


def start_engine(
    volume: Any,
    path: Any,
    config_json5: str,
    settings: ServerSettings | None = None,
    prefix: str = "dhg",
    session_config: Any = None,
) -> Any:
    """Starts the native engine (``dhg._bone_sim.Server``) on ``volume`` with the default path."""
    from dhg import _bone_sim

    s = settings or ServerSettings()
    flat = session_config.to_flat_dict() if session_config is not None else None
    return _bone_sim.Server(
        volume._vol,
        [float(v) for v in path.entry_m],
        [float(v) for v in path.target_m],
        config_json5,
        prefix=prefix,
        max_sessions=s.max_sessions,
        server=s.native(),
        session=flat,
    )

