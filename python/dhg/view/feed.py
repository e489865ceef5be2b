"""What a viewer hears of the server: one session's live streams and queries, and the volume.

A viewer is one more Zenoh client. It subscribes to a session's ``force``, ``pose``, ``state``
and ``guidance`` keys and asks the read-only ``bone``, ``xray``, ``metrics`` and ``info``
queryables (``docs/protocol.md``). Nothing here blocks the server: its publishers drop rather
than wait for a slow subscriber, and the bone query copies the session's drilled bricks between
two ticks. Messages that cannot be true (NaN, infinite) are counted and never drawn.
"""

from __future__ import annotations

import threading
from collections import deque
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from dhg.core import protocol
from dhg.core.volume import VIEW_NAMES
from dhg.live.client import all_finite, get_json, get_replies
from dhg.live.services import decode_npz

__all__ = ["SessionFeed", "VolumeData", "fetch_volume", "server_sessions"]

HISTORY_S = 20.0
"""The timeline's length (s)."""


@dataclass(frozen=True)
class VolumeData:
    """The pristine volume as the server serves it (``<prefix>/server/volume``)."""

    labels: npt.NDArray[np.uint8]
    """Layer ids, (nz, ny, nx)."""
    spacing_m: npt.NDArray[np.float64]
    origin_m: npt.NDArray[np.float64]
    direction: npt.NDArray[np.float64]


def fetch_volume(z: Any, prefix: str = "dhg", timeout_s: float = 10.0) -> VolumeData:
    """The server's volume; raises :class:`dhg.core.errors.TransportError` without an answer."""
    ((_, payload),) = get_replies(z, protocol.server_key(prefix, "volume"), None, timeout_s)[:1]
    a = decode_npz(payload)
    return VolumeData(a["labels"], a["spacing_m"], a["origin_m"], a["direction"])


def server_sessions(z: Any, prefix: str = "dhg", timeout_s: float = 2.0) -> list[str]:
    """The session ids the server lists in its health report."""
    return list(get_json(z, protocol.server_key(prefix, "health") + "?window=1", None, timeout_s)["session_ids"])


class SessionFeed:
    """One session's streams, kept for a page: the newest force, pose and guidance, the last
    :data:`HISTORY_S` of states, and the states of the attempt under way and of the one before
    (a ``reset`` restarts the session's clock; that ends an attempt)."""

    def __init__(self, z: Any, session_id: str, prefix: str = "dhg") -> None:
        self.session_id = protocol.check_session_id(session_id)
        self.prefix = prefix
        self.keys = protocol.keys(prefix, self.session_id)
        self._z = z
        self._lock = threading.Lock()
        self.force: dict[str, Any] | None = None
        self.pose: dict[str, Any] | None = None
        self.guidance: dict[str, Any] | None = None
        self.state: dict[str, Any] | None = None
        self.timeline: deque[dict[str, Any]] = deque(maxlen=int(HISTORY_S * 10) + 1)
        self.attempt: list[dict[str, Any]] = []
        """States of the attempt under way (at most an hour of them)."""
        self.finished: list[dict[str, Any]] = []
        """States of the attempt before it (empty until a reset)."""
        self.attempts_finished = 0
        self.forces = self.poses = self.states = 0
        self.invalid = 0
        """Messages that could not be decoded or held a NaN or infinite value."""
        # The server's view streams: the newest force and pose 50-60 times a second, not the two
        # 1 kHz streams (taking those in and dropping most cost the viewer three quarters of its CPU).
        self._subs = [
            z.declare_subscriber(self.keys["view/force"], lambda s: self._on("force", s)),
            z.declare_subscriber(self.keys["view/pose"], lambda s: self._on("pose", s)),
            z.declare_subscriber(self.keys["state"], lambda s: self._on("state", s)),
            z.declare_subscriber(self.keys["guidance"], lambda s: self._on("guidance", s)),
        ]

    def _on(self, name: str, sample: Any) -> None:
        try:
            m = protocol.decode(name, sample.payload.to_bytes())
        except ValueError:
            self.invalid += 1
            return
        if not all_finite(m):
            self.invalid += 1
            return
        with self._lock:
            if name == "force":
                self.force, self.forces = m, self.forces + 1
            elif name == "pose":
                self.pose, self.poses = m, self.poses + 1
            elif name == "guidance":
                self.guidance = m
            else:
                self._on_state(m)

    def _on_state(self, m: dict[str, Any]) -> None:
        if self.attempt and m["time_s"] < self.attempt[-1]["time_s"]:  # the clock restarted: a reset
            self.finished, self.attempt = self.attempt, []
            self.attempts_finished += 1
            self.timeline.clear()
        if len(self.attempt) < 36_000:
            self.attempt.append(m)
        # What the hand felt at this record: the newest device force (the 50-60 Hz view stream),
        # and its guidance share; the state's own force feature is the bone's feedback alone.
        f = self.force
        self.timeline.append(
            m
            | {
                "hand_force_n": float(np.linalg.norm(f["force_n"])) if f else 0.0,
                "guidance_share_n": float(np.linalg.norm(f["guidance_n"])) if f else 0.0,
            }
        )
        self.state, self.states = m, self.states + 1

    def snapshot(self) -> dict[str, Any]:
        """The newest force, pose, guidance and state (any may be None), under the lock."""
        with self._lock:
            return {"force": self.force, "pose": self.pose, "guidance": self.guidance, "state": self.state}

    def timeline_states(self) -> list[dict[str, Any]]:
        """The last :data:`HISTORY_S` of states, oldest first."""
        with self._lock:
            return list(self.timeline)

    def attempt_states(self, finished: bool = False) -> list[dict[str, Any]]:
        """The states of the attempt under way, or of the one before it."""
        with self._lock:
            return list(self.finished if finished else self.attempt)

    # -- queries ---------------------------------------------------------------------------
    def info(self, timeout_s: float = 2.0) -> dict[str, Any]:
        """The session's info (its planned path, burr, guidance): its read-only ``info`` key."""
        return get_json(self._z, self.keys["info"], None, timeout_s)

    def metrics(self, timeout_s: float = 2.0) -> dict[str, Any]:
        """The server's skill metrics of the attempt under way (``docs/protocol.md``)."""
        return get_json(self._z, self.keys["metrics"], None, timeout_s)

    def bricks(self, timeout_s: float = 2.0) -> tuple[np.ndarray, np.ndarray]:
        """The session's drilled bricks now: origins (n, 3) voxel (i, j, k), material (n, 8, 8, 8)."""
        ((_, payload),) = get_replies(
            self._z, protocol.session_key(self.prefix, self.session_id, "bone"), None, timeout_s
        )[:1]
        a = decode_npz(payload)
        return a["origins"], a["material"]

    def xray(self, view: str, timeout_s: float = 5.0) -> bytes:
        """One PNG radiograph (``top``, ``front`` or ``side``) of the bone as drilled now."""
        if view not in VIEW_NAMES:
            raise ValueError(f"unknown view {view!r}: use {', '.join(VIEW_NAMES)}")
        ((_, png),) = get_replies(self._z, f"{self.keys['xray']}/{view}", None, timeout_s)[:1]
        return png

    def close(self) -> None:
        """Undeclares the subscribers (the Zenoh session stays open: its owner closes it)."""
        for s in self._subs:
            try:
                s.undeclare()
            except Exception:  # the session may already be closed
                pass
        self._subs = []
