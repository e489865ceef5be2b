"""The paper's Table 1 on our data: all four presets trained on the same chronological split."""

from __future__ import annotations

import json
import os
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from dhg.core.protocol import WINDOW_RECORDS
from dhg.learning.network import PRESETS
from dhg.learning.train import TrainConfig, train

__all__ = ["TABLE1_PRESETS", "ablate", "markdown_table", "persistence_baseline"]

TABLE1_PRESETS = ("fusion-1x128", "fusion-2x256", "force-only-2x256", "all-2x256")


def persistence_baseline(
    data_dir: str | os.PathLike[str], cfg: TrainConfig | None = None, window: int = WINDOW_RECORDS
) -> dict:
    """Test RMSE (N) of predicting that the next force equals the last one, on the same split the
    models are scored on. The yardstick that shows how much the models learn beyond the force's
    autocorrelation."""
    from dhg.data.dataset import load_dataset
    from dhg.learning.train import make_windows, split_windows

    cfg = cfg or TrainConfig()
    x, y, _ = make_windows(load_dataset(data_dir), window, cfg.skill, cfg.best_only, cfg.horizon)
    split = split_windows(len(x), window + cfg.horizon - 1, cfg.test_fraction, cfg.val_fraction)
    err = x[split.test][:, -1, 0:3] - y[split.test][:, 0:3]
    return {"rmse_n": float(np.sqrt(np.mean(err**2))), "test_samples": int(len(err))}


def markdown_table(results: dict[str, list[dict[str, Any]]]) -> str:
    """The results in the layout of the paper's Table 1: test RMSE of the force in N (and
    normalised), as mean ± standard deviation over the seeds."""
    head = (
        "| configuration | input | output | time steps | layers | memory (units) | train samples | test samples "
        "| batch | seeds | RMSE (N) | RMSE (normalised) |\n|---|---|---|---|---|---|---|---|---|---|---|---|"
    )
    rows = [head]
    for name, runs in results.items():
        m = runs[0]
        mc = m["model_config"]
        rmse = np.array([r["test"]["rmse_n"] for r in runs])
        norm = np.array([r["test"]["rmse_normalized"] for r in runs])
        rows.append(
            f"| {name} | {len(mc['input_features'])} | {len(mc['output_features'])} | {mc['window']} | {mc['layers']} "
            f"| {mc['hidden']} | {m['samples']['train']} | {m['samples']['test']} | {m['train_config']['batch_size']} "
            f"| {len(runs)} | {rmse.mean():.4f} ± {rmse.std():.4f} | {norm.mean():.4f} ± {norm.std():.4f} |"
        )
    return "\n".join(rows) + "\n"


def ablate(
    data_dir: str | os.PathLike[str],
    out_dir: str | os.PathLike[str],
    cfg: TrainConfig | None = None,
    presets: tuple[str, ...] = TABLE1_PRESETS,
    seeds: tuple[int, ...] = (0,),
    on_start: Callable[[str, int], None] | None = None,
) -> dict[str, list[dict[str, Any]]]:
    """Trains each preset with each seed into ``out_dir/<preset>/seed-<s>`` (skipping runs whose
    ``metrics.json`` is already there) and writes ``table.md`` and ``results.json``."""
    cfg = cfg or TrainConfig()
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    results: dict[str, list[dict[str, Any]]] = {}
    for name in presets:
        for seed in seeds:
            run = out / name / f"seed-{seed}"
            done = run / "metrics.json"
            if done.is_file():
                results.setdefault(name, []).append(json.loads(done.read_text()))
                continue
            if on_start is not None:
                on_start(name, seed)
            results.setdefault(name, []).append(train(data_dir, run, PRESETS[name], replace(cfg, seed=seed)).metrics)
    baseline = persistence_baseline(data_dir, cfg, PRESETS[presets[0]].window)
    (out / "results.json").write_text(json.dumps({"runs": results, "persistence_baseline": baseline}, indent=1))
    (out / "table.md").write_text(
        markdown_table(results) + f"\nPersistence baseline (next force = last force) on the same test windows: "
        f"RMSE {baseline['rmse_n']:.4f} N.\n"
    )
    return results
