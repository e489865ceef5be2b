"""Recording a live session into a demonstrations dataset (``dhg record``).

The recorder subscribes to one session's 10 Hz state stream (the nine features, drill status,
temperatures), so it records whoever drives the session, a person at a haptic device or a
virtual trainee, without touching the session itself. With ``raw`` it also keeps the 1 kHz
stream (``raw.parquet``) from the server's ``ticks`` batches: ten a second, each with every
tick's pose, force and guidance share, which a recorder behind a congested link recovers from
the server's cache as it does the states. Every ``flush_every_s`` it rewrites the dataset folder
atomically (:func:`dhg.data.dataset.write_dataset`): a stop at any moment (Ctrl-C, the server or the
recorder crashing) leaves the last complete flush on disk, at most one flush old. The 1 kHz
stream is written in parts of 10 s that later flushes hard-link instead of rewriting, and
joined into one ``raw.parquet`` at a clean stop.

A reset of the session's bone (its clock restarts) starts a new episode (attempt) of the same
subject (:class:`dhg.live.streams.EpisodeSplitter`).

One session's recorder, :class:`SessionRecorder`, is in :mod:`dhg.live.session_recorder` (with
:func:`valid_message` and :data:`MAX_SESSION_TIME_S`, re-exported here); this module holds
:class:`AllSessionsRecorder`, which records every session of a server, and its waiting room for
session ids the server has not yet confirmed.
"""

from __future__ import annotations

import threading
from collections import deque
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from dhg.core import protocol
from dhg.live.session_recorder import (
    MAX_SESSION_TIME_S,
    FlushLoop,
    SessionRecorder,
    recorded_subscriber,
    valid_message,
)
from dhg.live.session_recorder import server_session_ids as _server_sessions

__all__ = ["MAX_SESSION_TIME_S", "AllSessionsRecorder", "SessionRecorder", "recorded_subscriber", "valid_message"]

PENDING_IDS = 64
""":class:`AllSessionsRecorder`: unconfirmed session ids held at once, awaiting the server's word."""
PENDING_PER_ID = 600
"""Messages held per unconfirmed id (a minute of 10 Hz states): older ones make way."""
PENDING_PER_ID_RAW = 1200
"""The same with ``raw``: a minute of a session's states and ``ticks`` batches, so a server slow
to confirm a new session (a loaded machine) costs none of its start."""
PENDING_TOTAL = 100_000
"""Messages held over all unconfirmed ids at once: a flood of fake ids cannot grow the memory
past this; a message that does not fit is counted in ``unconfirmed_messages``."""


