"""Guidance studies: do virtual novices drill better with guidance? (``dhg study``)

Each novice (a seed: one hand, :func:`dhg.surgeons.sample_style`) drills the planned path once per
arm, offline through the core (the same 1 kHz session code ``dhg-serve`` runs, faster than real
time) with the model in-process, queried at every 10 Hz record. An arm is a guidance mode at a
gain, or none. Because every arm sees the same hands with the same noise, arms are compared with
paired differences against the unguided arm: per metric, the mean difference and its 95 %
interval (Student's t over the novices).

The operator is :class:`dhg.surgeons.SurgeonController`: it feels the rendered force, guidance
included, and is told what the cue means (it leans into the paper's cue, yields to the others).
It does not learn across attempts yet, so each arm is one attempt and there is no pre/post-test
protocol: the study measures the guidance's immediate effect, not retention.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Sequence
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from dhg.errors import InvalidInputError
from dhg.session import GUIDANCE_MODES

__all__ = ["ARMS", "METRICS", "Arm", "StudyResult", "parse_arms", "run_study"]


@dataclass(frozen=True)
class Arm:
    """One way of drilling: a guidance mode at a gain, or ``mode=None`` for no guidance."""

    name: str
    mode: str | None
    gain: float = 1.0


ARMS: dict[str, Arm] = {"none": Arm("none", None, 0.0)} | {m: Arm(m, m) for m in GUIDANCE_MODES}
"""The arms ``dhg study`` knows: ``none`` and one per guidance mode at gain 1."""

METRICS: tuple[tuple[str, str, float, bool], ...] = (
    ("plunge_depth_m", "plunge (mm)", 1e3, True),
    ("max_deviation_m", "max deviation (mm)", 1e3, True),
    ("mean_deviation_m", "mean deviation (mm)", 1e3, True),
    ("target_distance_m", "to B (mm)", 1e3, True),
    ("completion_time_s", "time (s)", 1.0, True),
    ("time_above_47_s", "> 47 °C (s)", 1.0, True),
    ("peak_temperature_c", "peak (°C)", 1.0, True),
    ("reached_target", "reached B", 1.0, False),
)
"""(key, label, display scale, lower is better) of the metrics a study reports."""


def parse_arms(text: str) -> list[Arm]:
    """``"none,paper,shaped"`` → arms; ``mode@gain`` sets a gain (``shaped@0.5``)."""
    arms = []
    for item in (t.strip() for t in text.split(",") if t.strip()):
        name, _, gain = item.partition("@")
        if name not in ARMS:
            raise InvalidInputError(f"unknown arm {name!r}; the arms are {', '.join(ARMS)} (mode@gain sets a gain)")
        arm = ARMS[name]
        if gain:
            try:
                g = float(gain)
            except ValueError:
                raise InvalidInputError(f"arm {item!r}: the gain after @ must be a number") from None
            if not (math.isfinite(g) and 0 <= g <= 4):
                raise InvalidInputError(f"arm {item!r}: the gain must be within 0..4")
            arm = dataclasses.replace(arm, name=item, gain=g)
        arms.append(arm)
    if not arms or arms[0].mode is not None:
        raise InvalidInputError("the first arm must be 'none', the baseline the others are compared with")
    if len({a.name for a in arms}) != len(arms):
        raise InvalidInputError(f"arms repeat: {text!r}")
    return arms


@dataclass
class StudyResult:
    """Per arm and novice, the skill metrics; and the paired statistics against the first arm."""

    arms: list[Arm]
    seeds: list[int]
    metrics: dict[str, list[dict[str, float]]]
    """Arm name → one metrics dict per seed, in ``seeds`` order."""

    def values(self, arm: str, key: str) -> np.ndarray:
        return np.array([float(m[key]) for m in self.metrics[arm]])

    def paired(self, arm: str, key: str) -> tuple[float, float, float]:
        """Mean of (arm − baseline) over the novices and its 95 % interval (Student's t)."""
        from scipy import stats

        d = self.values(arm, key) - self.values(self.arms[0].name, key)
        if len(d) < 2:
            return float(d.mean()), float("nan"), float("nan")
        half = stats.t.ppf(0.975, len(d) - 1) * d.std(ddof=1) / math.sqrt(len(d))
        return float(d.mean()), float(d.mean() - half), float(d.mean() + half)

    def markdown(self) -> str:
        """A table: per arm, each metric's mean and, for guided arms, the paired difference with
        its 95 % interval."""
        head = "| arm | " + " | ".join(label for _, label, _, _ in METRICS) + " |"
        lines = [head, "|---|" + "---:|" * len(METRICS)]
        base = self.arms[0].name
        for arm in self.arms:
            cells = []
            for key, _, scale, _ in METRICS:
                mean = self.values(arm.name, key).mean() * scale
                if arm.name == base:
                    cells.append(f"{mean:.2f}")
                else:
                    d, lo, hi = (v * scale for v in self.paired(arm.name, key))
                    cells.append(f"{mean:.2f} ({d:+.2f} [{lo:+.2f}, {hi:+.2f}])")
            lines.append(f"| {arm.name} | " + " | ".join(cells) + " |")
        return "\n".join(lines) + "\n"

    def to_json(self) -> dict[str, Any]:
        return {
            "arms": [dataclasses.asdict(a) for a in self.arms],
            "seeds": self.seeds,
            "metrics": self.metrics,
            "paired": {
                a.name: {k: self.paired(a.name, k) for k, _, _, _ in METRICS} for a in self.arms[1:]
            },
        }

    def plot(self, path: str | Path) -> Path:
        """Paired differences (arm − none) with 95 % intervals, one panel per metric."""
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        shown = [m for m in METRICS if m[0] != "reached_target"]
        fig, axes = plt.subplots(1, len(shown), figsize=(3.0 * len(shown), 3.6))
        names = [a.name for a in self.arms[1:]]
        for ax, (key, label, scale, _) in zip(axes, shown, strict=True):
            stats = [self.paired(n, key) for n in names]
            d = np.array([s[0] for s in stats]) * scale
            err = np.array([[s[0] - s[1], s[2] - s[0]] for s in stats]).T * scale
            ax.bar(range(len(names)), d, yerr=err, capsize=4, color="#4c72b0")
            ax.axhline(0.0, color="black", lw=0.8)
            ax.set_xticks(range(len(names)), names, rotation=45, ha="right")
            ax.set_title(f"Δ {label}", fontsize=9)
        fig.suptitle(f"Guided − unguided, {len(self.seeds)} virtual novices (mean, 95 % interval)")
        fig.tight_layout()
        out = Path(path)
        fig.savefig(out, dpi=110)
        plt.close(fig)
        return out


# -- the work, in worker processes --------------------------------------------------------------
_WORKER: dict[str, Any] = {}


def _init_worker(model_path: str, voxel_m: float, duration_s: float) -> None:
    import torch

    from dhg import default_phantom
    from dhg.export import load_model

    torch.set_num_threads(1)
    phantom = default_phantom(voxel_m=voxel_m)
    _WORKER.update(phantom=phantom, model=load_model(model_path), duration_s=duration_s)


def _attempt(job: tuple[int, Arm]) -> tuple[int, str, dict[str, float]]:
    from dhg.session import DrillingSession
    from dhg.surgeons import run_episode, sample_style
    from dhg.task import TaskRules

    seed, arm = job
    phantom, model = _WORKER["phantom"], _WORKER["model"]
    session = DrillingSession(phantom.volume, phantom.path)
    session.set_guidance(arm.mode or "paper", arm.gain if arm.mode else 0.0)
    style = sample_style("novice", np.random.default_rng([seed, 1]))
    rng = np.random.default_rng([seed, 1, 1])
    rules = TaskRules(max_duration_s=_WORKER["duration_s"])
    predictor = (lambda w: model.predict(w)[0]) if arm.mode else None
    cue = "match" if arm.mode == "paper" else "yield"
    ep = run_episode(session, style, rng, f"n{seed}", 0, rules, predictor=predictor, cue_meaning=cue)
    metrics = {k: float(v) for k, v in ep.metrics.items()} | {k: float(v) for k, v in ep.extra.items()}
    return seed, arm.name, metrics


def run_study(
    seeds: Sequence[int],
    arms: Sequence[Arm],
    model_path: str | Path,
    duration_s: float = 150.0,
    workers: int = 2,
    voxel_m: float = 0.5e-3,
    progress: Callable[[int, int], None] | None = None,
) -> StudyResult:
    """Runs every novice in every arm (see the module docs) and returns the metrics."""
    if not seeds:
        raise InvalidInputError("a study needs at least one novice seed")
    if not (math.isfinite(duration_s) and duration_s > 0):
        raise InvalidInputError(f"duration must be positive, got {duration_s}")
    if workers < 1:
        raise InvalidInputError(f"workers must be at least 1, got {workers}")
    jobs = [(int(s), a) for s in seeds for a in arms]
    out: dict[str, dict[int, dict[str, float]]] = {a.name: {} for a in arms}
    init = (str(model_path), voxel_m, duration_s)
    done = 0
    if workers == 1:
        _init_worker(*init)
        results = map(_attempt, jobs)
        for seed, name, m in results:
            out[name][seed] = m
            done += 1
            if progress:
                progress(done, len(jobs))
    else:
        with ProcessPoolExecutor(workers, initializer=_init_worker, initargs=init) as pool:
            for seed, name, m in pool.map(_attempt, jobs):
                out[name][seed] = m
                done += 1
                if progress:
                    progress(done, len(jobs))
    seeds = [int(s) for s in seeds]
    return StudyResult(list(arms), seeds, {a: [out[a][s] for s in seeds] for a in out})
