"""Recording a live session into a demonstrations dataset (``dhg record``).

The recorder subscribes to one session's 10 Hz state stream (the nine features, drill status,
temperatures), so it records whoever drives the session, a person at a haptic device or a
virtual trainee, without touching the session itself. Every ``flush_every_s`` it rewrites the
dataset folder atomically (:func:`dhg.dataset.write_dataset`): a stop at any moment (Ctrl-C, the
server or the recorder crashing) leaves the last complete flush on disk, at most one flush old.

A reset of the session's bone (its clock restarts) starts a new episode (attempt) of the same
subject.
"""

from __future__ import annotations

import json
import threading
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from dhg import protocol
from dhg.dataset import EpisodeInput, write_dataset
from dhg.surgeons import skill_metrics
from dhg.synth import attempt_score
from dhg.task import PlannedPath, TaskRules
from dhg.trainee import state_records

__all__ = ["SessionRecorder"]


class SessionRecorder:
    """Records ``session_id`` on the server at ``connect`` into the dataset folder ``out_dir``.

    ``skill`` labels the subject (``expert`` demonstrations are what training uses). Records are
    kept in memory (about 100 bytes per 10 Hz record, so hours fit easily) and the whole dataset is
    rewritten on each flush.
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
    ) -> None:
        from dhg.serve import open_zenoh, zenoh_config_json5

        protocol.check_session_id(session_id)
        self.session_id = session_id
        self.out_dir = Path(out_dir)
        self.subject_id = subject_id or session_id
        self.skill = skill
        self.flush_every_s = flush_every_s
        self.keys = protocol.keys(prefix, session_id)
        endpoints = [connect] if isinstance(connect, str) else list(connect)
        self._z = open_zenoh(zenoh_config_json5(connect=endpoints, config_file=zenoh_config_file, mode="client"))
        self._lock = threading.Lock()
        self._episodes: list[list[dict[str, Any]]] = []
        self._dirty = False
        self.flushes = 0
        self.decode_errors = 0
        self.path: PlannedPath | None = None
        self._sub = self._z.declare_subscriber(self.keys["state"], self._on_state)

    def _on_state(self, sample: Any) -> None:
        try:
            m = protocol.decode("state", sample.payload.to_bytes())
        except ValueError:
            self.decode_errors += 1
            return
        with self._lock:
            eps = self._episodes
            if not eps or (eps[-1] and m["time_s"] < eps[-1][-1]["time_s"] - 1e-9):
                eps.append([])  # the first record, or the session was reset
            eps[-1].append(m)
            self._dirty = True

    @property
    def records(self) -> int:
        """Records received so far."""
        with self._lock:
            return sum(len(e) for e in self._episodes)

    def _fetch_path(self) -> None:
        """The session's planned path (for the skill metrics), asked once it answers. Best effort:
        without it the records are still written, with empty metrics."""
        if self.path is not None:
            return
        try:
            for r in self._z.get(self.keys["control"], payload=b'{"op":"info"}', timeout=1.0):
                if r.ok is not None:
                    info = json.loads(r.ok.payload.to_bytes())
                    self.path = PlannedPath(np.array(info["entry_m"]), np.array(info["target_m"]))
        except Exception:  # zenoh errors, a closed session or a malformed reply: try again next flush
            pass

    def flush(self) -> bool:
        """Writes everything received so far (atomically) if anything new arrived; returns whether
        it wrote."""
        with self._lock:
            if not self._dirty:
                return False
            episodes = [list(e) for e in self._episodes if e]
            self._dirty = False
        self._fetch_path()
        rules = TaskRules()
        inputs = []
        for attempt, states in enumerate(episodes):
            records = state_records(states)
            last = states[-1]
            metrics: dict[str, Any] = {}
            if self.path is not None:
                metrics = skill_metrics(
                    records,
                    self.path,
                    rules,
                    final_tip_m=records[-1, 4:7],
                    drilling_s=float(np.count_nonzero(records[:, 10] > 0.5)) * 0.1,
                    plunge_depth_m=max(s["plunge_depth_m"] for s in states),
                    peak_temperature_c=last["peak_temperature_c"],
                    time_above_47_s=last["time_above_47_s"],
                )
            inputs.append(EpisodeInput(self.subject_id, self.skill, attempt, records, metrics))
        if inputs:  # the paper trains on each subject's best attempt
            scored = [i for i, ep in enumerate(inputs) if ep.metrics]
            best = min(scored, key=lambda i: attempt_score(inputs[i].metrics)) if scored else len(inputs) - 1
            inputs[best].best_of_subject = True
        card: dict[str, Any] = {
            "generator": {
                "name": "dhg record (live session)",
                "session": self.session_id,
                "flushed_at_unix_s": time.time(),
            },
        }
        if self.path is not None:
            card["planned_path"] = self.path.to_dict()
        write_dataset(self.out_dir, inputs, card, overwrite=True)
        self.flushes += 1
        return True

    def run(self, stop: threading.Event, duration_s: float | None = None) -> None:
        """Flushes every ``flush_every_s`` until ``stop`` is set (or ``duration_s`` passes), then
        flushes once more."""
        t_end = None if duration_s is None else time.monotonic() + duration_s
        while not stop.wait(self.flush_every_s):
            self.flush()
            if t_end is not None and time.monotonic() >= t_end:
                break
        self.flush()

    def close(self) -> None:
        """Closes the Zenoh session (call :meth:`flush` first to keep the last records)."""
        try:
            self._z.close()
        except Exception:
            pass
