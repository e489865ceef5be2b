"""The model service, the X-ray service and the bone service: the Python halves of ``dhg-serve``
on Zenoh."""

from __future__ import annotations

import io
import json
import logging
import os
import queue
import threading
import time
from collections import deque
from collections.abc import Callable
from typing import Any

import numpy as np

from dhg.core import protocol
from dhg.core.errors import InvalidInputError
from dhg.core.protocol import check_session_id
from dhg.core.volume import VIEW_NAMES

__all__ = [
    "BURST_MEMORY_S",
    "BURST_WAIT_S",
    "MODEL_NICE",
    "AboutService",
    "BoneService",
    "CorridorCheck",
    "ModelService",
    "XRayService",
    "corridor_mismatch",
    "decode_npz",
    "encode_npz",
]

MODEL_NICE = 10
"""``dhg-serve``'s nice value for the model worker thread: on shared cores a forward pass gives way
to the forces' threads (decision 0026), yet still gets about a tenth of a core where other programs
keep the cores busy at nice 0 (at 19 it got 1.5 %, and a third of the guidance timed out; 0038)."""

BURST_WAIT_S = 0.002
"""How long (s) the model worker waits, after a batch of N > 1 queries, for the next burst's N: the
engine's sessions record on one 100 ms grid, and an engine sends each burst of their windows in
one query (decision 0032), so N > 1 queries a burst come from several engines sharing the worker
(or an engine whose query was full), within a tick or two of the mark; 2 ms gathers a burst that
a forward pass would otherwise split in two (decision 0028). An engine whose window comes late
sends its query up to 6 ms after its first (decision 0035); that query then misses this wait and
takes a pass of its own (several engines on one worker are not remeasured since)."""

BURST_MEMORY_S = 0.15
"""How long (s) the model worker remembers a batch's size as the size of the bursts to come: one
100 ms record period and a half."""

MAX_NPZ_BYTES = 12 * 1024 * 1024
"""The largest bone or volume reply (bytes): clients take messages up to 16 MiB."""


def encode_npz(**arrays: np.ndarray) -> bytes:
    """Arrays as a compressed ``.npz`` (the bone and volume replies' format)."""
    buf = io.BytesIO()
    np.savez_compressed(buf, **arrays)  # type: ignore[arg-type]  # the stub types **kwds as numpy 2.2's allow_pickle
    return buf.getvalue()


def decode_npz(payload: bytes) -> dict[str, np.ndarray]:
    """The arrays of an ``.npz`` reply (no pickled objects)."""
    with np.load(io.BytesIO(payload), allow_pickle=False) as z:
        return {k: z[k] for k in z.files}


log = logging.getLogger("dhg.live.runner")


