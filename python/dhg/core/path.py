"""The surgical task: a straight planned path from an entry point A to a target B (m, world frame)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from dhg import _bone_sim
from dhg.core.errors import InvalidInputError

__all__ = ["PLAN_STEP_M", "PlannedPath", "TaskRules"]

PLAN_STEP_M: float = float(_bone_sim.PLAN_STEP_M)
"""The step (m) at which a planned path's layers are read off the planning CT: the sessions'
planned breakthrough and the info's ``path_layers`` use it (0.25 mm). Defined in the core."""

_RULES: dict[str, float] = _bone_sim.defaults()["task_rules"]
"""The core's ``TaskRules::default()``: the one place the task's tolerances are defined."""


@dataclass(frozen=True)
class TaskRules:
    """What counts as completing the drilling task A → B (DHG's tolerances: Fekri et al. 2021
    state none)."""

    max_target_distance_m: float = _RULES["max_target_distance_m"]
    """The final tip must be this close to B (m)."""
    max_deviation_m: float = _RULES["max_deviation_m"]
    """The tip may stray at most this far from the planned segment while in bone (m)."""
    max_duration_s: float = _RULES["max_duration_s"]
    """The attempt must finish within this time (s)."""

    def to_dict(self) -> dict[str, float]:
        """The rules as a dataset card's ``task_rules`` holds them (m, m, s)."""
        return {
            "max_target_distance_m": self.max_target_distance_m,
            "max_deviation_m": self.max_deviation_m,
            "max_duration_s": self.max_duration_s,
        }


@dataclass(frozen=True)
class PlannedPath:
    """A straight drilling path A → B, as in hip pinning (entry on the lateral cortex, target in
    the femoral head). Points are in metres, world frame (LPS)."""

    entry_m: npt.NDArray[np.float64]
    """A: where the drill enters the bone surface (m)."""
    target_m: npt.NDArray[np.float64]
    """B: where the drill tip should stop (m)."""

    def __post_init__(self) -> None:
        try:
            a = np.asarray(self.entry_m, dtype=np.float64).reshape(-1)
            b = np.asarray(self.target_m, dtype=np.float64).reshape(-1)
        except (TypeError, ValueError):
            raise InvalidInputError(
                f"entry and target must be 3-D points of numbers (m), got {self.entry_m!r} and {self.target_m!r}"
            ) from None
        if a.shape != (3,) or b.shape != (3,):
            raise InvalidInputError(f"entry and target must be 3-D points, got {a.shape} and {b.shape}")
        if not (np.all(np.isfinite(a)) and np.all(np.isfinite(b))):
            raise InvalidInputError("entry and target must be finite")
        if np.linalg.norm(b - a) < _bone_sim.MIN_PATH_LENGTH_M:
            raise InvalidInputError(f"entry and target must be at least {_bone_sim.MIN_PATH_LENGTH_M * 1e3:g} mm apart")
        object.__setattr__(self, "entry_m", a)
        object.__setattr__(self, "target_m", b)

    @property
    def length_m(self) -> float:
        """|B − A| (m)."""
        return float(np.linalg.norm(self.target_m - self.entry_m))

    @property
    def direction(self) -> npt.NDArray[np.float64]:
        """Unit vector from A to B."""
        return (self.target_m - self.entry_m) / self.length_m

    def point_at(self, depth_m: npt.ArrayLike) -> npt.NDArray[np.float64]:
        """World points (N, 3) at the given depths (m) along the path from A (negative: before A)."""
        d = np.atleast_1d(np.asarray(depth_m, dtype=np.float64))
        return self.entry_m + d[:, None] * self.direction

    def depth_of(self, points_m: npt.ArrayLike) -> npt.NDArray[np.float64]:
        """Penetration depth (m) of points along the path: projection onto A→B, from A."""
        p = np.atleast_2d(np.asarray(points_m, dtype=np.float64))
        return (p - self.entry_m) @ self.direction

    def lateral_deviation(self, points_m: npt.ArrayLike) -> npt.NDArray[np.float64]:
        """Distance (m) of points from the segment AB: the perpendicular distance to the path while
        between A and B, the distance to A or B beyond them (the same definition as the core's)."""
        p = np.atleast_2d(np.asarray(points_m, dtype=np.float64))
        rel = p - self.entry_m
        t = np.clip(rel @ self.direction, 0.0, self.length_m)
        return np.linalg.norm(rel - np.outer(t, self.direction), axis=1)

    def offset_from_line(self, points_m: npt.ArrayLike) -> npt.NDArray[np.float64]:
        """Distance (m) of points from the line through A and B: how far across the path a tip is,
        wherever along it, so a tip past B counts its offset across the path but not its overshoot
        along it (which :meth:`lateral_deviation` adds, and the target distance measures); the
        guidance studies judge lateral accuracy by it (docs/decisions/0015-offset-across-the-path.md)."""
        p = np.atleast_2d(np.asarray(points_m, dtype=np.float64))
        rel = p - self.entry_m
        return np.linalg.norm(rel - np.outer(rel @ self.direction, self.direction), axis=1)

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready form (m)."""
        return {"entry_m": self.entry_m.tolist(), "target_m": self.target_m.tolist()}

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> PlannedPath:
        """Inverse of :meth:`to_dict`; a dict without ``entry_m`` and ``target_m`` is an
        :class:`InvalidInputError` naming what is missing."""
        if not isinstance(d, dict):
            raise InvalidInputError(f"a planned path is a dict with entry_m and target_m, got {type(d).__name__}")
        missing = [k for k in ("entry_m", "target_m") if k not in d]
        if missing:
            raise InvalidInputError(f"a planned path needs {' and '.join(missing)} (m); it has {sorted(d)}")
        return cls(d["entry_m"], d["target_m"])
