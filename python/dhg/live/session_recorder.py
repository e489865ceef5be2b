"""One live session recorded into a demonstrations dataset: :class:`SessionRecorder`, the
writer behind ``dhg record --session`` and each session of ``dhg record --all``
(:mod:`dhg.live.recorder`), with what both recorders share: the subscriber that recovers
messages a congested link lost, the check that a message can be true, and the flush loop.

The recorder keeps the session's 10 Hz records in memory and, every ``flush_every_s``, rewrites
its dataset folder atomically (:func:`dhg.data.dataset.write_dataset`); with ``raw`` the 1 kHz
rows wait only until their flush, written in parts (:class:`dhg.live.streams.RawParts`) that a
clean stop joins into one ``raw.parquet``.
"""

from __future__ import annotations

import json
import math
import threading
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from dhg.core import protocol
from dhg.core.errors import InvalidInputError
from dhg.core.features import FEATURE_NAMES, RECORD_COLUMNS, RECORD_INDEX, RECORD_PERIOD_S, TICK_S
from dhg.core.layers import Layer
from dhg.core.path import PlannedPath, TaskRules
from dhg.core.skill import skill_metrics
from dhg.core.version import __version__
from dhg.data.dataset import EpisodeInput, write_dataset
from dhg.data.synth import attempt_score
from dhg.live.streams import STATE_INDEX, EpisodeSplitter, RawParts, RecordingEpisode, force_jerk

__all__ = [
    "MAX_SESSION_TIME_S",
    "FlushLoop",
    "SessionRecorder",
    "recorded_subscriber",
    "server_session_ids",
    "valid_message",
]

_DRILL_ON = protocol.FLAGS["drill_on"]
_LAYER_FEATURE = FEATURE_NAMES.index("layer")
_LAYER_IDS = frozenset(float(layer) for layer in Layer)

MAX_SESSION_TIME_S = 7 * 24 * 3600.0
"""A session clock past a week (s) is not a session's: such a state is refused."""


def recorded_subscriber(z: Any, key: str, callback: Callable[[Any], None], on_miss: Callable[[int], None]) -> Any:
    """A subscriber to a recorded stream (state, guidance, ticks) that does not lose samples to a
    congested link: the server's publishers drop rather than block (so no subscriber can stall
    a session), keep the last 60 s (10 s of ticks), and announce their sequence numbers; this subscriber (a
    zenoh-ext advanced subscriber) asks for what it missed, and for the history of a session
    it joins late. ``on_miss(n)`` hears of samples it could not recover."""
    import zenoh.ext as zx

    sub = zx.declare_advanced_subscriber(
        z,
        key,
        callback,
        history=zx.HistoryConfig(detect_late_publishers=True),
        recovery=zx.RecoveryConfig(periodic_queries=None, heartbeat=True),
    )
    listener = sub.sample_miss_listener(lambda miss: on_miss(int(miss.nb)))
    return sub, listener


def valid_message(name: str, m: dict[str, Any]) -> bool:
    """Whether a decoded ``state``, ``pose`` or ``force`` message can be true: every float
    finite; a state's clock within 0..:data:`MAX_SESSION_TIME_S` and its layer feature a layer id."""
    from dhg.live.client import all_finite

    if not all_finite(m):
        return False
    if name != "state":
        return True
    layer = m["features"][_LAYER_FEATURE]
    return 0.0 <= m["time_s"] <= MAX_SESSION_TIME_S and layer in _LAYER_IDS


ABOUT_ASKS = 3
"""Flushes at which a recorder asks the server's ``about`` before it gives up (each ask waits up
to 1 s for a server that does not answer it)."""

SESSION_INFO_KEYS = (
    "guidance_mode",
    "burr_radius_m",
    "planned_breakthrough_depth_m",
    "path_layer_step_m",
    "path_layers",
)
"""The fields of the server's ``info`` reply a recording's card keeps (``session_info``): the
guidance mode and burr it was drilled with, and the planned path's layers (the gain can change
per attempt: each episode's metrics hold it as ``guidance_gain``)."""