class ModelService:
    """Answers the engine's model queries with the model's predicted expert force.

    The service joins the engine's worker pool: it serves ``<prefix>/model/workers/<id>/predict``
    and holds the liveliness token ``<prefix>/model/workers/<id>``, and the engine sends each
    window to one worker of the pool (the one with the fewest queries in flight; see
    ``docs/protocol.md``). ``worker_id`` names it (a session id's characters; default: the Zenoh
    session's id; in the secure lab mode the worker's user name, the one key its access control
    lets it hold). It also serves the shared ``<prefix>/model/predict``, which the engine queries
    while its pool is empty.

    A query holds the windows of one or more sessions (the engine sends each 100 ms burst in one
    query; ``docs/protocol.md``), and its reply one prediction per window. Queries are queued by the
    Zenoh callback; one worker thread takes everything that arrived within ``max_wait_s`` of the
    first query (up to ``max_batch`` queries), runs one forward pass (``max_batch`` windows at most;
    more take more passes), and replies to each query. With the default ``max_wait_s = 0`` it waits
    for nothing: queries that arrive during a forward pass form the next batch, so batches grow with
    the load and a lone query pays no waiting. One exception: the engines put every session's
    records on one 100 ms grid, so where several engines share the worker their queries come in
    bursts, one an engine (each sends its sessions' windows in one query). Within
    :data:`BURST_MEMORY_S` of a batch of N > 1 queries the worker waits up to ``burst_wait_s``
    (default :data:`BURST_WAIT_S`) for N, so that one pass answers the whole burst, not its first
    query alone; where the batches were lone queries it waits for nothing
    (``docs/decisions/0028-records-on-one-grid.md``). Bad queries get an error reply and are
    counted. The queue holds at most ``max_queue`` queries (more are refused at once, as ``busy``),
    and a query that waited longer than ``max_age_s`` (the engine's 0.25 s query timeout by default:
    its asker has given up) is refused as ``stale`` instead of computed. Why no batching wait:
    ``docs/decisions/0010-model-service.md``.

    The worker thread runs at the Linux nice value ``nice`` (default :data:`MODEL_NICE`): where the
    model shares cores with the 1 kHz engine, the Zenoh threads that carry poses and forces preempt
    a forward pass as soon as they wake, instead of waiting behind a few milliseconds of LSTM
    (``docs/decisions/0026-the-model-yields-to-the-forces.md``, ``0038-the-model-yields-at-nice-10.md``).
    0 leaves it as it is; where nice values do not exist (not Linux) it is ignored.
    """

    def __init__(
        self,
        session: Any,
        model: Any,
        prefix: str = "dhg",
        max_batch: int = 64,
        max_wait_s: float = 0.0,
        burst_wait_s: float | None = None,
        max_queue: int = 256,
        max_age_s: float = 0.25,
        clock: Callable[[], float] = time.perf_counter,
        worker_id: str | None = None,
        nice: int = 0,
    ):
        if max_batch < 1:
            raise InvalidInputError(f"max_batch is the most windows a forward pass takes: at least 1, got {max_batch}")
        if not 0 <= nice <= 19:
            raise InvalidInputError(f"nice must be 0 (as the engine) to 19 (yield to everything), got {nice}")
        if model.window != protocol.WINDOW_RECORDS:
            raise InvalidInputError(
                f"the model takes windows of {model.window} records, but the engine sends "
                f"{protocol.WINDOW_RECORDS} (docs/protocol.md, predict): train it with window {protocol.WINDOW_RECORDS}"
            )
        self.model = model
        self.model_id = str(model.meta.get("id") or model.meta.get("preset") or model.path.name)
        self.key = protocol.shared_predict_key(prefix)
        self.max_batch = max_batch
        self.max_wait_s = max_wait_s
        self.burst_wait_s = BURST_WAIT_S if burst_wait_s is None else burst_wait_s
        self.max_age_s = max_age_s
        self._clock = clock  # what a query's age is measured with (s)
        self.answered = 0
        self.refused = 0
        self.busy = 0
        self.stale = 0
        self.batches = 0
        self.inference_s: deque[float] = deque(maxlen=1000)
        """The last 1,000 forward passes' durations (s)."""
        self._queue: queue.Queue[tuple[float, Any]] = queue.Queue(maxsize=max_queue)
        self._stop = threading.Event()
        self.nice = nice
        # TorchScript's profiling executor optimises on the first calls (100s of ms): do them now,
        # not on a trainee's first windows.
        for batch in (1, 2, 1):
            model.predict(np.zeros((batch, model.window, 9), dtype=np.float32))
        self._worker = threading.Thread(target=self._run, name="dhg-model", daemon=True)
        self._worker.start()
        self.worker_id = check_session_id(worker_id if worker_id is not None else str(session.info.zid()))
        self.worker_key = protocol.worker_key(prefix, self.worker_id)
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
        if self.nice and hasattr(os, "setpriority"):
            # Linux nice values are per thread: this lowers the worker's (torch runs its forward
            # passes on this thread with one intra-op thread, dhg-serve's default on ≤ 7 cores) and
            # those of ONNX Runtime's intra-op pool when it has one (more threads).
            for tid in (threading.get_native_id(), *getattr(getattr(self.model, "runner", None), "pool_threads", ())):
                try:
                    os.setpriority(os.PRIO_PROCESS, tid, self.nice)
                except OSError:  # a pool thread that has ended
                    pass
        # The largest batch of the last grid period and a half: the queries of the burst now
        # arriving (a session a stall put off the grid for a few records then waits 2 ms alone,
        # instead of splitting the bursts of the others).
        recent: deque[tuple[float, int]] = deque(maxlen=64)
        while not self._stop.is_set():
            try:
                first = self._queue.get(timeout=0.1)
            except queue.Empty:
                continue
            batch = [first]
            t0 = time.perf_counter()
            expect = max((n for t, n in recent if t0 - t < BURST_MEMORY_S), default=1)
            while len(batch) < self.max_batch:
                wait = max(self.burst_wait_s if len(batch) < expect else 0.0, self.max_wait_s)
                left = t0 + wait - time.perf_counter()
                try:
                    batch.append(self._queue.get(timeout=left) if left > 0 else self._queue.get_nowait())
                except queue.Empty:
                    break
            recent.append((t0, len(batch)))
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
                seqs, w = protocol.decode_predict(payload)
                if w.shape[1:] != (self.model.window, 9):
                    raise InvalidInputError(f"windows of shape {w.shape[1:]}, the model takes ({self.model.window}, 9)")
            except (InvalidInputError, ValueError) as exc:
                self._reply_error(q, str(exc))
                continue
            good.append((q, seqs))
            windows.append(w)
        if not good:
            return
        stacked = np.concatenate(windows)
        # A window with NaN or inf is not computed.
        usable = np.asarray(np.isfinite(stacked).all(axis=(1, 2)), dtype=np.bool_)
        stacked = np.where(usable[:, None, None], stacked, np.float32(0.0))
        forces = np.empty((len(stacked), 3), dtype=np.float32)
        pass_s = np.empty(len(stacked))
        try:
            # One forward pass for the whole batch, up to max_batch windows a pass.
            for i in range(0, len(stacked), self.max_batch):
                t0 = time.perf_counter()
                forces[i : i + self.max_batch] = self.model.predict(stacked[i : i + self.max_batch], check_output=False)
                pass_s[i : i + self.max_batch] = dt = time.perf_counter() - t0
                self.batches += 1
                self.inference_s.append(dt)
        except Exception as exc:  # a model failure must not kill the worker
            log.exception("model forward failed")
            for q, _ in good:
                self._reply_error(q, f"model failed: {exc}")
            return
        usable &= np.isfinite(forces).all(axis=1)  # a window far outside the training ranges overflows
        at = 0
        for q, seqs in good:
            part = range(at, at + len(seqs))
            at += len(seqs)
            # A window the model cannot answer goes unanswered (its session keeps its last
            # guidance); the query's other windows are answered.
            answered = [k for k in part if usable[k]]
            if not answered:
                self._reply_error(
                    q,
                    "no window of the query has a finite prediction: its values are not finite, or lie "
                    "far outside the model's ranges",
                )
                continue
            try:
                body = b"".join(
                    protocol.encode_prediction(
                        int(seqs[k - part.start]), forces[k], pass_s[k], self.model_id, k - part.start
                    )
                    for k in answered
                )
                q.reply(q.key_expr, body)
                self.answered += len(answered)
            except Exception:  # a reply Zenoh cannot send (the session closing) must not end the worker
                log.exception("model reply failed")
            finally:
                q.drop()

    def stats(self) -> dict[str, float]:
        """Answered windows, refused queries (of them: busy, stale), batches, and inference time p50/p99 (s)."""
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


