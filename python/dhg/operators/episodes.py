"""One drilling attempt by a virtual surgeon through an offline session, with the model queried
at every 10 Hz record as ``dhg-serve`` queries it."""

from __future__ import annotations

from collections.abc import Callable, Generator
from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt

from dhg.bone.planning import planned_breakthrough_depth_m
from dhg.core.features import FEATURE_NAMES
from dhg.core.path import PlannedPath, TaskRules
from dhg.core.protocol import WINDOW_RECORDS
from dhg.core.session import DrillingSession
from dhg.core.skill import skill_metrics
from dhg.core.surgeon import CueMeaning, Skill, SurgeonController, SurgeonStyle

__all__ = ["Episode", "drill_episode", "run_episode"]


@dataclass
class Episode:
    """One drilling attempt: its 10 Hz records, optional 1 kHz stream, and skill metrics."""

    subject: str
    skill: Skill
    attempt: int
    style: SurgeonStyle
    records: npt.NDArray[np.float64]
    """(M, 11): columns :data:`dhg.core.features.RECORD_COLUMNS`."""
    metrics: dict[str, float | bool]
    raw_poses: npt.NDArray[np.float64] | None = None
    """(N, 9) 1 kHz poses (:data:`dhg.core.features.POSE_COLUMNS`), if kept."""
    raw_forces_n: npt.NDArray[np.float64] | None = None
    """(N, 3) 1 kHz device forces (N), if kept."""
    extra: dict[str, float] = field(default_factory=dict)


def run_episode(
    session: DrillingSession,
    style: SurgeonStyle,
    rng: np.random.Generator,
    subject: str = "s0",
    attempt: int = 0,
    rules: TaskRules | None = None,
    keep_raw: bool = False,
    predictor: Callable[[npt.NDArray[np.float64]], npt.ArrayLike] | None = None,
    cue_meaning: CueMeaning = "match",
    rest_device: bool = False,
) -> Episode:
    """Drills the session's planned path once with a surgeon of ``style``. The session is reset
    first (with ``rest_device``, the device too: zero force and cold motors, so that the attempt
    replays exactly through a fresh session). Deterministic for the generator's state.

    With a ``predictor`` (a window of the last 20 records' nine features, (20, 9), to the predicted
    expert force (3,) in N; ``dhg.learning.torchscript.load_model(...).predict`` on one window), the model is
    queried at every 10 Hz record, as ``dhg-serve`` queries it, and the session renders guidance
    in whatever mode and gain it was given (:meth:`DrillingSession.set_guidance`); the window is
    padded at the front with the first record until 20 exist, as the server pads it. Offline, the
    reply is applied at once (the server's takes the model's latency, about 5–10 ms). The surgeon
    feels the guidance and reads it as ``cue_meaning`` says (:class:`SurgeonController`).

    :func:`drill_episode` is the same attempt as a generator, for callers that answer the model's
    queries of many attempts at once."""
    steps = drill_episode(
        session, style, rng, subject, attempt, rules, keep_raw, predictor is not None, cue_meaning, rest_device
    )
    try:
        window = next(steps)
        while True:
            assert predictor is not None
            window = steps.send(np.asarray(predictor(window), dtype=float).reshape(3))
    except StopIteration as done:
        return done.value


def drill_episode(
    session: DrillingSession,
    style: SurgeonStyle,
    rng: np.random.Generator,
    subject: str = "s0",
    attempt: int = 0,
    rules: TaskRules | None = None,
    keep_raw: bool = False,
    guided: bool = False,
    cue_meaning: CueMeaning = "match",
    rest_device: bool = False,
) -> Generator[npt.NDArray[np.float64], npt.NDArray[np.float64], Episode]:
    """:func:`run_episode` as a generator: when ``guided``, it yields the model's window (20, 9)
    at every 10 Hz record and takes the predicted expert force (3,) in N by ``send``; its return
    value (``StopIteration.value``) is the :class:`Episode`. The yielded array is reused: copy it
    to keep it past the next ``send``."""
    rules = rules or TaskRules()
    session.reset(rest_device)
    path: PlannedPath = session.path
    planned = planned_breakthrough_depth_m(session.volume, path, session.config.burr_radius_m)
    surgeon = SurgeonController(
        path, style, rng, rules, breakthrough_depth_m=planned, cue_meaning=cue_meaning, keep_raw=keep_raw
    )
    records: list[npt.NDArray[np.float64]] = []
    window = np.empty((WINDOW_RECORDS, len(FEATURE_NAMES)))
    while (record := session.drive(surgeon, guided)) is not None:
        records.append(record)
        if guided:
            recent = records[-WINDOW_RECORDS:]
            pad = WINDOW_RECORDS - len(recent)
            window[:pad] = recent[0][1:10]
            for i, r in enumerate(recent):
                window[pad + i] = r[1:10]
            predicted = yield window
            session.set_prediction((float(predicted[0]), float(predicted[1]), float(predicted[2])))
    raw = surgeon.raw()
    raw_poses, raw_forces = raw if raw is not None else (None, None)
    rec = np.array(records) if records else np.empty((0, 11))
    st = session.state
    metrics = skill_metrics(
        rec,
        path,
        rules,
        final_tip_m=st.tip_m,
        drilling_s=surgeon.drilling_s,
        plunge_depth_m=surgeon.max_plunge,
        peak_temperature_c=st.peak_temperature_c,
        time_above_47_s=st.time_above_47_s,
        forces_n=raw_forces,
    )
    return Episode(
        subject=subject,
        skill=style.skill,
        attempt=attempt,
        style=style,
        records=rec,
        metrics=metrics,
        raw_poses=raw_poses,
        raw_forces_n=raw_forces,
        extra={"reached_target": float(surgeon.phase == "done"), "buzz_felt_s": surgeon.buzz_felt_s},
    )
