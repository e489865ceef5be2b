"""The real-time engine on Zenoh (the native ``Server``): the 1 kHz tick thread, the comm thread
and the keys of ``docs/protocol.md``, with its settings (defined in the core)."""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Any

import numpy as np

from dhg import _bone_sim

__all__ = ["Server", "ServerSettings", "check_zenoh_runtime", "reply_schemas", "start_engine"]


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
    demonstration profiles (:mod:`dhg.learning.profiles`); None: the fixed 400 N/m."""
    session_owners: tuple[str, ...] = ()
    """Stations whose sessions (``S`` or ``S-<anything>``) are capped at ``max_sessions_per_owner``
    each (``dhg-serve --lab`` reads them from the lab file)."""
    max_sessions_per_owner: int = _SERVER["max_sessions_per_owner"]
    """Most sessions one station may hold at once (0: no cap)."""
    wait: str = _SERVER["wait"]
    """How the 1 kHz tick thread and the force publisher wait: ``"sleep"`` (idle cores stay idle),
    or ``"spin"`` (while a session is open each keeps a core at 100 %, so no wake-up latency is added
    to a force; for hosts with cores to spare and no real-time scheduling)."""
    tick_on: str = _SERVER["tick_on"]
    """Where a pose ticks its session: ``"pose"`` (the default: a pose that finds its session due
    ticks it on the Zenoh thread that received it, and the force leaves from there) or
    ``"thread"`` (every pose is handed to the tick thread and its force to the comm thread: two
    thread hand-offs per pose, the design before; for comparison)."""

    def native(self) -> dict[str, Any]:
        """The dict ``dhg._bone_sim.Server`` takes (the core's ``ServerSettings``)."""
        return asdict(self)


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
        """A session's metrics; an unknown session is an :class:`~dhg.core.errors.EngineError`."""
        return self._native.metrics(session_id)

    def control(self, session_id: str, request: dict[str, Any]) -> dict[str, Any]:
        """Applies a control request (``{"op": ...}``, ``docs/protocol.md``); returns the session info."""
        return self._native.control(session_id, request)

    def xray(self, session_id: str, timeout_s: float = 1.0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The (top, front, side) X-ray line integrals of a session's bone as drilled now."""
        return self._native.xray(session_id, timeout_s)

    def bricks(self, session_id: str, timeout_s: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
        """A session's drilled bricks as drilled now: origins (n, 3) voxel (i, j, k), uint32, and
        material (n, 8, 8, 8) [k][j][i], uint16 (65535 = full). Every other voxel is pristine."""
        return self._native.bricks(session_id, timeout_s)

    def stop(self) -> None:
        """Stops the threads and closes the engine's Zenoh session (idempotent)."""
        self._native.stop()

    @property
    def running(self) -> bool:
        """Whether the engine runs."""
        return self._native.running

    @property
    def new_session_guidance(self) -> dict[str, Any]:
        """How a new session is guided: ``mode``, ``gain``, and ``params``, the guidance laws and
        limits every session runs (:data:`dhg.core.session.GUIDANCE_DEFAULTS`' keys, with the
        server's settings applied: ``max_n`` (N), ``max_rate_n_per_s`` (N/s), ``timeout_s`` (s), the
        corridor's profile, ...)."""
        return self._native.new_session_guidance


def start_engine(
    volume: Any,
    path: Any,
    config_json5: str,
    settings: ServerSettings | None = None,
    prefix: str = "dhg",
    session_config: Any = None,
) -> Server:
    """Starts the engine on ``volume`` with ``path`` as new sessions' planned path, Zenoh
    configured by ``config_json5`` (:func:`dhg.live.zenoh_config.zenoh_config_json5`)."""
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


def check_zenoh_runtime() -> None:
    """Raises :class:`dhg.core.errors.InvalidInputError` when the ``ZENOH_RUNTIME`` environment
    variable (Zenoh's runtime threads, e.g. ``(rx: (worker_threads: 1))``) is one Zenoh cannot
    read or asks for zero threads (Zenoh would panic at this process's first session), or has
    changed since Zenoh read it; nothing when it is unset or readable. The engine's own check,
    called before any Zenoh session opens, Python's included."""
    _bone_sim.check_zenoh_runtime()


def reply_schemas() -> dict[str, dict[str, Any]]:
    """The JSON schemas of the server's replies (``metrics``, ``health``), generated from their
    Rust types by ``schemars``: the contract ``docs/protocol.md`` describes, for clients that
    validate what they receive."""
    return _bone_sim.reply_schemas()