def corridor_mismatch(about: dict[str, Any], meta: dict[str, Any]) -> str | None:
    """Why an engine (its ``<prefix>/server/about`` reply, ``about``) guides its sessions' corridor
    by other expert profiles than those of the model whose metadata is ``meta``, or None where they
    agree. The corridor comes from the engine's ``--model`` (``dhg-serve --role sim``), the cue from
    the worker's: with two models, a session is kept on one set of experts' line and eased by
    another's forces."""
    from dhg.learning.profiles import DemoProfiles

    params = about.get("guidance", {}).get("params", {})
    engine = [float(v) for v in params.get("corridor_profile_n_per_m", [])]
    engine_bin = float(params.get("corridor_profile_bin_m", 0.0))
    mine = None if meta.get("profiles") is None else DemoProfiles.from_dict(meta["profiles"])
    if mine is None:
        if not engine:
            return None
        return (
            "this model has no expert profiles, but the engine guides its corridor by profiles of "
            f"{len(engine)} depth bins: it was started with another --model"
        )
    ours = [float(v) for v in mine.corridor_n_per_m]
    same = (
        len(ours) == len(engine)
        and abs(engine_bin - mine.bin_m) <= 1e-12
        and all(abs(a - b) <= 1e-9 * max(1.0, abs(a)) for a, b in zip(ours, engine, strict=True))
    )
    if same:
        return None
    if not engine:
        return "the engine guides its corridor at a fixed stiffness, not by this model's expert profiles"
    return (
        f"the engine guides its corridor by other expert profiles ({len(engine)} bins of {engine_bin * 1e3:g} mm, "
        f"{min(engine):.0f}-{max(engine):.0f} N/m) than this model's ({len(ours)} bins of {mine.bin_m * 1e3:g} mm, "
        f"{min(ours):.0f}-{max(ours):.0f} N/m): start the engine with --model set to the file this worker serves"
    )


