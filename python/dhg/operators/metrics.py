"""Skill metrics of a drilling attempt (SI units)."""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

from dhg.core.path import PlannedPath, TaskRules

__all__ = ["skill_metrics"]


def skill_metrics(
    records: npt.NDArray[np.float64],
    path: PlannedPath,
    rules: TaskRules,
    final_tip_m: npt.ArrayLike,
    drilling_s: float,
    plunge_depth_m: float,
    peak_temperature_c: float,
    time_above_47_s: float,
    forces_n: npt.NDArray[np.float64] | None = None,
) -> dict[str, float | bool]:
    """Skill metrics of a run (SI units). Force smoothness is the RMS rate of change of the device
    force over the 10 Hz records (N/s), or over the 1 kHz stream when given."""
    tips = records[:, 4:7] if len(records) else np.empty((0, 3))
    depth = records[:, 8] if len(records) else np.empty(0)
    inside = depth > 0
    dev = path.lateral_deviation(tips[inside]) if inside.any() else np.zeros(1)
    across = path.offset_from_line(tips[inside]) if inside.any() else np.zeros(1)
    target_dist = float(np.linalg.norm(np.asarray(final_tip_m, float) - path.target_m))
    if forces_n is not None and len(forces_n) > 1:
        dF = np.diff(forces_n, axis=0) / 1e-3
    elif len(records) > 1:
        dF = np.diff(records[:, 1:4], axis=0) / 0.1
    else:
        dF = np.zeros((1, 3))
    metrics: dict[str, float | bool] = {
        "completion_time_s": float(drilling_s),
        "mean_deviation_m": float(dev.mean()),
        "max_deviation_m": float(dev.max()),
        "max_lateral_deviation_m": float(across.max()),
        "target_distance_m": target_dist,
        "plunge_depth_m": float(plunge_depth_m),
        "peak_temperature_c": float(peak_temperature_c),
        "time_above_47_s": float(time_above_47_s),
        "force_jerk_n_per_s": float(np.sqrt(np.mean(np.sum(dF * dF, axis=1)))),
    }
    metrics["completed"] = bool(
        target_dist <= rules.max_target_distance_m
        and metrics["max_deviation_m"] <= rules.max_deviation_m
        and drilling_s <= rules.max_duration_s
    )
    return metrics