class FlushLoop:
    """``run``: the flush loop both recorders share."""

    flush_every_s: float
    flush_errors: int = 0
    """Flushes that failed (a full disk, a folder gone, ...): what they held stays for the next."""
    last_flush_error: str = ""

    def flush(self, final: bool = False) -> Any:
        raise NotImplementedError

    def run(
        self,
        stop: threading.Event,
        duration_s: float | None = None,
        status: Callable[[float], None] | None = None,
        status_every_s: float = 5.0,
    ) -> None:
        """Flushes every ``flush_every_s`` until ``stop`` is set (or ``duration_s`` passes), then
        flushes once more, joining the 1 kHz parts. ``status(elapsed_s)`` is called every
        ``status_every_s`` (0: never)."""
        t0 = time.monotonic()
        next_status = t0 + status_every_s
        while True:
            now = time.monotonic()
            wake = now + self.flush_every_s
            if duration_s is not None:
                wake = min(wake, t0 + duration_s)
            if stop.wait(max(0.0, wake - now)):
                break
            try:
                self.flush()
            except Exception as exc:  # everything is still held: the next flush retries
                self.flush_errors += 1
                self.last_flush_error = str(exc)
            now = time.monotonic()
            if status is not None and status_every_s > 0 and now >= next_status:
                status(now - t0)
                next_status += status_every_s * (int((now - next_status) // status_every_s) + 1)
            if duration_s is not None and now - t0 >= duration_s:
                break
        self.flush(final=True)


class SessionRecorder(FlushLoop):
    """Records ``session_id`` on the server at ``connect`` into the dataset folder ``out_dir``.

    ``skill`` labels the subject (``expert`` demonstrations are what training uses). Records are
    kept in memory (a 10 Hz state takes 15 float64, twice that once its attempt's metrics are kept
    between flushes: an hour of one session about 9 MB) and ``records.parquet`` is rewritten whole
    on each flush, so a flush's cost grows with the recording (``docs/benchmarks.md``). An attempt's
    skill metrics are computed again only when it changed. With ``raw``, the 1 kHz rows wait in
    memory only until their flush (``raw_part_rows`` rows make a part).
    """

    def __init__(
        self,
        connect: str | Sequence[str],
        session_id: str,
        out_dir: str | Path,
        prefix: str = "dhg",
        subject_id: str | None = None,
        skill: str = "unknown",
        flush_every_s: float = 1.0,
        zenoh_config_file: str | None = None,
        raw: bool = False,
        raw_part_rows: int = 10_000,
        zenoh_session: Any | None = None,
        overwrite: bool = False,
    ) -> None:
        """``zenoh_session``: share an open Zenoh session instead of opening one; the recorder then
        neither subscribes (its owner feeds :meth:`on_sample`) nor closes it. ``out_dir`` must be
        new or empty unless ``overwrite``: the recorder's first flush replaces what is there (a
        recorder restarted into its folder would lose the recording before it)."""
        from dhg.live.zenoh_config import open_zenoh, zenoh_config_json5

        protocol.check_session_id(session_id)
        self.session_id = session_id
        self.out_dir = Path(out_dir)
        if not overwrite and self.out_dir.is_dir() and any(self.out_dir.iterdir()):
            raise InvalidInputError(
                f"{self.out_dir} is not empty: recording there would replace what it holds "
                "(choose another folder, or pass --overwrite)"
            )
        self.subject_id = subject_id or session_id
        self.skill = skill
        self.flush_every_s = flush_every_s
        self.keys = protocol.keys(prefix, session_id)
        self._owns_zenoh = zenoh_session is None
        if zenoh_session is None:
            endpoints = [connect] if isinstance(connect, str) else list(connect)
            cfg = zenoh_config_json5(connect=endpoints, config_file=zenoh_config_file, mode="client")
            zenoh_session = open_zenoh(cfg)
        self._z = zenoh_session
        self._lock = threading.Lock()
        self._flush_lock = threading.Lock()
        self._split = EpisodeSplitter()
        self._parts = RawParts(raw_part_rows) if raw else None
        self._next_id = 0
        self._dirty = False
        self._finished = False
        self.flushes = 0
        self.decode_errors = 0
        self.invalid_messages = 0
        """Messages that decoded but cannot be true (a NaN or infinite value, a clock before 0 or
        past :data:`MAX_SESSION_TIME_S`): counted and left out, never a reason to stop."""
        self.lost_tick_batches = 0
        """``ticks`` batches (100 ticks each) the server published that never reached the
        recorder, even after recovery."""
        self.raw_rows_without_records = 0
        """Raw rows of an attempt too short for a record (no 10 Hz state): left out."""
        self.path: PlannedPath | None = None
        self.about: dict[str, Any] | None = None
        """The server's ``about`` reply (its version, volume, session configuration, guidance and
        model, docs/protocol.md); ``None`` until it answered (a server before it never does: it is asked
        at :data:`ABOUT_ASKS` flushes at most)."""
        self._about_asks = 0
        self.session_info: dict[str, Any] | None = None
        """What the server's ``info`` reply said of the session when the recorder first reached
        it (its settings and the planned path's layers, docs/protocol.md); ``None`` until then."""
        self._subs = []
        self.lost_states = 0
        """States the server published that never reached the recorder, even after recovery."""
        if self._owns_zenoh:
            self._subs.extend(recorded_subscriber(self._z, self.keys["state"], self._on_state, self._lost))
            if raw:
                self._subs.extend(recorded_subscriber(self._z, self.keys["ticks"], self._on_ticks, self._lost_ticks))

    def _lost(self, n: int) -> None:
        self.lost_states += n

    def _lost_ticks(self, n: int) -> None:
        self.lost_tick_batches += n

    def on_sample(self, leaf: str, sample: Any) -> None:
        """Feeds one sample of this session's ``state`` or ``ticks`` key (for an owner that
        subscribes for many sessions); other leaves are ignored."""
        if leaf == "state":
            self._on_state(sample)
        elif leaf == "ticks" and self._parts is not None:
            self._on_ticks(sample)

    def _decode(self, name: str, sample: Any) -> dict[str, Any] | None:
        try:
            m = protocol.decode(name, sample.payload.to_bytes())
        except ValueError:
            self.decode_errors += 1
            return None
        if not valid_message(name, m):
            self.invalid_messages += 1
            return None
        return m

    def _on_state(self, sample: Any) -> None:
        m = self._decode("state", sample)
        if m is None:
            return
        tick = round(m["time_s"] / TICK_S) - 1  # the step that completed this record
        with self._lock:
            ep = self._split.place("state", tick)
            ep.records.append(m, drill_on=bool(m["flags"] & _DRILL_ON))
            if ep.episode_id is None:
                ep.episode_id, self._next_id = self._next_id, self._next_id + 1
            self._dirty = True

    def _on_ticks(self, sample: Any) -> None:
        try:
            t = protocol.decode_ticks(sample.payload.to_bytes())
        except ValueError:  # a wrong size or kind, or a NaN or infinite value
            self.decode_errors += 1
            return
        t = t[t["tick"] >= 1]
        if len(t) == 0:
            return
        ticks = t["tick"].astype(np.int64) - 1  # the step the force ended (see dhg.live.streams)
        rows = np.column_stack(
            [
                ticks,
                t["position_m"],
                t["orientation_wxyz"],
                (t["flags"] & _DRILL_ON) != 0,
                t["spindle_rpm"],
                t["force_n"],
                t["guidance_n"],
            ]
        ).astype(np.float64)
        drilled = t["pose_seq"] != 0  # before the session's first pose nothing was drilled
        starts = [0, *(np.flatnonzero(np.diff(ticks) <= 0) + 1)]  # a reset restarts the clock
        with self._lock:
            for a, b in zip(starts, [*starts[1:], len(ticks)], strict=True):
                ep = self._split.place("force", int(ticks[a]))
                ep.last["force"] = max(ep.last["force"], int(ticks[b - 1]))
                keep = rows[a:b][drilled[a:b]]
                if len(keep):
                    ep.rows.append(keep)
                    self._dirty = True

    @property
    def records(self) -> int:
        """Records received so far."""
        with self._lock:
            return sum(len(e.records) for e in self._split.episodes)

    @property
    def raw_rows(self) -> int:
        """1 kHz rows written so far (0 without ``raw``)."""
        return 0 if self._parts is None else self._parts.rows

    def _fetch_path(self) -> None:
        """The server's ``about`` and the session's planned path (for the skill metrics) and
        settings (for the card), asked until they answer. Best effort: without the path the
        records are still written, with empty metrics; without ``about`` the card lacks the
        volume, session configuration, guidance and model."""
        if self.about is None and self._about_asks < ABOUT_ASKS:
            self._about_asks += 1
            try:
                for r in self._z.get(self.keys["about"], timeout=1.0):
                    if r.ok is not None:
                        about = json.loads(r.ok.payload.to_bytes())
                        if isinstance(about, dict):  # in the open mode any peer may answer
                            self.about = about
            except Exception:  # as below: try again next flush
                pass
        with self._lock:
            unplaced = [ep for ep in self._split.episodes if ep.episode_id is not None and ep.path is None]
        if self.path is not None and not unplaced:
            return
        answered = False
        try:
            for r in self._z.get(self.keys["info"], timeout=1.0):
                if r.ok is not None:
                    info = json.loads(r.ok.payload.to_bytes())
                    self.path = PlannedPath(np.array(info["entry_m"]), np.array(info["target_m"]))
                    self.session_info = {k: info[k] for k in SESSION_INFO_KEYS if k in info}
                    answered = True
        except Exception:  # zenoh errors, a closed session or a malformed reply: try again next flush
            return
        if answered:  # each new attempt: the session's path as asked after it began (no answer: ask again)
            for ep in unplaced:
                ep.path = self.path

    def _take(
        self, final: bool
    ) -> tuple[
        list[tuple[RecordingEpisode, npt.NDArray[np.float64] | None]],
        list[tuple[RecordingEpisode, npt.NDArray[np.float64]]],
    ]:
        """Under the lock: the episodes with records (with a copy of their states, or ``None``
        where the last write had them all), and the raw rows now ready to write. Rows of an
        episode the states passed by without a record are dropped; an episode still waiting for
        its first record holds back its rows and every later one's (written by the next flush
        that has its record)."""
        state_at = self._split.at("state")
        ready: list[tuple[RecordingEpisode, npt.NDArray[np.float64]]] = []
        waiting = False
        for i, ep in enumerate(self._split.episodes):
            if ep.episode_id is None:
                if i < state_at or final:
                    self.raw_rows_without_records += sum(len(r) for r in ep.rows)
                    ep.rows = []
                    continue
                waiting = any(e.rows for e in self._split.episodes[i:])
                break
            if ep.rows:
                ready.append((ep, np.concatenate(ep.rows)))
                ep.rows = []
        self._dirty = waiting
        episodes = [
            (ep, None if ep.written is not None and len(ep.written[1]) == len(ep.records) else ep.records.array())
            for ep in self._split.episodes
            if ep.episode_id is not None
        ]
        return episodes, ready

    def flush(self, final: bool = False) -> bool:
        """Writes everything received so far (atomically) if anything new arrived; returns whether
        it wrote. ``final`` also joins the 1 kHz parts into one ``raw.parquet``; the recorder
        writes nothing after that."""
        with self._flush_lock:
            with self._lock:
                joining = final and self._parts is not None and self._parts.rows > 0
                if self._finished or not (self._dirty or joining):
                    return False
                self._dirty = False
                episodes, ready = self._take(final)
            if self._parts is not None:
                for ep, arr in ready:
                    force_jerk(ep, arr)
                    assert ep.episode_id is not None
                    self._parts.add(ep.episode_id, arr)
            try:
                self._write(episodes, final)
            except BaseException:
                with self._lock:
                    self._dirty = True  # everything is still held: the next flush retries
                raise
            self._finished = final
            return True

    def _write(self, episodes: list[tuple[RecordingEpisode, npt.NDArray[np.float64] | None]], final: bool) -> None:
        self._fetch_path()
        rules = TaskRules()
        inputs = []
        for attempt, (ep, states) in enumerate(episodes):
            records, metrics = self._episode(ep, states, rules)
            inputs.append(EpisodeInput(self.subject_id, self.skill, attempt, records, dict(metrics)))
        if inputs:  # the paper trains on each subject's best attempt
            scored = [i for i, ep in enumerate(inputs) if "completed" in ep.metrics]
            best = min(scored, key=lambda i: attempt_score(inputs[i].metrics)) if scored else len(inputs) - 1
            inputs[best].best_of_subject = True
        card: dict[str, Any] = {
            "generator": {
                "name": "dhg record (live session)",
                "dhg_version": __version__,
                "session": self.session_id,
                "flushed_at_unix_s": time.time(),
            },
            "task_rules": rules.to_dict(),
        }
        if self.session_info is not None:
            card["session_info"] = self.session_info
        if self.about is not None:
            card["generator"]["server_dhg_version"] = self.about.get("dhg_version")
            for key in ("volume", "session_config", "guidance", "model"):
                if isinstance(self.about.get(key), dict):
                    card[key] = self.about[key]
            if "model" in self.about and self.about["model"] is None:
                card["model"] = None  # the server's model runs in other processes (--role sim)
        parts = []
        if self._parts is not None:
            parts = self._parts.joined(self.out_dir) if final else self._parts.parts()
            card["generator"]["raw"] = {
                "rows": self._parts.rows,
                "lost_batches": self.lost_tick_batches,
                "rows_without_records": self.raw_rows_without_records,
            }
        if self.path is not None:
            card["planned_path"] = self.path.to_dict()
        write_dataset(self.out_dir, inputs, card, overwrite=True, raw_parts=parts)
        if self._parts is not None and not final:
            self._parts.written(parts)
        self.flushes += 1

    def _episode(
        self, ep: RecordingEpisode, states: npt.NDArray[np.float64] | None, rules: TaskRules
    ) -> tuple[npt.NDArray[np.float64], dict[str, Any]]:
        """An episode's records and skill metrics from its ``states`` (:data:`dhg.live.streams.STATE_COLUMNS`;
        ``None``: those of the last write). They are the last write's while the states, the path
        and the 1 kHz force count are the same: a long recording's ended attempts are not
        computed again at every flush (``bench_recorder_flush.py``)."""
        if states is None:
            states = ep.written[1]
        path = ep.path if ep.path is not None else self.path
        if ep.written is not None:
            (n, seen_path, jerks), _, records, metrics = ep.written
            if n == len(states) and seen_path is path and jerks == ep.jerk_count:
                return records, metrics
        records, last = states[:, : len(RECORD_COLUMNS)], states[-1]
        metrics = {}
        if path is not None:
            metrics = skill_metrics(
                records,
                path,
                rules,
                final_tip_m=records[-1, RECORD_INDEX["tip_x_m"] : RECORD_INDEX["tip_x_m"] + 3],
                drilling_s=float(np.count_nonzero(records[:, RECORD_INDEX["drill_on"]] > 0.5)) * RECORD_PERIOD_S,
                plunge_depth_m=float(states[:, STATE_INDEX["plunge_depth_m"]].max()),
                peak_temperature_c=float(last[STATE_INDEX["peak_temperature_c"]]),
                time_above_47_s=float(last[STATE_INDEX["time_above_47_s"]]),
            )
            if ep.jerk_count:  # the device force at 1 kHz, as a virtual surgeon's raw stream gives it
                metrics["force_jerk_n_per_s"] = math.sqrt(ep.jerk_sum / ep.jerk_count)
        # The gain the attempt was drilled at (a fading schedule sets it per attempt; 0 on a probe).
        metrics["guidance_gain"] = float(last[STATE_INDEX["guidance_gain"]])
        ep.written = ((len(states), path, ep.jerk_count), states, records, metrics)
        return records, metrics

    @property
    def attempts(self) -> int:
        """Attempts (episodes) with at least one record so far."""
        with self._lock:
            return self._next_id

    def server_sessions(self, timeout_s: float = 1.0) -> list[str] | None:
        """The session ids the server has now (from its health report), or None if it does not
        answer: tells a user waiting on a mistyped id what is there."""
        return server_session_ids(self._z, self.keys["health"], timeout_s)

    def close(self) -> None:
        """Closes the Zenoh session if it opened it (call :meth:`flush` first to keep the last
        records)."""
        if not self._owns_zenoh:
            return
        try:
            self._z.close()
        except Exception:
            pass


def server_session_ids(z: Any, health_key: str, timeout_s: float) -> list[str] | None:
    """The session ids the server lists in its health report (``health_key``), or None if it does
    not answer within ``timeout_s`` (s)."""
    try:
        for r in z.get(f"{health_key}?window=1", timeout=timeout_s):
            if r.ok is not None:
                return list(json.loads(r.ok.payload.to_bytes()).get("session_ids", []))
    except Exception:  # no server, a closed session or a malformed reply
        pass
    return None
