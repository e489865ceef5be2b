"""A dataset at a glance (``dhg inspect``): one line per episode with its skill metrics, and a plot
of one episode over time. Works alike on ``dhg synth`` datasets and ``dhg record`` recordings."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import numpy as np

from dhg.core.features import TICK_S
from dhg.data.dataset import Dataset, DatasetError, load_raw

__all__ = ["METRIC_COLUMNS", "episode_summaries", "load_with_raw", "plot_episode", "summary_table"]

METRIC_COLUMNS: tuple[tuple[str, str, float], ...] = (
    ("completed", "completed", 1.0),
    ("to B (mm)", "target_distance_m", 1e3),
    ("max dev. (mm)", "max_deviation_m", 1e3),
    ("plunge (mm)", "plunge_depth_m", 1e3),
    ("peak (°C)", "peak_temperature_c", 1.0),
    ("> 47 °C (s)", "time_above_47_s", 1.0),
    ("jerk (N/s)", "force_jerk_n_per_s", 1.0),
)
"""(column title, card metric, factor from SI to the title's unit) of the summary table."""


def episode_summaries(ds: Dataset, raw: Any | None = None) -> list[dict[str, Any]]:
    """Per episode: id, subject, skill, attempt, whether it is the subject's best, its records,
    its duration (s), its 1 kHz ticks (None without a raw stream) and its skill metrics (SI)."""
    ticks: dict[int, int] = {}
    if raw is not None:
        ids, counts = np.unique(raw.column("episode_id").to_numpy(), return_counts=True)
        ticks = {int(i): int(c) for i, c in zip(ids, counts, strict=True)}
    return [
        {
            "episode_id": e.episode_id,
            "subject_id": e.subject_id,
            "skill": e.skill,
            "attempt": e.attempt,
            "best_of_subject": e.best_of_subject,
            "records": len(e.times_s),
            "duration_s": float(e.times_s[-1] - e.times_s[0] + 0.1) if len(e.times_s) else 0.0,
            "raw_ticks": ticks.get(e.episode_id, 0) if raw is not None else None,
            "metrics": e.metrics,
        }
        for e in ds.episodes
    ]


def summary_table(rows: list[dict[str, Any]]) -> Any:
    """A :class:`rich.table.Table` of :func:`episode_summaries`, metrics in the units of
    :data:`METRIC_COLUMNS`; ``*`` marks each subject's best attempt."""
    from rich.table import Table

    table = Table(show_edge=False)
    for col in ("ep", "subject", "skill", "try", "best", "records", "time (s)", "ticks"):
        table.add_column(col, justify="left" if col in ("subject", "skill") else "right")
    for title, _, _ in METRIC_COLUMNS:
        table.add_column(title, justify="right")
    for r in rows:
        cells = [str(r["episode_id"]), r["subject_id"], r["skill"], str(r["attempt"])]
        cells += ["*" if r["best_of_subject"] else "", str(r["records"]), f"{r['duration_s']:.1f}"]
        cells.append("" if r["raw_ticks"] is None else str(r["raw_ticks"]))
        for _, key, factor in METRIC_COLUMNS:
            v = r["metrics"].get(key)
            cells.append("" if v is None else ("yes" if v else "no") if isinstance(v, bool) else f"{v * factor:.2f}")
        table.add_row(*cells)
    return table


def plot_episode(ds: Dataset, episode_id: int, out: str | os.PathLike[str], raw: Any | None = None) -> Path:
    """Writes a PNG of one episode over time: the device force (1 kHz with its guidance share when
    the dataset keeps the raw stream, else the 10 Hz feedback force), the tip temperature and the
    depth, with the layer at the tip shaded (:func:`dhg.data.plots.plot_timeline`).

    Raises:
        DatasetError: no episode ``episode_id`` in the dataset.
    """
    from dhg.data.plots import plot_timeline

    by_id = {e.episode_id: e for e in ds.episodes}
    if episode_id not in by_id:
        raise DatasetError(f"{ds.path}: no episode {episode_id} (it has {_id_range(sorted(by_id))})")
    e = by_id[episode_id]
    title = f"{ds.path.name}: episode {episode_id}, {e.subject_id} ({e.skill}), attempt {e.attempt}"
    rows = None
    if raw is not None:
        mask = raw.column("episode_id").to_numpy() == episode_id
        if mask.any():
            rows = {n: raw.column(n).to_numpy()[mask] for n in raw.schema.names}
    if rows is None:
        return plot_timeline(e.times_s, e.features[:, 0:3], e.times_s, e.features, out, title + " (10 Hz)")
    forces = np.column_stack([rows[f"force_{a}_n"] for a in "xyz"])
    guidance = np.column_stack([rows[f"guidance_{a}_n"] for a in "xyz"])
    t = (rows["tick"] + 1) * TICK_S  # the tick ending at this time (docs/dataset.md)
    return plot_timeline(t, forces, e.times_s, e.features, out, title, guidance if guidance.any() else None)


def _id_range(ids: list[int]) -> str:
    if not ids:
        return "none"
    shown = ", ".join(str(i) for i in ids[:8])
    return f"episodes {shown}{', ...' if len(ids) > 8 else ''}"


def load_with_raw(path: str | os.PathLike[str]) -> tuple[Dataset, Any | None]:
    """The dataset at ``path`` and its raw stream (None without one), both validated."""
    from dhg.data.dataset import load_dataset

    ds = load_dataset(path)
    return ds, load_raw(ds)
