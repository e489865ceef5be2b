"""The browser pages of ``dhg view``: a trainee's live bone, drill and X-rays (:class:`TraineePage`),
and the instructor's list of every session (:class:`InstructorPage`, in :mod:`dhg.view.instructor`
and re-exported here). Each page is its own viser server (viser serves one page per port);
``docs/viewer.md`` says why viser. What both pages draw with is in :mod:`dhg.view.scene`.

The 3D scene is drawn in millimetres (world metres × :data:`SCENE_MM_PER_M`), in the volume's
world frame with +z up.
"""

from __future__ import annotations

import html
import io
import logging
import threading
import time
from typing import Any

import numpy as np

from dhg.core.features import FEATURE_INDEX
from dhg.core.session import FADING_DEFAULTS, ThermalParams
from dhg.core.volume import VIEW_NAMES
from dhg.view.feed import SessionFeed, VolumeData
from dhg.view.instructor import InstructorPage
from dhg.view.scene import LAYER_NAMES, SCENE_MM_PER_M, add_bone_piece, add_whole_bone, along, look_at, stop_quietly
from dhg.view.scene import viser_server as _viser_server  # a module global: bench_browser.py swaps it
from dhg.view.surfaces import ChunkMesh, LayerSurfaces, display_step

__all__ = ["SCENE_MM_PER_M", "InstructorPage", "TraineePage"]

log = logging.getLogger(__name__)

ARROW_MM_PER_N = 10.0
"""Force arrows: millimetres of arrow per newton."""

REDRAW_TIP_M = 0.05e-3
REDRAW_FORCE_N = 0.02
"""The drill and its arrows are redrawn when the tip moved by ``REDRAW_TIP_M`` (a twentieth of the
1 mm display voxel) or a force by ``REDRAW_FORCE_N`` (0.2 mm of arrow): a stylus held still in
the bone, whose tip and forces creep by far less, sends about 3 updates a second instead of 31
(docs/benchmarks.md "What the page costs the browser")."""

SHAFT_LENGTH_M = 0.06
SHAFT_RADIUS_M = 0.8e-3
"""The drawn drill shaft behind the burr (m): a 60 mm shank, 1.6 mm across."""

PLUNGE_WARNING_M = float(FADING_DEFAULTS["plunge_tolerance_m"])
"""A plunge past this is shown as a warning (m): the fading schedule's tolerance, from the core."""

NECROSIS_C = ThermalParams().necrosis_threshold_c
"""Bone necrosis threshold (°C; Eriksson & Albrektsson 1983), drawn on the temperature plot: the
core's default (``ThermalParams``)."""


def _png_array(png: bytes) -> np.ndarray:
    from PIL import Image

    with Image.open(io.BytesIO(png)) as im:
        return np.asarray(im.convert("RGB"))


INFO_REFRESH_S = 2.0
"""How often a page asks its session's info again (s), to follow a changed path, burr or guidance."""
_DRAWN_INFO = ("entry_m", "target_m", "burr_radius_m", "guidance_mode")
"""The fields of the session info a page draws."""


