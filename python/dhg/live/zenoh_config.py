"""Zenoh configurations and sessions for every DHG process (server roles, clients, recorders):
one place that decides scouting, endpoints and the transport's message-size cap."""

from __future__ import annotations

import json
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from dhg.core.errors import InvalidInputError, TransportError

__all__ = [
    "CLIENT_MAX_MESSAGE_BYTES",
    "SERVER_MAX_MESSAGE_BYTES",
    "open_zenoh",
    "zenoh_config_json5",
    "zenoh_user",
]

SERVER_MAX_MESSAGE_BYTES = 8 * 1024 * 1024
"""What a server process (engine, model and X-ray services) accepts as one Zenoh message, at the
transport, so that a 100 MB put is dropped as it arrives instead of being reassembled first
(Zenoh's default cap is 1 GiB). The largest messages a server handles are the X-ray PNGs it
sends, which pass through the engine when it routes them: 40–80 KB each for the phantom, about 1 MB
for an incompressible 1024 × 1024 view; every other message is under 4 KB."""
CLIENT_MAX_MESSAGE_BYTES = 16 * 1024 * 1024
"""The same cap for clients (the X-ray PNGs are the largest replies they receive)."""
_ZENOH_DEFAULT_MAX_MESSAGE = 2**30


def zenoh_config_json5(
    listen: Sequence[str] = (),
    connect: Sequence[str] = (),
    config_file: str | Path | None = None,
    mode: str = "peer",
    max_message_bytes: int = CLIENT_MAX_MESSAGE_BYTES,
) -> str:
    """A Zenoh configuration (JSON5 text) for both the Rust and the Python sessions.

    Zenoh's default transport, not the low-latency one: ``docs/decisions/0011-default-zenoh-transport.md``.
    Without ``config_file``, multicast scouting is off, so that only the given endpoints connect
    (several servers on one host or network never join each other by accident). Endpoints look like
    ``tcp/127.0.0.1:7447``. Messages larger than ``max_message_bytes`` are dropped by the
    transport before they are reassembled (``transport/link/rx/max_message_size``), unless the
    file sets its own cap.
    """
    cap = json.dumps(int(max_message_bytes))
    if config_file is not None:
        import zenoh

        try:
            cfg = zenoh.Config.from_file(str(config_file))
            cfg.insert_json5("mode", json.dumps(mode))
            if listen or mode == "client":  # a client never listens (the file may name the server's port)
                cfg.insert_json5("listen/endpoints", json.dumps(list(listen)))
            if connect:
                cfg.insert_json5("connect/endpoints", json.dumps(list(connect)))
            if json.loads(cfg.get_json("transport/link/rx/max_message_size")) == _ZENOH_DEFAULT_MAX_MESSAGE:
                cfg.insert_json5("transport/link/rx/max_message_size", cap)
        except Exception as exc:  # zenoh raises its own ZError
            raise InvalidInputError(f"cannot read the zenoh config {config_file}: {exc}") from None
        return str(cfg)  # the whole configuration, as JSON
    conf: dict[str, Any] = {
        "scouting": {"multicast": {"enabled": False}},
        "mode": mode,
        "transport": {"link": {"rx": {"max_message_size": int(max_message_bytes)}}},
    }
    if listen:
        conf["listen"] = {"endpoints": list(listen)}
    if connect:
        conf["connect"] = {"endpoints": list(connect)}
    return json.dumps(conf)


def open_zenoh(config_json5: str) -> Any:
    """Opens a Python Zenoh session from :func:`zenoh_config_json5` text.

    Raises :class:`InvalidInputError` when Zenoh cannot use the ``ZENOH_RUNTIME`` environment
    variable (:func:`dhg.core.server.check_zenoh_runtime`), and :class:`TransportError` when the
    session does not open."""
    import zenoh

    from dhg.core.server import check_zenoh_runtime

    check_zenoh_runtime()
    try:
        return zenoh.open(zenoh.Config.from_json5(config_json5))
    except Exception as exc:  # zenoh.ZError
        raise TransportError(f"cannot open a zenoh session: {exc}") from None
    except BaseException as exc:  # pyo3's PanicException derives from BaseException
        if type(exc).__name__ != "PanicException":
            raise
        raise TransportError(f"cannot open a zenoh session: Zenoh panicked: {exc}") from None


def zenoh_user(config: str | Path | None) -> str | None:
    """The user name of a Zenoh config's user/password authentication, if it has one."""
    if config is None:
        return None
    import zenoh

    try:
        user = json.loads(zenoh.Config.from_file(str(config)).get_json("transport/auth/usrpwd/user"))
    except Exception:  # unreadable files are reported when the session opens
        return None
    return user if isinstance(user, str) and user else None
