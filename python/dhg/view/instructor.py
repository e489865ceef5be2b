"""The instructor's page of ``dhg view``: every session on the server, with its live state and
metrics and a link to its trainee's page (:class:`dhg.view.pages.TraineePage`), and every
trainee's tip in the pristine bone. Like the trainee's page it is its own viser server.
"""

from __future__ import annotations

import html
import logging
import threading
from collections.abc import Callable
from typing import Any

import numpy as np

from dhg.view.feed import VolumeData, server_sessions
from dhg.view.scene import LAYER_NAMES, SCENE_MM_PER_M, add_whole_bone, look_at, stop_quietly, viser_server
from dhg.view.surfaces import LayerSurfaces, display_step

__all__ = ["InstructorPage"]

log = logging.getLogger("dhg.view.pages")  # one logger for both pages, under the name it always had


class InstructorPage:
    """Every session on the server, with its live state and the server's metrics, refreshed each
    second, and a link that opens its :class:`~dhg.view.pages.TraineePage`
    (``open_page(session_id)`` returns the page's URL, starting the page if need be)."""

    def __init__(
        self,
        z: Any,
        volume: VolumeData,
        port: int,
        open_page: Callable[[str], str],
        host: str = "127.0.0.1",
        prefix: str = "dhg",
        refresh_s: float = 1.0,
    ) -> None:
        from dhg.core import protocol

        self._z, self.prefix, self.open_page, self.refresh_s = z, prefix, open_page, refresh_s
        self._states: dict[str, dict[str, Any]] = {}
        self._pageless: set[str] = set()  # sessions told to have no page (told once)
        self._lock = threading.Lock()
        self.refreshes = 0
        self.sessions: list[str] = []
        self._protocol = protocol
        self._sub = z.declare_subscriber(protocol.session_key(prefix, "*", "state"), self._on_state)
        self.server = viser_server(host, port, "DHG: instructor")
        self.url = f"http://{host}:{self.server.get_port()}"
        gui = self.server.gui
        gui.configure_theme(control_width="large", dark_mode=False, show_logo=False)
        gui.add_markdown("**DHG: every session on the server** (refreshed each second; open one to watch it)")
        self._table = gui.add_html('<div id="dhg-sessions"></div>')
        # The pristine bone with every trainee's tip in it, labelled.
        surfaces = LayerSurfaces(
            volume.labels, volume.spacing_m, volume.origin_m, volume.direction, step=display_step(volume.spacing_m)
        )
        self._meshes: dict[str, Any] = {}
        add_whole_bone(self.server, surfaces, self._meshes)
        self._tips: dict[str, Any] = {}
        self.server.on_client_connect(lambda client: look_at(client, volume))
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._loop, name="view-instructor", daemon=True)
        self._thread.start()

    def _on_state(self, sample: Any) -> None:
        sid = self._protocol.session_of(self.prefix, str(sample.key_expr))
        if sid is None:
            return
        from dhg.live.session_recorder import valid_message

        try:
            m = self._protocol.decode("state", sample.payload.to_bytes())
        except ValueError:
            return
        if not valid_message("state", m):  # a NaN or a layer no layer has would stop the table
            return
        with self._lock:
            if sid in self._states or len(self._states) < 1024:  # a flood of fake ids stays bounded
                self._states[sid] = m

    def _loop(self) -> None:
        from dhg.live.client import get_json

        while not self._stop.is_set():
            try:
                ids = server_sessions(self._z, self.prefix)
                with self._lock:  # states of sessions gone: a long class's ids do not fill the 1024
                    for gone in [sid for sid in self._states if sid not in ids]:
                        del self._states[gone]
                rows = []
                for sid in ids:
                    try:
                        url: str | None = self.open_page(sid)
                    except Exception as exc:  # no page for this one (all taken): the rest still show
                        if sid not in self._pageless:  # once a session, not at every refresh
                            self._pageless.add(sid)
                            log.warning("instructor page: no page for %s: %s", sid, exc)
                        url = None
                    try:
                        met = get_json(self._z, self._protocol.session_key(self.prefix, sid, "metrics"), None, 2.0)
                    except Exception:
                        met = None
                    with self._lock:
                        st = self._states.get(sid)
                    rows.append(self._row(sid, url, st, met))
                self.sessions = ids
                self._table.content = (
                    f'<div id="dhg-sessions">{"".join(rows)}</div>'
                    if rows
                    else '<p id="dhg-sessions">No sessions on the server yet.</p>'
                )
                self._show_tips(ids)
                self.refreshes += 1
            except Exception as exc:  # the server restarting: keep the last table, try again
                log.debug("instructor page: %s", exc)
            self._stop.wait(self.refresh_s)

    @staticmethod
    def _row(sid: str, url: str | None, st: dict[str, Any] | None, met: dict[str, Any] | None) -> str:
        e = html.escape(sid)
        if st is None:
            live = "no state yet"
        else:
            f = st["features"]
            live = (
                f"{st['time_s']:.1f} s · depth {f[7] * 1e3:.1f} mm · {LAYER_NAMES.get(int(f[6]), '?')} · "
                f"{f[8]:.1f} °C · plunge {st['plunge_depth_m'] * 1e3:.1f} mm · "
                f"deviation {st['deviation_m'] * 1e3:.1f} mm"
            )
        if met:
            plunge, lateral = met["plunge_depth_m"] * 1e3, met["max_lateral_deviation_m"] * 1e3
            attempt = (
                f"{met['guidance_mode']} × {met['guidance_gain']:.2f} · this attempt: {met['records']} records, "
                f"largest plunge {plunge:.1f} mm, lateral {lateral:.1f} mm, peak {met['peak_temperature_c']:.1f} °C"
            )
        else:
            attempt = "no metrics yet"
        return (
            f'<div class="dhg-session" data-session="{e}" style="border-top:1px solid #ddd;padding:4px 0">'
            f"<b>{e}</b> "
            + (
                f'<a href="{html.escape(url)}" target="_blank" id="dhg-open-{e}">open its page</a>'
                if url is not None
                else "(no page: this viewer shows as many as it can)"
            )
            + f'<div style="font-size:85%">{live}</div><div style="font-size:85%;color:#555">{attempt}</div></div>'
        )

    def _show_tips(self, ids: list[str]) -> None:
        """Each listed session's tip (from its newest state) as a labelled dot in the bone."""
        with self._lock:
            tips = {sid: self._states[sid]["features"][3:6] for sid in ids if sid in self._states}
        sc = self.server.scene
        for sid in list(self._tips):
            if sid not in tips:
                for h in self._tips.pop(sid):
                    h.remove()
        for sid, tip in tips.items():
            p = tuple(np.asarray(tip, dtype=float) * SCENE_MM_PER_M)
            if sid in self._tips:
                for h in self._tips[sid]:
                    h.position = p
            else:
                self._tips[sid] = (
                    sc.add_icosphere(f"/tips/{sid}", radius=1.5, color=(30, 90, 200), position=p),
                    sc.add_label(f"/tips/{sid}-label", sid, position=p),
                )

    def close(self) -> None:
        """Stops the refresh, the subscription and the page's server."""
        self._stop.set()
        self._thread.join(timeout=5.0)
        try:
            self._sub.undeclare()
        except Exception:
            pass
        stop_quietly(self.server)
