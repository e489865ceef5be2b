"""X-ray views as pictures: the Rust line integrals turned into radiograph-like PNGs, with the drill
tip and the planned path drawn on top (like the paper's Figure 5).

Display conventions (``docs/frames.md``): the front and side views show superior up; the front view
shows the patient's left on the image's right (radiological convention); the top view shows
anterior up. Images are upscaled so that one pixel is ``PIXEL_MM`` mm or less.
"""

from __future__ import annotations

import os
from collections.abc import Iterable
from pathlib import Path

import numpy as np
import numpy.typing as npt
from PIL import Image, ImageDraw

from dhg.core.path import PlannedPath
from dhg.core.volume import VIEW_NAMES, Volume, XRayViews

__all__ = ["VIEW_NAMES", "auto_windows", "radiograph", "render_views", "view_pixel", "write_views"]

PIXEL_MM = 0.2
_PATH_RGB = (60, 220, 90)
_TIP_RGB = (235, 50, 40)
_TARGET_RGB = (80, 160, 255)


def _absorbed(line_integral: npt.NDArray[np.floating]) -> np.ndarray:
    return 1.0 - np.exp(-np.asarray(line_integral, dtype=np.float64))


def auto_window(line_integral: npt.NDArray[np.floating]) -> tuple[float, float]:
    """Grey window of a view: the 1st–99.8th percentiles of its absorbed fraction."""
    img = _absorbed(line_integral)
    return float(np.percentile(img, 1)), float(np.percentile(img, 99.8))


def auto_windows(views: XRayViews) -> dict[str, tuple[float, float]]:
    """:func:`auto_window` of each view, to render other views (e.g. after drilling) alike."""
    return {name: auto_window(data) for name, data in views.as_dict().items()}


def radiograph(line_integral: npt.NDArray[np.floating], window: tuple[float, float] | None = None) -> np.ndarray:
    """Maps line integrals ∫μ dl to an 8-bit radiograph (dense = bright): the absorbed fraction
    ``1 − exp(−∫μ dl)`` windowed to ``window`` (default :func:`auto_window`)."""
    img = _absorbed(line_integral)
    lo, hi = window if window is not None else auto_window(line_integral)
    scaled = np.clip((img - lo) / max(hi - lo, 1e-9), 0.0, 1.0)
    return (scaled * 255.0 + 0.5).astype(np.uint8)


def _display(view: str, img: np.ndarray) -> np.ndarray:
    """Flips a view so superior is up (front, side)."""
    return img[::-1] if view in ("front", "side") else img


def view_pixel(volume: Volume, view: str, points_m: npt.ArrayLike) -> np.ndarray:
    """(row, col) display pixel coordinates (before upscaling) of world points (m) in ``view``."""
    ijk = volume.world_to_index(points_m)
    nz = volume.shape[0]
    if view == "top":
        return np.stack([ijk[:, 1], ijk[:, 0]], axis=1)
    if view == "front":
        return np.stack([nz - 1 - ijk[:, 2], ijk[:, 0]], axis=1)
    if view == "side":
        return np.stack([nz - 1 - ijk[:, 2], ijk[:, 1]], axis=1)
    raise ValueError(f"view must be one of {VIEW_NAMES}, got {view!r}")


def render_views(
    volume: Volume,
    views: XRayViews,
    path: PlannedPath | None = None,
    tip_m: npt.ArrayLike | None = None,
    windows: dict[str, tuple[float, float]] | None = None,
) -> dict[str, Image.Image]:
    """RGB images of the three views with the optional planned path (green, target in blue) and
    drill tip (red). ``windows`` fixes each view's grey window, e.g. to compare before/after."""
    scale = max(1, round(min(volume.spacing_m) * 1e3 / PIXEL_MM))
    out: dict[str, Image.Image] = {}
    for name, data in views.as_dict().items():
        grey = _display(name, radiograph(data, (windows or {}).get(name)))
        img = Image.fromarray(grey, mode="L").convert("RGB")
        img = img.resize((img.width * scale, img.height * scale), Image.Resampling.BILINEAR)
        draw = ImageDraw.Draw(img)

        def px(points: npt.ArrayLike, name: str = name) -> Iterable[tuple[float, float]]:
            rc = (view_pixel(volume, name, points) + 0.5) * scale
            return [(float(c), float(r)) for r, c in rc]

        if path is not None:
            a, b = px(np.stack([path.entry_m, path.target_m]))
            # Dotted every 3 mm, so a drilled tunnel under it stays visible.
            for cx, cy in px(path.point_at(np.arange(0.0, path.length_m, 3e-3))):
                draw.point([(cx, cy)], fill=_PATH_RGB)
            ring = 2 * scale
            for (cx, cy), rgb in ((a, _PATH_RGB), (b, _TARGET_RGB)):
                draw.ellipse([cx - ring, cy - ring, cx + ring, cy + ring], outline=rgb, width=max(1, scale // 2))
        if tip_m is not None:
            ((cx, cy),) = px(np.asarray(tip_m, dtype=float).reshape(1, 3))
            r = 1.5 * scale
            draw.ellipse([cx - r, cy - r, cx + r, cy + r], fill=_TIP_RGB)
        out[name] = img
    return out


def write_views(images: dict[str, Image.Image], out_dir: str | os.PathLike[str]) -> dict[str, Path]:
    """Writes ``top.png``, ``front.png``, ``side.png`` into ``out_dir`` (created if needed), each
    atomically. Returns the paths."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    paths = {}
    for name, img in images.items():
        final = out / f"{name}.png"
        tmp = out / f".{name}.png.tmp"
        img.save(tmp, format="PNG")
        os.replace(tmp, final)
        paths[name] = final
    return paths