class TraineePage:
    """One session's page: the bone's layers (re-meshed where drilled), the planned path A→B,
    the drill at the tip's pose (``frame_hz``), force and guidance arrows, the numbers a hand
    feels, a 20 s timeline, X-rays on demand and the summary of the last attempt.

    ``z`` is an open Zenoh session (client mode) the page shares with others; ``volume`` the
    server's (:func:`dhg.view.feed.fetch_volume`). The page's counters (:attr:`frames`,
    :attr:`bone_updates`, :attr:`remeshed_chunks`) tell what it sent: :attr:`frames` counts drill
    updates, sent only when the tip, its pose or the forces changed."""

    def __init__(
        self,
        z: Any,
        session_id: str,
        volume: VolumeData,
        port: int,
        host: str = "127.0.0.1",
        prefix: str = "dhg",
        frame_hz: float = 30.0,
        bone_hz: float = 4.0,
    ) -> None:
        if not (1.0 <= frame_hz <= 120.0) or not (0.2 <= bone_hz <= 30.0):
            raise ValueError(
                f"frame_hz must be within [1, 120] and bone_hz within [0.2, 30], got {frame_hz}, {bone_hz}"
            )
        self.session_id = session_id
        self.feed = SessionFeed(z, session_id, prefix)
        self.surfaces = LayerSurfaces(
            volume.labels, volume.spacing_m, volume.origin_m, volume.direction, step=display_step(volume.spacing_m)
        )
        self.frame_hz, self.bone_hz = frame_hz, bone_hz
        self.frames = 0
        """Drill updates sent."""
        self.watched_s = 0.0
        """How long a browser had the page open (s, counted in frames)."""
        self.bone_updates = 0
        """Bone queries answered."""
        self.remeshed_chunks = 0
        """Chunks re-meshed after drilling (the first full meshing not counted)."""
        self.bone_errors = 0
        self._info: dict[str, Any] | None = None
        self._metrics: dict[str, Any] | None = None
        self._last_metrics: dict[str, Any] | None = None  # the attempt before the last reset
        self._metric_resets = 0  # resets the metrics poll has seen (its newest is of the new attempt)
        self._shown_attempts = 0
        self._last_removed = -1.0
        self._drawn: tuple[Any, ...] | None = None  # what the drill was last drawn from
        self._plotted = -1.0  # the newest state's time in the plots
        self._stop = threading.Event()

        self.server = _viser_server(host, port, f"DHG: {session_id}")
        self.url = f"http://{host}:{self.server.get_port()}"
        self.server.scene.set_up_direction("+z")
        self._meshes: dict[str, Any] = {}
        self._build_scene(volume)
        self._build_gui()
        self.server.on_client_connect(lambda client: look_at(client, volume))
        self._threads = [
            threading.Thread(target=self._frame_loop, name=f"view-frames-{session_id}", daemon=True),
            threading.Thread(target=self._bone_loop, name=f"view-bone-{session_id}", daemon=True),
        ]
        for t in self._threads:
            t.start()

    # -- the scene -------------------------------------------------------------------------
    def _build_scene(self, volume: VolumeData) -> None:
        sc = self.server.scene
        add_whole_bone(self.server, self.surfaces, self._meshes)
        self._drill = sc.add_frame("/drill", show_axes=False)
        self._burr = sc.add_icosphere("/drill/burr", radius=1.25, color=(90, 90, 100), subdivisions=2)
        self._shaft = sc.add_cylinder(
            "/drill/shaft",
            radius=SHAFT_RADIUS_M * SCENE_MM_PER_M,
            height=SHAFT_LENGTH_M * SCENE_MM_PER_M,
            color=(170, 170, 180),
            position=(0.0, 0.0, -(1.25 + SHAFT_LENGTH_M * SCENE_MM_PER_M / 2)),
        )
        self._drill.visible = False
        # One handle whose points each redraw moves (a new add_arrows per frame made a new handle,
        # whose first property write has viser resolve its type hints: most of a redraw's CPU).
        self._arrows = sc.add_arrows(
            "/forces",
            np.zeros((2, 2, 3), np.float32),
            colors=np.array([[31, 78, 121], [230, 126, 34]], np.uint8),
            shaft_radius=0.3,
            head_radius=0.8,
            head_length=1.5,
            visible=False,
        )

    def _show(self, piece: ChunkMesh) -> None:
        add_bone_piece(self.server, self.surfaces, self._meshes, piece)

    def _show_path(self, info: dict[str, Any]) -> None:
        a = np.array(info["entry_m"]) * SCENE_MM_PER_M
        b = np.array(info["target_m"]) * SCENE_MM_PER_M
        sc = self.server.scene
        sc.add_line_segments("/path/line", np.array([[a, b]]), colors=(40, 160, 60), thickness=0.4)
        sc.add_icosphere("/path/entry", radius=1.2, color=(40, 160, 60), position=tuple(a))
        sc.add_icosphere("/path/target", radius=1.2, color=(30, 90, 200), position=tuple(b))
        r_mm = float(info["burr_radius_m"]) * SCENE_MM_PER_M
        self._burr = sc.add_icosphere("/drill/burr", radius=r_mm, color=(90, 90, 100), subdivisions=2)
        self._shaft.position = (0.0, 0.0, -(r_mm + SHAFT_LENGTH_M * SCENE_MM_PER_M / 2))

    # -- the panel -------------------------------------------------------------------------
    def _build_gui(self) -> None:
        gui = self.server.gui
        gui.configure_theme(control_width="large", dark_mode=False, show_logo=False)
        self._title = gui.add_markdown(f"**Session `{html.escape(self.session_id)}`**: waiting for the server")
        self._readout = gui.add_html(self._readout_html(None, None))
        with gui.add_folder("X-ray"):
            self._xray_buttons = gui.add_button_group("View", VIEW_NAMES)
            self._xray_image = gui.add_image(np.full((8, 8, 3), 240, np.uint8), label="press a view", visible=False)
            self._xray_buttons.on_click(lambda event: self._take_xray(event.target.value))
        with gui.add_folder("Attempt"):
            self._summary_button = gui.add_button("Summary of this attempt")
            self._summary_button.on_click(lambda _: self._summarize(finished=False))
            self._summary = gui.add_markdown("The summary of an attempt shows here when it ends (a reset).")
            self._summary_plot = gui.add_image(np.full((8, 8, 3), 255, np.uint8), visible=False)
        with gui.add_folder("Timeline (last 20 s)"):
            self._plots = self._add_plots()

    def _add_plots(self) -> dict[str, Any]:
        from viser import uplot

        empty = np.zeros(0)
        out = {}
        for key, title, labels in (
            ("force", "Force (N)", ("|F| on the hand", "thrust", "guidance share")),
            ("temperature", "Tip temperature (°C)", ("temperature", f"{NECROSIS_C:g} °C")),
            ("depth", "Depth and deviation (mm)", ("depth along A→B", "deviation from A→B")),
        ):
            colours = ("#1f4e79", "#c0392b", "#e67e22")
            series = (uplot.Series(label="time (s)"),) + tuple(
                uplot.Series(label=lab, stroke=colours[i], width=1.5) for i, lab in enumerate(labels)
            )
            out[key] = self.server.gui.add_uplot(
                (empty,) * (len(labels) + 1), series, title=title, aspect=2.2, scales={"x": uplot.Scale(time=False)}
            )
        return out

    @staticmethod
    def _readout_html(snap: dict[str, Any] | None, info: dict[str, Any] | None) -> str:
        f = (snap or {}).get("force")
        st = (snap or {}).get("state")

        def row(key: str, label: str, value: str, style: str = "") -> str:
            return f'<tr><td>{label}</td><td id="dhg-{key}" style="text-align:right;{style}">{value}</td></tr>'

        if f is None:
            body = row("status", "Session", "no force yet: is a trainee drilling?")
            return f'<table id="dhg-readout" style="width:100%">{body}</table>'
        force = np.asarray(f["force_n"], dtype=float)
        guide = np.asarray(f["guidance_n"], dtype=float)
        fn, gn = float(np.linalg.norm(force)), float(np.linalg.norm(guide))
        share = 100.0 * gn / fn if fn > 1e-9 else 0.0
        hot = f["temperature_c"] >= NECROSIS_C
        rows = [
            row("force", "Force on the hand", f"{fn:.2f} N"),
            row("guidance", "of which guidance", f"{gn:.2f} N ({share:.0f} %)"),
            row("thrust", "Thrust", f"{st['thrust_n']:.2f} N" if st else "–"),
            row(
                "temperature",
                "Tip temperature",
                f"{f['temperature_c']:.1f} °C (limit {NECROSIS_C:.0f})",
                "color:#c0392b;font-weight:bold" if hot else "",
            ),
            row("depth", "Depth along A→B", f"{f['depth_m'] * 1e3:.2f} mm"),
            row("deviation", "Deviation from A→B", f"{f['deviation_m'] * 1e3:.2f} mm"),
            row("layer", "Layer at the tip", LAYER_NAMES.get(int(f["layer"]), "?")),
            row("removed", "Bone removed", f"{st['removed_volume_m3'] * 1e9:.1f} mm³" if st else "–"),
            row("breakthroughs", "Breakthroughs", str(int(f["breakthroughs"]))),
        ]
        if info is not None:
            gain = st["guidance_gain"] if st else info["guidance_gain"]
            rows.append(row("mode", "Guidance", f"{info['guidance_mode']}, gain {gain:.2f}"))
        plunge = float(f["plunge_depth_m"])
        warn = (
            f'<div id="dhg-plunge" style="background:#c0392b;color:white;padding:4px;font-weight:bold">'
            f"PLUNGE {plunge * 1e3:.1f} mm past the breakthrough</div>"
            if plunge > PLUNGE_WARNING_M
            else '<div id="dhg-plunge" style="display:none"></div>'
        )
        return f'{warn}<table id="dhg-readout" style="width:100%">{"".join(rows)}</table>'

    def _update_plots(self) -> None:
        states = self.feed.timeline_states()
        if not states:
            return
        t = np.array([s["time_s"] for s in states])
        feats = np.array([s["features"] for s in states], dtype=float)
        thrust = np.array([s["thrust_n"] for s in states])
        dev = np.array([s["deviation_m"] for s in states]) * 1e3
        hand = np.array([s["hand_force_n"] for s in states])
        share = np.array([s["guidance_share_n"] for s in states])
        self._plots["force"].data = (t, hand, thrust, share)
        self._plots["temperature"].data = (t, feats[:, FEATURE_INDEX["temperature_c"]], np.full_like(t, NECROSIS_C))
        self._plots["depth"].data = (t, feats[:, FEATURE_INDEX["depth_m"]] * 1e3, dev)

    # -- actions ---------------------------------------------------------------------------
    def _take_xray(self, view: str) -> None:
        try:
            img = _png_array(self.feed.xray(view))
            self._xray_image.image = img
            self._xray_image.label = f"{view} view, as drilled now"
        except Exception as exc:  # no session yet, a refusal: say so on the page
            self._xray_image.label = f"no {view} X-ray: {exc}"
        self._xray_image.visible = True

    def _summarize(self, finished: bool) -> None:
        """Shows an attempt's skill metrics (the server's) and the plot ``dhg inspect --plot``
        draws (10 Hz records)."""
        import tempfile

        from dhg.data.plots import plot_timeline

        states = self.feed.attempt_states(finished)
        metrics = self._last_metrics if finished else self._metrics
        if not states:
            self._summary.content = "No states of this attempt yet."
            return
        t = np.array([s["time_s"] for s in states])
        feats = np.array([s["features"] for s in states], dtype=float)
        with tempfile.TemporaryDirectory() as d:
            out = plot_timeline(t, feats[:, 0:3], t, feats, f"{d}/attempt.png", f"{self.session_id}: attempt (10 Hz)")
            self._summary_plot.image = _png_array(out.read_bytes())
        self._summary_plot.visible = True
        self._summary.content = self._metrics_markdown(metrics, "the attempt that ended" if finished else "so far")

    @staticmethod
    def _metrics_markdown(m: dict[str, Any] | None, which: str) -> str:
        if not m:
            return f"Skill metrics ({which}): none from the server yet."

        def mm(key: str) -> str:
            v = m.get(key)
            return "–" if v is None else f"{v * 1e3:.2f} mm"

        lines = [
            f"**Skill metrics, {which}** (the server's, `docs/protocol.md`)",
            "",
            "| metric | value |",
            "|---|---|",
            f"| time | {m['time_s']:.1f} s |",
            f"| deepest along A→B | {mm('max_depth_m')} |",
            f"| largest plunge | {mm('plunge_depth_m')} |",
            f"| largest lateral deviation | {mm('max_lateral_deviation_m')} |",
            f"| distance to B at the end | {mm('target_distance_m')} |",
            f"| peak temperature | {m['peak_temperature_c']:.1f} °C |",
            f"| time above {NECROSIS_C:g} °C | {m['time_above_47_s']:.1f} s |",
            f"| force jerk | {m['force_jerk_n_per_s']:.1f} N/s |",
            f"| bone removed | {m['removed_volume_m3'] * 1e9:.1f} mm³ |",
        ]
        return "\n".join(lines)

    # -- the loops -------------------------------------------------------------------------
    @property
    def watched(self) -> bool:
        """Whether a browser has the page open. An instructor's viewer starts a page for every
        session on the server, most of them unwatched at any time: those hear their streams (so
        the timeline and the attempt's states are there when someone opens them) but draw
        nothing, re-mesh nothing and plot nothing."""
        return bool(self.server.get_clients())

    def _frame_loop(self) -> None:
        period = 1.0 / self.frame_hz
        next_t = time.monotonic()
        k = 0
        while not self._stop.is_set():
            try:
                self._frame(k)
            except Exception:  # a page must outlive any one bad frame
                log.exception("viewer frame")
            k += 1
            next_t += period
            self._stop.wait(max(0.0, next_t - time.monotonic()))

    def _frame(self, k: int) -> None:
        """One frame: the drill and arrows when the tip, pose or forces changed by what a person
        can see (:data:`REDRAW_TIP_M`, :data:`REDRAW_FORCE_N`; a still stylus costs no redraw),
        the numbers at 10 Hz and the plots at 2 Hz when they changed. Nothing while no browser
        watches the page (what changed meanwhile is drawn when one connects)."""
        if not self.watched:
            return
        self.watched_s += 1.0 / self.frame_hz
        snap = self.feed.snapshot()
        f, pose = snap["force"], snap["pose"]
        if f is not None:
            key = (
                tuple(np.round(np.asarray(f["tip_m"]) / REDRAW_TIP_M).astype(int)),
                tuple(np.round(np.asarray(f["force_n"]) / REDRAW_FORCE_N).astype(int)),
                tuple(np.round(np.asarray(f["guidance_n"]) / REDRAW_FORCE_N).astype(int)),
                pose and tuple(np.round(np.asarray(pose["orientation_wxyz"]), 3)),
            )
            if key != self._drawn:
                self._draw_drill(f, pose)
                self._drawn = key
                self.frames += 1
        every = max(1, round(self.frame_hz / 10))
        if k % every == 0:
            text = self._readout_html(snap, self._info)
            if text != self._readout.content:
                self._readout.content = text
        if k % (every * 5) == 0:
            st = snap["state"]
            if st is not None and st["time_s"] != self._plotted:
                self._update_plots()
                self._plotted = st["time_s"]

    def _draw_drill(self, f: dict[str, Any], pose: dict[str, Any] | None) -> None:
        tip = np.asarray(f["tip_m"], dtype=float) * SCENE_MM_PER_M
        with self.server.atomic():
            self._drill.position = tuple(tip)
            if pose is not None:
                self._drill.wxyz = tuple(pose["orientation_wxyz"])
            elif self._info is not None:  # no pose heard yet (the session's first forces): along A→B
                self._drill.wxyz = along(np.array(self._info["target_m"]) - np.array(self._info["entry_m"]))
            self._drill.visible = True
            self._arrows.points = np.array(
                [
                    [tip, tip + np.asarray(f["force_n"]) * ARROW_MM_PER_N],
                    [tip, tip + np.asarray(f["guidance_n"]) * ARROW_MM_PER_N],
                ],
                np.float32,
            )
            self._arrows.visible = True

    def _bone_loop(self) -> None:
        period = 1.0 / self.bone_hz
        last_metrics = last_info = 0.0
        while not self._stop.wait(period):
            # Each step on its own: a bone snapshot refused must not stop the metrics, nor they it.
            try:
                # Asked again every INFO_REFRESH_S: a set_path, set_drill or set_guidance (or the
                # session made anew under its id) redraws the path, the burr and the title.
                if self._info is None or time.monotonic() - last_info >= INFO_REFRESH_S:
                    last_info = time.monotonic()
                    info = self.feed.info()
                    if self._info is None or any(info[k] != self._info[k] for k in _DRAWN_INFO):
                        self._show_path(info)
                        self._title.content = (
                            f"**Session `{html.escape(self.session_id)}`**: {info['guidance_mode']} guidance"
                        )
                    self._info = info
                if self.watched:
                    self._update_bone()
            except Exception as exc:  # no such session yet, a server restarting: try again
                self.bone_errors += 1
                log.debug("viewer bone: %s", exc)
                if self.feed.state is None:
                    self._info = None
            try:
                if time.monotonic() - last_metrics >= 1.0:
                    last_metrics = time.monotonic()
                    m = self.feed.metrics()
                    if self._metrics is not None and m["time_s"] < self._metrics["time_s"]:
                        # The attempt that just ended, as of the poll before its end (up to 1 s short).
                        self._last_metrics = self._metrics
                        self._metric_resets += 1
                    self._metrics = m
                # Once both the states and the metrics poll have seen the reset: before the poll
                # has, its newest metrics are still of the attempt before the one that ended.
                ended = min(self.feed.attempts_finished, self._metric_resets)
                if ended > self._shown_attempts and self.watched:
                    self._shown_attempts = ended
                    self._summarize(finished=True)
            except Exception as exc:
                self.bone_errors += 1
                log.debug("viewer metrics: %s", exc)

    def _update_bone(self) -> None:
        st = self.feed.state
        removed = -2.0 if st is None else float(st["removed_volume_m3"])
        if removed == self._last_removed and st is not None:
            return  # nothing drilled since the last query (the states say): no snapshot asked
        origins, material = self.feed.bricks()
        self.bone_updates += 1
        chunks = self.surfaces.update(origins, material)
        with self.server.atomic():
            for c in sorted(chunks):
                for piece in self.surfaces.mesh(c):
                    self._show(piece)
        self.remeshed_chunks += len(chunks)
        self._last_removed = removed

    def close(self) -> None:
        """Stops the loops, the subscriptions and the page's server."""
        self._stop.set()
        for t in self._threads:
            t.join(timeout=5.0)
        self.feed.close()
        stop_quietly(self.server)