class AllSessionsRecorder(FlushLoop):
    """Records every session on the server at ``connect``, each into ``out_root/<session id>`` as
    its own dataset (:class:`SessionRecorder`): a class of trainees needs one recorder, and nobody
    has to know the session ids beforehand. A session is recorded once the server confirms it
    (its health report lists the id): messages under ids the server does not have (any peer can
    put on any key in open mode) make no folder. Until then its messages wait, at most
    :data:`PENDING_PER_ID` (:data:`PENDING_PER_ID_RAW` with ``raw``) for each of at most
    :data:`PENDING_IDS` ids and :data:`PENDING_TOTAL` in all; ids the server still
    does not list at the second check after their first message are dropped and counted
    (:attr:`refused_ids`, :attr:`unconfirmed_messages`). ``on_new_session(session_id, folder)``
    is called for each session recorded."""

    def __init__(
        self,
        connect: str | Sequence[str],
        out_root: str | Path,
        prefix: str = "dhg",
        skill: str = "unknown",
        flush_every_s: float = 1.0,
        zenoh_config_file: str | None = None,
        raw: bool = False,
        on_new_session: Callable[[str, Path], None] | None = None,
        confirm_every_s: float = 0.25,
    ) -> None:
        from dhg.live.zenoh_config import open_zenoh, zenoh_config_json5

        self.out_root = Path(out_root)
        self._folders: set[Path] = set()  # the folders this recorder writes
        self.prefix, self.skill, self.raw = prefix, skill, raw
        self.flush_every_s = flush_every_s
        self.on_new_session = on_new_session
        self.refused_ids = 0
        """Ids refused: not a valid session id, or never confirmed by the server."""
        self.unconfirmed_messages = 0
        """Messages under ids that were never confirmed (or that did not fit the waiting room)."""
        self.flush_errors = 0
        """Flushes of one session that failed (the others, and later flushes, go on)."""
        self.last_flush_error = ""
        self._health_key = protocol.keys(prefix, "x")["health"]
        endpoints = [connect] if isinstance(connect, str) else list(connect)
        self._z = open_zenoh(zenoh_config_json5(connect=endpoints, config_file=zenoh_config_file, mode="client"))
        self._lock = threading.Lock()
        self.sessions: dict[str, SessionRecorder] = {}
        self._pending: dict[str, tuple[int, deque[tuple[str, Any]]]] = {}  # id -> (checks seen, samples)
        self._pending_per_id = PENDING_PER_ID_RAW if raw else PENDING_PER_ID
        self._pending_total = 0
        self._refused: set[str] = set()
        self._wake = threading.Event()
        self._stop = threading.Event()
        self._confirmer = threading.Thread(target=self._confirm_loop, args=(confirm_every_s,), daemon=True)
        self._confirmer.start()
        self.lost_tick_batches = 0
        """``ticks`` batches that never reached the recorder, even after recovery."""
        self.lost_states = 0
        """States the server published that never reached the recorder, even after recovery."""
        self._subs: list[Any] = list(
            recorded_subscriber(self._z, protocol.session_key(prefix, "*", "state"), self._on_sample, self._lost)
        )
        if raw:
            self._subs.extend(
                recorded_subscriber(
                    self._z, protocol.session_key(prefix, "*", "ticks"), self._on_sample, self._lost_ticks
                )
            )

    def _on_sample(self, sample: Any) -> None:
        key = str(sample.key_expr)
        session_id = protocol.session_of(self.prefix, key) or ""
        leaf = key[len(protocol.session_key(self.prefix, session_id)) + 1 :] if session_id else ""
        rec = self.sessions.get(session_id)
        if rec is not None:
            rec.on_sample(leaf, sample)
            return
        with self._lock:
            rec = self.sessions.get(session_id)
            if rec is None:
                if session_id in self._refused:
                    self.unconfirmed_messages += 1
                    return
                try:
                    protocol.check_session_id(session_id)
                except ValueError:
                    self.refused_ids += 1
                    self._remember_refused(session_id)
                    return
                waiting = self._pending.get(session_id)
                if waiting is None:
                    if len(self._pending) >= PENDING_IDS:
                        self.unconfirmed_messages += 1
                        return
                    waiting = self._pending[session_id] = (0, deque(maxlen=self._pending_per_id))
                    self._wake.set()
                held = waiting[1]
                if len(held) == held.maxlen:
                    self.unconfirmed_messages += 1  # the oldest makes way
                elif self._pending_total >= PENDING_TOTAL:
                    self.unconfirmed_messages += 1
                    return
                else:
                    self._pending_total += 1
                held.append((leaf, sample))
                return
        rec.on_sample(leaf, sample)

    def _lost(self, n: int) -> None:
        self.lost_states += n

    def _lost_ticks(self, n: int) -> None:
        self.lost_tick_batches += n

    def _remember_refused(self, session_id: str) -> None:
        if len(self._refused) >= 10_000:  # bounded: a flood of fresh ids only costs a lookup each
            self._refused.clear()
        self._refused.add(session_id)

    def _confirm_loop(self, every_s: float) -> None:
        while not self._stop.is_set():
            self._wake.wait(every_s)
            self._wake.clear()
            if self._pending and not self._stop.is_set():
                self.confirm()

    def _free_folder(self, sid: str) -> Path:
        """The folder of session ``sid``'s dataset: ``<out>/<sid>``, or ``<sid>-2``, ``-3``, ... where
        that holds a recording already (a recorder restarted into the same ``--out``, or a session
        id used again): nothing recorded before is replaced."""
        folder, k = self.out_root / sid, 1
        while folder.is_dir() and any(folder.iterdir()) or folder in self._folders:
            k += 1
            folder = self.out_root / f"{sid}-{k}"
        self._folders.add(folder)
        return folder

    def confirm(self, timeout_s: float = 1.0) -> int:
        """Asks the server which sessions it has; starts recording every waiting one it lists
        (with the messages it sent meanwhile) and drops those it did not list twice. Returns how
        many it started. Runs by itself every ``confirm_every_s`` while ids wait."""
        listed = _server_sessions(self._z, self._health_key, timeout_s)
        if listed is None:
            return 0  # no answer: keep waiting (the server may be restarting)
        started: list[SessionRecorder] = []
        with self._lock:
            for sid, (checks, samples) in list(self._pending.items()):
                if sid in listed:
                    rec = SessionRecorder(
                        (),
                        sid,
                        self._free_folder(sid),
                        self.prefix,
                        skill=self.skill,
                        raw=self.raw,
                        zenoh_session=self._z,
                    )
                    for leaf, sample in samples:
                        rec.on_sample(leaf, sample)
                    self.sessions[sid] = rec
                    del self._pending[sid]
                    self._pending_total -= len(samples)
                    started.append(rec)
                elif checks >= 1:
                    self.refused_ids += 1
                    self.unconfirmed_messages += len(samples)
                    self._remember_refused(sid)
                    del self._pending[sid]
                    self._pending_total -= len(samples)
                else:
                    self._pending[sid] = (checks + 1, samples)
        if self.on_new_session is not None:
            for rec in started:
                self.on_new_session(rec.session_id, rec.out_dir)
        return len(started)

    @property
    def records(self) -> int:
        """Records received so far, over all sessions."""
        return sum(r.records for r in list(self.sessions.values()))

    @property
    def invalid_messages(self) -> int:
        """Messages of recorded sessions that could not be true (see :class:`SessionRecorder`)."""
        return sum(r.invalid_messages for r in list(self.sessions.values()))

    def flush(self, final: bool = False) -> int:
        """Flushes every session (see :meth:`SessionRecorder.flush`); returns how many wrote."""
        if final and self._pending:
            self.confirm()
        wrote = 0
        for rec in list(self.sessions.values()):
            try:  # one session's trouble (a full disk for its folder, ...) must not stop the class's
                wrote += bool(rec.flush(final))
            except Exception as exc:
                self.flush_errors += 1
                self.last_flush_error = f"{rec.session_id}: {exc}"
        return wrote

    def close(self) -> None:
        """Closes the Zenoh session (call :meth:`flush` first)."""
        self._stop.set()
        self._wake.set()
        self._confirmer.join(timeout=5.0)
        try:
            self._z.close()
        except Exception:
            pass