class CorridorCheck:
    """A model worker's check of the engine it serves: asks ``<prefix>/server/about`` (every
    ``every_s`` until an engine answers) and reports, through ``report``, a warning where
    :func:`corridor_mismatch` finds one, or a note that the corridor is this model's; after
    ``quiet_tries`` unanswered asks it also says, once, that no engine has answered yet. Once
    answered it asks again every ``recheck_s``, so an engine restarted with another ``--model``
    is found, and reports again only when the outcome changes (a restart with the same model
    says nothing)."""

    def __init__(
        self,
        session: Any,
        meta: dict[str, Any],
        prefix: str = "dhg",
        *,
        report: Callable[[str], None],
        every_s: float = 2.0,
        quiet_tries: int = 15,
        recheck_s: float = 30.0,
    ):
        if not (every_s > 0 and recheck_s > 0):
            raise InvalidInputError(f"every_s and recheck_s must be > 0 s, not {every_s} and {recheck_s}")
        self.result: str | None = None
        """The line last reported on an engine's answer (None until one came)."""
        self._z, self._meta, self._report = session, meta, report
        self._key = protocol.server_key(prefix, "about")
        self._every, self._quiet_tries, self._recheck = every_s, quiet_tries, recheck_s
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="dhg-corridor-check", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        from dhg.live.client import get_json

        tries = 0
        while not self._stop.is_set():
            try:
                about = get_json(self._z, self._key, None, timeout_s=self._every)
            except Exception:  # no engine (yet, or restarting), or the session is closing: ask again
                tries += 1
                if tries == self._quiet_tries and self.result is None and not self._stop.is_set():
                    self._report(
                        f"note: no engine has answered {self._key} yet; the corridor is not checked until one does"
                    )
                self._stop.wait(self._every if self.result is None else self._recheck)
                continue
            try:
                why = corridor_mismatch(about, self._meta)
            except Exception as exc:  # a malformed reply or profile: say so rather than die silently
                why = f"could not check the engine's corridor ({exc})"
            if self._stop.is_set():
                return  # closing: nothing after dhg-serve's last lines
            line = f"warning: {why}" if why else "note: the engine's corridor follows this model's expert profiles"
            if line != self.result:
                self.result = line
                self._report(line)
            self._stop.wait(self._recheck)

    def close(self) -> None:
        """Stops asking and waits for the thread (at most one query's timeout)."""
        self._stop.set()
        self._thread.join(timeout=self._every + 1.0)


class AboutService:
    """Where a live session's data comes from, for a recording's dataset card: the key
    ``<prefix>/server/about`` answers (JSON) with ``dhg_version``, ``volume`` (as a card's:
    :func:`dhg.data.dataset.volume_card`, a CT's ``source`` by its file name only, since every
    station may ask and folder names can carry a patient's), ``session_config`` (what a new
    session starts with, flat: :meth:`dhg.core.session.SessionConfig.to_flat_dict`),
    ``planned_path`` (new sessions' default A and B, m), ``guidance`` (how a new session is
    guided and the laws every session runs: :attr:`dhg.core.server.Server.new_session_guidance`)
    and ``model`` (:func:`dhg.learning.model_file.model_identity` of the model this process serves,
    where other workers may join the pool; None when the model runs in other processes only,
    ``--role sim``). The reply is made once, at start."""

    def __init__(
        self,
        session: Any,
        volume: Any,
        path: Any,
        config: Any,
        *,
        guidance: dict[str, Any],
        model: Any = None,
        prefix: str = "dhg",
    ):
        from pathlib import Path

        from dhg.core.version import __version__
        from dhg.data.dataset import volume_card
        from dhg.learning.model_file import model_identity

        self.key = protocol.server_key(prefix, "about")
        described = volume_card(volume)
        if "source" in described:  # every station may ask: a CT by its file name, not its folders
            described["source"] = Path(str(described["source"])).name
        self.reply = json.dumps(
            {
                "dhg_version": __version__,
                "volume": described,
                "session_config": config.to_flat_dict(),
                "planned_path": path.to_dict(),
                "guidance": guidance,
                "model": None if model is None else model_identity(model.path, model.meta),
            }
        )
        self._queryable = session.declare_queryable(self.key, self._on_query)

    def _on_query(self, query: Any) -> None:
        try:
            query.reply(self.key, self.reply, encoding="application/json")
        except Exception:  # a session closing: the asker times out, as for any lost reply
            log.debug("server/about reply failed", exc_info=True)

    def close(self) -> None:
        """Undeclares the queryable."""
        try:
            self._queryable.undeclare()
        except Exception:
            pass


