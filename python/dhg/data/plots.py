"""Pictures a person would rather look at than read: drilling runs over time."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import numpy.typing as npt

from dhg.core.features import FEATURE_INDEX, RECORD_PERIOD_S, TICK_S
from dhg.core.layers import Layer
from dhg.core.session import StepResult, ThermalParams

__all__ = ["plot_drilling", "plot_forces", "plot_losses", "plot_timeline"]

_LAYER_COLOURS = {
    Layer.OUTSIDE: "#ffffff",
    Layer.CORTICAL: "#d9c9a3",
    Layer.CANCELLOUS: "#f1e6c8",
    Layer.MARROW: "#f6d4c4",
    Layer.NECROSIS: "#d6c2e0",
}


def plot_drilling(result: StepResult, out: str | os.PathLike[str], title: str = "") -> Path:
    """Writes a PNG of a drilling run: device force (N, 1 kHz), drill-tip temperature (°C) and
    penetration depth (mm) over time (s), with the layer at the tip shaded behind."""
    t_ticks = np.arange(1, len(result.forces_n) + 1) * TICK_S
    return plot_timeline(t_ticks, result.forces_n, result.times_s, result.features, out, title)


def plot_timeline(
    force_t_s: npt.ArrayLike,
    forces_n: npt.ArrayLike,
    times_s: npt.ArrayLike,
    features: npt.ArrayLike,
    out: str | os.PathLike[str],
    title: str = "",
    guidance_n: npt.ArrayLike | None = None,
) -> Path:
    """Writes a PNG of one attempt over time (s): the device force |F| (N) at ``force_t_s`` (1 kHz
    ticks or the 10 Hz records) with its guidance share |G| when given, and from the 10 Hz records
    (``times_s``, ``features`` in :data:`dhg.core.features.FEATURE_NAMES` order) the drill-tip
    temperature (°C) and the depth along A→B (mm), with the layer at the tip shaded behind."""
    from matplotlib.figure import Figure
    from matplotlib.patches import Patch

    t_rec = np.asarray(times_s, dtype=float)
    feats = np.asarray(features, dtype=float)
    # A Figure of its own, not pyplot's global state: pages plot from several threads at once.
    fig = Figure(figsize=(9, 7), constrained_layout=True)
    axes = fig.subplots(3, 1, sharex=True)
    for layer, start_s, end_s in _layer_spans(t_rec, feats[:, FEATURE_INDEX["layer"]]):
        for ax in axes:
            ax.axvspan(start_s, end_s, color=_LAYER_COLOURS[layer], lw=0)
    t_f = np.asarray(force_t_s, dtype=float)
    axes[0].plot(t_f, np.linalg.norm(np.asarray(forces_n, dtype=float), axis=1), lw=0.8, color="#1f4e79", label="|F|")
    if guidance_n is not None:
        g = np.linalg.norm(np.asarray(guidance_n, dtype=float), axis=1)
        axes[0].plot(t_f, g, lw=0.8, color="#e67e22", label="guidance share |G|")
    axes[0].set_ylabel("device force (N)")
    necrosis_c = ThermalParams().necrosis_threshold_c  # the core's default (Eriksson & Albrektsson 1983)
    axes[1].plot(t_rec, feats[:, FEATURE_INDEX["temperature_c"]], color="#c0392b")
    axes[1].axhline(necrosis_c, ls="--", lw=0.8, color="#c0392b")
    label = f"{necrosis_c:g} °C necrosis threshold"
    axes[1].text(t_rec[0] if len(t_rec) else 0, necrosis_c + 0.2, label, fontsize=8, color="#c0392b")
    axes[1].set_ylabel("tip temperature (°C)")
    axes[2].plot(t_rec, feats[:, FEATURE_INDEX["depth_m"]] * 1e3, color="#2d6a4f")
    axes[2].set_ylabel("depth along A→B (mm)")
    axes[2].set_xlabel("time (s)")
    handles = [Patch(color=c, label=layer.name.lower()) for layer, c in _LAYER_COLOURS.items() if layer]
    axes[0].legend(handles=handles, loc="upper right", fontsize=8, ncols=4, title="layer at the tip")
    if guidance_n is not None:
        axes[0].add_artist(axes[0].get_legend())
        axes[0].legend(*axes[0].get_legend_handles_labels(), loc="upper left", fontsize=8)
    if title:
        fig.suptitle(title)
    return _save(fig, out)


def _layer_spans(t_rec: npt.NDArray[np.float64], layers: npt.NDArray[np.float64]) -> list[tuple[Layer, float, float]]:
    """The records' layer as runs (layer, start s, end s): each record covers the period before
    its time; a run ends where the layer changes or a record is missing. One span per run, not
    per record (an hour of records drew for minutes)."""
    if len(t_rec) == 0:
        return []
    breaks = np.flatnonzero((np.diff(layers) != 0) | (np.diff(t_rec) > 1.5 * RECORD_PERIOD_S)) + 1
    starts = np.concatenate([[0], breaks])
    ends = np.concatenate([breaks, [len(t_rec)]]) - 1
    return [
        (Layer(int(layers[a])), float(t_rec[a] - RECORD_PERIOD_S), float(t_rec[b]))
        for a, b in zip(starts, ends, strict=True)
    ]


def _save(fig, out: str | os.PathLike[str]) -> Path:
    """Writes a figure as PNG atomically and closes it."""
    import matplotlib.pyplot as plt

    path = Path(out)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp")
    fig.savefig(tmp, dpi=110, format="png")
    if fig.canvas.manager is not None:  # one of pyplot's: let it go
        plt.close(fig)
    os.replace(tmp, path)
    return path


def plot_losses(history: list[dict[str, float]], out: str | os.PathLike[str], title: str = "") -> Path:
    """Training and validation RMSE (normalised) per epoch, as a PNG."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4), constrained_layout=True)
    epochs = [h["epoch"] + 1 for h in history]
    ax.plot(epochs, [h["train_rmse"] for h in history], label="train")
    ax.plot(epochs, [h["val_rmse"] for h in history], label="validation")
    ax.set_xlabel("epoch")
    ax.set_ylabel("RMSE (normalised)")
    ax.legend()
    ax.set_title(title)
    return _save(fig, out)


def plot_forces(reference: np.ndarray, predicted: np.ndarray, out: str | os.PathLike[str], title: str = "") -> Path:
    """Reference vs predicted force per axis over a test window (the paper's Figure 9), as a PNG."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(3, 1, figsize=(9, 6.5), sharex=True, constrained_layout=True)
    for i, (ax, name) in enumerate(zip(axes, ("x", "y", "z"), strict=True)):
        ax.plot(reference[:, i], lw=1.0, label="reference (expert)")
        ax.plot(predicted[:, i], lw=1.0, label="predicted")
        ax.set_ylabel(f"force {name} (N)")
    axes[0].legend(loc="upper right", fontsize=8)
    axes[-1].set_xlabel("test record (10 Hz)")
    if title:
        fig.suptitle(title)
    return _save(fig, out)
