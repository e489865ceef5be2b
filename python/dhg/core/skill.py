"""Skill metrics of a drilling attempt (SI units): the core's one definition (``skill.rs``), the
same figures the server reports per session and ``dhg record`` stores (``docs/dataset.md``)."""

from __future__ import annotations

from dataclasses import asdict

import numpy as np
import numpy.typing as npt

from dhg import _bone_sim
from dhg.core.errors import ShapeError
from dhg.core.features import RECORD_COLUMNS
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
    """Skill metrics of an attempt from its 10 Hz ``records`` (M, 11: time, the nine features,
    drill on) on ``path``, judged by ``rules``, and how it ended: the final tip (m), the drilling
    time (s), its largest plunge (m), peak tip temperature (°C) and time above 47 °C (s). Deviation
    counts the records with the tip in bone (depth along A→B > 0). Force smoothness
    (``force_jerk_n_per_s``) is the RMS rate of change of the device force (N/s) over the 1 kHz
    ``forces_n`` (N, 3) when given, else over the 10 Hz records.

    Raises :class:`~dhg.core.errors.ShapeError` for records, forces or a final tip of the wrong
    shape, :class:`~dhg.core.errors.InvalidInputError` for a non-positive rule, a NaN or infinite
    value, or a negative duration or plunge."""
    rec = np.ascontiguousarray(records, dtype=np.float64)
    if rec.size == 0:
        rec = rec.reshape(0, len(RECORD_COLUMNS))
    if rec.ndim != 2:
        raise ShapeError(f"records must be (M, {len(RECORD_COLUMNS)}), got shape {rec.shape}")
    tip = np.asarray(final_tip_m, dtype=np.float64)
    if tip.shape != (3,):
        raise ShapeError(f"final_tip_m must be 3 coordinates (m), got shape {tip.shape}")
    forces = None if forces_n is None else np.ascontiguousarray(forces_n, dtype=np.float64)
    if forces is not None and forces.ndim != 2:
        raise ShapeError(f"forces_n must be (N, 3), got shape {forces.shape}")
    return dict(
        _bone_sim.skill_metrics(
            rec,
            path.entry_m.tolist(),
            path.target_m.tolist(),
            tip.tolist(),
            float(drilling_s),
            float(plunge_depth_m),
            float(peak_temperature_c),
            float(time_above_47_s),
            rules=asdict(rules),
            forces_n=forces,
        )
    )