class XRayService:
    """Answers ``<prefix>/session/<id>/xray/<view>`` (view: top, front, side or ``*``) with PNG
    radiographs of that session's bone as drilled now, with the planned path drawn in."""

    def __init__(self, session: Any, server: Any, volume: Any, prefix: str = "dhg"):
        from dhg.bone.xray import auto_windows

        self.server = server
        self.volume = volume
        self.prefix = prefix
        self.windows = auto_windows(volume.xray())
        self._queryable = session.declare_queryable(protocol.session_key(prefix, "*", "xray/*"), self._on_query)

    def _on_query(self, query: Any) -> None:
        from dhg.bone.xray import render_views
        from dhg.core.path import PlannedPath
        from dhg.core.volume import XRayViews

        try:
            key = str(query.key_expr)
            sid, view = protocol.session_of(self.prefix, key), key.rsplit("/", 1)[-1]
            if sid is None:
                raise InvalidInputError(f"not a session's key: {key!r}")
            if view not in (*VIEW_NAMES, "*"):
                raise InvalidInputError(f"unknown view {view!r}: use {', '.join(VIEW_NAMES)} or *")
            info = self.server.control(sid, {"op": "info"})
            top, front, side = self.server.xray(sid)
            path = PlannedPath(np.array(info["entry_m"]), np.array(info["target_m"]))
            images = render_views(self.volume, XRayViews(top, front, side), path, windows=self.windows)
            for name, img in images.items():
                if view in ("*", name):
                    buf = io.BytesIO()
                    img.save(buf, format="PNG")
                    reply_key = protocol.session_key(self.prefix, sid, f"xray/{name}")
                    query.reply(reply_key, buf.getvalue(), encoding="image/png")
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


class BoneService:
    """What a viewer meshes. ``<prefix>/server/volume`` answers with the pristine volume (npz:
    ``labels`` (nz, ny, nx) uint8 layer ids, ``spacing_m``, ``origin_m``, ``direction``), and
    ``<prefix>/session/<id>/bone`` with that session's drilled bricks as drilled now (npz:
    ``origins`` (n, 3) uint32 voxel (i, j, k), ``material`` (n, 8, 8, 8) uint16 [k][j][i], 65535
    full; every other voxel is pristine). A brick snapshot is taken by the tick thread between
    two ticks (a copy of what the session drilled)."""

    def __init__(self, session: Any, server: Any, volume: Any, prefix: str = "dhg"):
        self.server = server
        self.prefix = prefix
        self._volume = encode_npz(
            labels=volume.labels(),
            spacing_m=np.asarray(volume.spacing_m),
            origin_m=np.asarray(volume.origin_m),
            direction=np.asarray(volume.direction),
        )
        self._queryables = [
            session.declare_queryable(protocol.server_key(prefix, "volume"), self._on_volume),
            session.declare_queryable(protocol.session_key(prefix, "*", "bone"), self._on_bone),
        ]

    def _on_volume(self, query: Any) -> None:
        try:
            if len(self._volume) > MAX_NPZ_BYTES:
                raise InvalidInputError(
                    f"the volume is {len(self._volume)} bytes compressed, over the {MAX_NPZ_BYTES} a reply may hold"
                )
            query.reply(protocol.server_key(self.prefix, "volume"), self._volume, encoding="application/octet-stream")
        except Exception as exc:
            query.reply_err(json.dumps({"error": str(exc)}))
        finally:
            query.drop()

    def _on_bone(self, query: Any) -> None:
        try:
            sid = check_session_id(protocol.session_of(self.prefix, str(query.key_expr)) or "")
            origins, material = self.server.bricks(sid)
            payload = encode_npz(origins=origins, material=material)
            if len(payload) > MAX_NPZ_BYTES:
                raise InvalidInputError(f"session {sid}'s bricks are {len(payload)} bytes, over {MAX_NPZ_BYTES}")
            query.reply(protocol.session_key(self.prefix, sid, "bone"), payload, encoding="application/octet-stream")
        except Exception as exc:  # every failure becomes an error reply, never a dead callback
            query.reply_err(json.dumps({"error": str(exc)}))
        finally:
            query.drop()

    def close(self) -> None:
        """Undeclares the queryables."""
        for q in self._queryables:
            try:
                q.undeclare()
            except Exception:
                pass
