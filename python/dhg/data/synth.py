"""Synthetic demonstrations: virtual surgeons drilling the planned path, written as a dataset.

The paper's data (six people drilling A → B, ~10.6k records at 10 Hz) is private. This makes
its own: ``subjects`` experts and ``novices`` novices, each with a style drawn once
(:func:`dhg.operators.styles.sample_style`), each drilling ``attempts`` times. Each subject's best
attempt is marked, as the paper selected. Deterministic for a seed.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np

from dhg.core.path import PlannedPath, TaskRules
from dhg.core.session import DrillingSession, SessionConfig
from dhg.core.version import __version__
from dhg.core.volume import Volume
from dhg.data.dataset import EpisodeInput, volume_card
from dhg.operators.episodes import Episode, run_episode
from dhg.operators.styles import sample_style

__all__ = ["attempt_score", "synthesize"]


def attempt_score(metrics: dict[str, Any]) -> float:
    """Lower is better: how the best attempt of a subject is chosen. Completing the task comes
    first; then time (per minute), deviation and distance to target (per mm), plunge (per 5 mm)
    and time above 47 °C (per 10 s) count alike."""
    return (
        (0.0 if metrics["completed"] else 1e3)
        + metrics["completion_time_s"] / 60.0
        + metrics["mean_deviation_m"] * 1e3
        + metrics["target_distance_m"] * 1e3
        + metrics["plunge_depth_m"] * 1e3 / 5.0
        + metrics["time_above_47_s"] / 10.0
    )


def synthesize(
    volume: Volume,
    path: PlannedPath,
    subjects: int = 6,
    attempts: int = 3,
    novices: int = 2,
    seed: int = 0,
    keep_raw: bool = False,
    config: SessionConfig | None = None,
    rules: TaskRules | None = None,
    progress: Callable[[int, int], None] | None = None,
) -> tuple[list[EpisodeInput], dict[str, Any]]:
    """Runs every subject's attempts and returns the episodes and the card sections that describe
    how they were made. Subject ids are ``e0``… for experts and ``n0``… for novices."""
    if subjects < 0 or novices < 0 or attempts < 1 or subjects + novices < 1:
        raise ValueError(f"need at least one subject and one attempt, got {subjects=}, {novices=}, {attempts=}")
    rules = rules or TaskRules()
    session = DrillingSession(volume, path, config)
    plan = [("expert", f"e{i}", i) for i in range(subjects)] + [("novice", f"n{i}", i) for i in range(novices)]
    total = len(plan) * attempts
    done = 0
    episodes: list[EpisodeInput] = []
    for skill, subject_id, index in plan:
        style_rng = np.random.default_rng([seed, 0 if skill == "expert" else 1, index])
        style = sample_style(skill, style_rng)  # type: ignore[arg-type]
        runs: list[Episode] = []
        for attempt in range(attempts):
            rng = np.random.default_rng([seed, 0 if skill == "expert" else 1, index, attempt + 1])
            runs.append(run_episode(session, style, rng, subject_id, attempt, rules, keep_raw, rest_device=True))
            done += 1
            if progress is not None:
                progress(done, total)
        best = min(range(len(runs)), key=lambda i: attempt_score(runs[i].metrics))
        for i, ep in enumerate(runs):
            episodes.append(
                EpisodeInput(
                    subject_id=subject_id,
                    skill=skill,
                    attempt=ep.attempt,
                    records=ep.records,
                    metrics=ep.metrics,
                    style=style.to_dict(),
                    best_of_subject=i == best,
                    raw_poses=ep.raw_poses,
                    raw_forces_n=ep.raw_forces_n,
                )
            )
    card = {
        "generator": {
            "name": "dhg.data.synth (virtual surgeons)",
            "dhg_version": __version__,
            "seed": int(seed),
            "subjects": int(subjects),
            "novices": int(novices),
            "attempts": int(attempts),
        },
        "volume": volume_card(volume),
        "planned_path": path.to_dict(),
        "task_rules": rules.to_dict(),
        "session_config": session.config.to_flat_dict(),
    }
    return episodes, card
