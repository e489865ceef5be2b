"""``dhg view``: the live pages of one server, as one Zenoh client.

With a session id, one :class:`dhg.view.pages.TraineePage` on ``port``. Without, the
:class:`dhg.view.pages.InstructorPage` on ``port`` and a trainee page for each session it lists,
on the ports after it (started when the session first shows, kept until the viewer stops).
"""

from __future__ import annotations

import threading
from collections.abc import Sequence
from typing import Any

from dhg.view.feed import VolumeData, fetch_volume
from dhg.view.pages import InstructorPage, TraineePage

__all__ = ["MAX_PAGES", "Viewer"]

MAX_PAGES = 64
"""Trainee pages one viewer starts at most (a server holds 16 sessions by default)."""


class Viewer:
    """The pages of one server (see the module). ``connect`` are its Zenoh endpoints,
    ``zenoh_config_file`` the lab mode's client file (an instructor or station identity)."""

    def __init__(
        self,
        connect: str | Sequence[str],
        port: int = 8080,
        session_id: str | None = None,
        host: str = "127.0.0.1",
        prefix: str = "dhg",
        zenoh_config_file: str | None = None,
        frame_hz: float = 30.0,
        volume_timeout_s: float = 30.0,
    ) -> None:
        from dhg.core.protocol import check_session_id
        from dhg.live.zenoh_config import open_zenoh, zenoh_config_json5

        if session_id is not None:
            check_session_id(session_id)
        if not (0 <= port <= 65535):
            raise ValueError(f"port must be within 0..65535, got {port}")
        endpoints = [connect] if isinstance(connect, str) else list(connect)
        self.host, self.prefix, self.frame_hz = host, prefix, frame_hz
        conf = zenoh_config_json5(connect=endpoints, config_file=zenoh_config_file, mode="client")
        self._z = open_zenoh(conf)
        self._lock = threading.Lock()
        self.pages: dict[str, TraineePage] = {}
        self.instructor: InstructorPage | None = None
        try:
            self.volume: VolumeData = fetch_volume(self._z, prefix, volume_timeout_s)
            if session_id is not None:
                self.url = self._start_page(session_id, port)
            else:
                self._next_port = port + 1 if port else 0
                self.instructor = InstructorPage(self._z, self.volume, port, self.page_url, host, prefix)
                self.url = self.instructor.url
        except BaseException:
            self.close()
            raise

    def _start_page(self, session_id: str, port: int) -> str:
        page = TraineePage(self._z, session_id, self.volume, port, self.host, self.prefix, self.frame_hz)
        self.pages[session_id] = page
        return page.url

    def page_url(self, session_id: str) -> str:
        """The URL of a session's trainee page, starting it on the next free port first."""
        with self._lock:
            page = self.pages.get(session_id)
            if page is not None:
                return page.url
            if len(self.pages) >= MAX_PAGES:
                raise RuntimeError(f"this viewer already shows {MAX_PAGES} sessions")
            port = self._next_port
            url = self._start_page(session_id, port)
            if port:
                self._next_port = port + 1
            return url

    def close(self) -> None:
        """Closes every page, then the Zenoh session (idempotent)."""
        if self.instructor is not None:
            self.instructor.close()
            self.instructor = None
        for page in list(self.pages.values()):
            page.close()
        self.pages.clear()
        if self._z is not None:
            try:
                self._z.close()
            except Exception:
                pass
            self._z = None

    def __enter__(self) -> Viewer:
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()
