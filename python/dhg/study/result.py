"""A study's results: every attempt, the paired statistics (mean difference and its 95 % interval,
Student's t over the novices), the Markdown tables and the figure."""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from dhg.study.design import METRICS, Arm, Protocol

__all__ = ["Attempt", "StudyResult"]


Attempt = dict[str, Any]
"""One attempt: ``phase`` (pre, train, post), ``index`` (0.. in the protocol), ``gain`` (the gain
it was drilled at), ``probe`` (a fading probe), and the skill metrics (SI units); a test measured
with several replicates holds their mean, and each replicate's metrics under ``replicates``."""


@dataclass
class StudyResult:
    """Per arm and novice, every attempt of the protocol; paired statistics against the first arm."""

    arms: list[Arm]
    seeds: list[int]
    attempts: dict[str, list[list[Attempt]]]
    """Arm name → per seed (in ``seeds`` order) its attempts in protocol order (the shared
    pre-test first)."""
    operator: str = "impedance"
    protocol: Protocol = dataclasses.field(default_factory=Protocol)

    def values(self, arm: str, key: str, phase: str = "train", which: int = 0) -> np.ndarray:
        """Per seed, ``key`` of the ``which``-th attempt of ``phase`` (-1: the last)."""
        return np.array([float([a for a in atts if a["phase"] == phase][which][key]) for atts in self.attempts[arm]])

    def paired(self, arm: str, key: str, phase: str = "train") -> tuple[float, float, float]:
        """Mean over the novices of (arm − baseline) in the first attempt of ``phase``, and its 95 %
        interval (Student's t)."""
        return _t_interval(self.values(arm, key, phase) - self.values(self.arms[0].name, key, phase))

    def learning(self, arm: str, key: str) -> tuple[float, float, float]:
        """Mean of post-test − pre-test within ``arm``, and its 95 % interval."""
        return _t_interval(self.values(arm, key, "post") - self.values(arm, key, "pre"))

    def markdown(self) -> str:
        """Three tables: the first training attempt (guidance's immediate effect) and the
        post-test, each per arm the mean and, for guided arms, the paired difference with 'none'
        [95 % interval]; then post − pre within each arm."""
        base = self.arms[0].name
        out = []
        for title, phase in (
            ("First training attempt (guidance on; the same learned state in every arm)", "train"),
            ("Post-test (guidance off, after training)", "post"),
        ):
            out += [f"**{title}**", "", _head(), _rule()]
            for arm in self.arms:
                cells = []
                for key, _, scale, _ in METRICS:
                    mean = self.values(arm.name, key, phase).mean() * scale
                    if arm.name == base:
                        cells.append(f"{mean:.2f}")
                    else:
                        d, lo, hi = (v * scale for v in self.paired(arm.name, key, phase))
                        cells.append(f"{mean:.2f} ({d:+.2f} [{lo:+.2f}, {hi:+.2f}])")
                out.append(f"| {arm.name} | " + " | ".join(cells) + " |")
            out.append("")
        out += ["**Learning: post-test − pre-test within each arm**", "", _head(), _rule()]
        for arm in self.arms:
            cells = []
            for key, _, scale, _ in METRICS:
                d, lo, hi = (v * scale for v in self.learning(arm.name, key))
                cells.append(f"{d:+.2f} [{lo:+.2f}, {hi:+.2f}]")
            out.append(f"| {arm.name} | " + " | ".join(cells) + " |")
        return "\n".join(out) + "\n"

    def to_json(self) -> dict[str, Any]:
        keys = [k for k, _, _, _ in METRICS]
        return {
            "operator": self.operator,
            "protocol": dataclasses.asdict(self.protocol),
            "arms": [dataclasses.asdict(a) for a in self.arms],
            "seeds": self.seeds,
            "attempts": self.attempts,
            "paired_first_training": {a.name: {k: self.paired(a.name, k) for k in keys} for a in self.arms[1:]},
            "paired_post": {a.name: {k: self.paired(a.name, k, "post") for k in keys} for a in self.arms[1:]},
            "learning": {a.name: {k: self.learning(a.name, k) for k in keys} for a in self.arms},
        }

    def plot(self, path: str | Path) -> Path:
        """Paired differences (arm − none) with 95 % intervals, per metric: the first training
        attempt (filled) and the post-test (hatched)."""
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        shown = [m for m in METRICS if m[0] != "reached_target"]
        cols = 4
        rows = -(-len(shown) // cols)
        fig, axes = plt.subplots(rows, cols, figsize=(3.2 * cols, 3.4 * rows), squeeze=False)
        names = [a.name for a in self.arms[1:]]
        x = np.arange(len(names))
        for ax, (key, label, scale, _) in zip(axes.flat, shown, strict=False):
            for phase, dx, color, legend in (
                ("train", -0.2, "#4c72b0", "guided (1st training attempt)"),
                ("post", 0.2, "#dd8452", "post-test (unguided)"),
            ):
                stats = [self.paired(n, key, phase) for n in names]
                d = np.array([s[0] for s in stats]) * scale
                err = np.nan_to_num(np.array([[s[0] - s[1], s[2] - s[0]] for s in stats]).T * scale)
                ax.bar(x + dx, d, 0.4, yerr=err, capsize=3, color=color, label=legend)
            ax.axhline(0.0, color="black", lw=0.8)
            ax.set_xticks(x, names, rotation=45, ha="right")
            ax.set_title(f"Δ {label}", fontsize=9)
        for ax in list(axes.flat)[len(shown) :]:
            ax.axis("off")
        axes.flat[0].legend(fontsize=7)
        fig.suptitle(
            f"Arm − unguided, {len(self.seeds)} virtual novices ({self.operator} operator; mean, 95 % interval)"
        )
        fig.tight_layout()
        out = Path(path)
        fig.savefig(out, dpi=110)
        plt.close(fig)
        return out


def _head() -> str:
    return "| arm | " + " | ".join(label for _, label, _, _ in METRICS) + " |"


def _rule() -> str:
    return "|---|" + "---:|" * len(METRICS)


def _t_interval(d: np.ndarray) -> tuple[float, float, float]:
    from scipy import stats

    if len(d) < 2:
        return float(d.mean()), float("nan"), float("nan")
    half = stats.t.ppf(0.975, len(d) - 1) * d.std(ddof=1) / math.sqrt(len(d))
    return float(d.mean()), float(d.mean() - half), float(d.mean() + half)


# -- the attempts: one job per novice and arm -----------------------------------------------------
Window = np.ndarray
"""A model query: the last 20 records' nine features, (20, 9)."""
