"""Operators without human behaviour: a drill eroding along the path without force feedback
(:func:`straight_line_drill`) and a stylus pushed along the path (:func:`scripted_stylus`)."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from dhg.bone.planning import layer_runs
from dhg.core.errors import InvalidInputError
from dhg.core.features import TICK_S
from dhg.core.path import PlannedPath
from dhg.core.session import MAX_SPINDLE_RPM, poses
from dhg.core.surgeon import MAX_ATTEMPT_S, axis_quaternion
from dhg.core.volume import DrilledVolume

__all__ = ["DrillRun", "scripted_stylus", "straight_line_drill"]


@dataclass
class DrillRun:
    """Summary of a scripted drilling run (SI units)."""

    duration_s: float
    """Simulated time (s)."""
    ticks: int
    """1 ms ticks simulated."""
    mass_removed_kg: float
    """Bone mass removed (kg)."""
    voxels_removed: int
    """Voxels fully removed."""
    tip_m: np.ndarray
    """Final burr centre (m)."""
    layers: list[tuple[str, float, float]] = field(default_factory=list)
    """Layers crossed: (name, depth where it starts (m), depth where it ends (m)) along the path."""


def straight_line_drill(
    bone: DrilledVolume,
    path: PlannedPath,
    radius_m: float = 1.25e-3,
    feed_m_s: float = 1.5e-3,
    spindle_rpm: float = 1200.0,
    tick_s: float = 1e-3,
    start_before_m: float = 2e-3,
    chunk_ticks: int = 1000,
    progress: Callable[[int, int], None] | None = None,
) -> DrillRun:
    """Drills ``bone`` from ``start_before_m`` (m) before A to B at a constant feed (m/s).

    Each tick moves the burr centre ``feed_m_s · tick_s`` along the path and erodes for ``tick_s``.
    ``progress(done_ticks, total_ticks)`` is called after each chunk of ticks.
    """
    for name, v in (("radius_m", radius_m), ("feed_m_s", feed_m_s), ("tick_s", tick_s)):
        if not (np.isfinite(v) and v > 0):
            raise InvalidInputError(f"{name} must be > 0, got {v}")
    total_m = path.length_m + start_before_m
    ticks = int(np.ceil(total_m / (feed_m_s * tick_s)))
    depths = -start_before_m + np.linspace(feed_m_s * tick_s, total_m, ticks)
    centers = path.point_at(depths)
    mass = 0.0
    removed = 0
    for start in range(0, ticks, chunk_ticks):
        r = bone.remove_along(centers[start : start + chunk_ticks], radius_m, spindle_rpm, tick_s)
        mass += r.mass_removed_kg
        removed += r.voxels_removed
        if progress is not None:
            progress(min(start + chunk_ticks, ticks), ticks)
    return DrillRun(
        duration_s=ticks * tick_s,
        ticks=ticks,
        mass_removed_kg=mass,
        voxels_removed=removed,
        tip_m=centers[-1],
        layers=layer_runs(bone, path),
    )


def scripted_stylus(
    path: PlannedPath,
    duration_s: float,
    feed_m_s: float = 1.5e-3,
    lead_m: float = 4e-3,
    start_before_m: float = 5e-3,
    spindle_rpm: float = 1250.0,
) -> np.ndarray:
    """Pose rows (N, 9) for :meth:`dhg.DrillingSession.step`: a stylus commanded along the path at
    ``feed_m_s`` (m/s), ``lead_m`` (m) ahead of the planned feed, that stops at B.

    Against bone, the drill lags the command. The stylus then runs ahead of the tip, and the
    coupling force (the push) grows until the cutting law lets the tip keep up. It is a
    position-driven operator with no human behaviour (that comes with the virtual surgeons).
    """
    if not 0 < duration_s <= MAX_ATTEMPT_S:  # also False for NaN
        raise InvalidInputError(f"duration_s must be > 0 and at most {MAX_ATTEMPT_S:g} s, got {duration_s}")
    if not (np.isfinite(feed_m_s) and feed_m_s > 0):
        raise InvalidInputError(f"feed_m_s must be a number > 0 m/s, got {feed_m_s}")
    for name, v in (("lead_m", lead_m), ("start_before_m", start_before_m)):
        if not (np.isfinite(v) and v >= 0):
            raise InvalidInputError(f"{name} must be a number >= 0 m, got {v}")
    if not 0.0 <= spindle_rpm <= MAX_SPINDLE_RPM:  # also False for NaN
        raise InvalidInputError(
            f"spindle_rpm must be 0 to {MAX_SPINDLE_RPM:g} rpm (a faster pose is refused), got {spindle_rpm}"
        )
    n = int(round(duration_s / TICK_S))
    depth = np.minimum(-start_before_m + np.arange(n) * TICK_S * feed_m_s + lead_m, path.length_m)
    return poses(path.point_at(depth), axis_quaternion(path.direction), True, spindle_rpm)
