"""A virtual trainee that drills through a running server, feeling the forces (and guidance) it sends.

The operator model is the virtual surgeon of :mod:`dhg.operators`; here its hand is pushed by the
force the server renders (bone feedback plus any guidance), and it perceives the drill through the
server's 1 kHz force messages. It paces itself at 1 kHz on absolute deadlines.
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np
import numpy.typing as npt

from dhg.bone.planning import breakthrough_depth_from_runs
from dhg.core.errors import InvalidInputError
from dhg.core.features import TICK_S
from dhg.core.path import PlannedPath, TaskRules
from dhg.core.session import ThermalParams
from dhg.core.skill import skill_metrics
from dhg.core.surgeon import START_S_M, CueMeaning, SurgeonController
from dhg.live.client import TraineeClient, feedback_tuple
from dhg.operators.styles import sample_style

__all__ = [
    "TraineeRun",
    "drive_surgeon",
    "live_metrics",
    "planned_depth_from_info",
    "run_course",
    "run_trainee",
    "state_records",
    "states_since_reset",
]

_BODY_C = ThermalParams().body_temperature_c
"""A resting drill's temperature (°C): the core's body temperature."""


@dataclass
class TraineeRun:
    """What a networked run produced (SI units)."""

    session_id: str
    skill: str
    guidance_gain: float
    metrics: dict[str, Any]
    """Skill metrics (as :func:`dhg.core.skill.skill_metrics`) from the server's state stream."""
    latency: dict[str, float]
    """Pose → force and pose → guidance latency quantiles (s) and message counts."""
    records: npt.NDArray[np.float64]
    """(M, 11) records from the state stream: time, nine features, drill_on."""
    guidance: list[dict[str, Any]] = field(default_factory=list)
    """Guidance messages received."""
    states: list[dict[str, Any]] = field(default_factory=list)
    """State messages received."""
    poses_sent: int = 0
    wall_s: float = 0.0
    server_health: dict[str, Any] = field(default_factory=dict)
    """The server's health report after the run, when the caller asked for it."""
    burr_radius_m: float = 0.0
    """The burr (drill tip) radius the session drilled with (m)."""
    planned_breakthrough_depth_m: float | None = None
    """The tip depth (m) at which the trainee planned the first cortex to give (``None``: the
    generic 2.2 mm, for lack of a cortex on the path or of layers in the session info)."""
    guidance_mode: str = "paper"
    """The session's guidance mode."""
    attempt: int = 0
    """Which of the trainee's attempts this was (0: the first)."""
    probe: bool = False
    """Whether the server's fading schedule made this attempt a guidance-free probe."""
    fading: dict[str, Any] | None = None
    """The session's fading schedule as it stood when the attempt began (``docs/protocol.md``),
    or ``None`` without one."""


def state_records(states: list[dict[str, Any]]) -> npt.NDArray[np.float64]:
    """(M, 11) records (time, nine features, drill_on) from decoded state messages."""
    from dhg.core.protocol import FLAGS

    if not states:
        return np.empty((0, 11))
    return np.array([[s["time_s"], *s["features"], float(bool(s["flags"] & FLAGS["drill_on"]))] for s in states])


def states_since_reset(states: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """The states from the last restart of the session's clock on: a state published before a
    reset can arrive after it."""
    times = [st["time_s"] for st in states]
    return states[max((i for i in range(1, len(times)) if times[i] < times[i - 1]), default=0) :]


def planned_depth_from_info(info: dict[str, Any]) -> float | None:
    """The planned breakthrough depth (m) for a session, from the info its control query returns:
    the end of the first cortical run in ``path_layers`` less the session's burr radius. ``None``
    when the info has no layers (an older server) or the path crosses no cortex."""
    if "planned_breakthrough_depth_m" in info:  # the server's own plan (the session's guidance uses it)
        planned = info["planned_breakthrough_depth_m"]
        return None if planned is None else float(planned)
    layers = info.get("path_layers")
    if not layers:
        return None
    entry, target = np.array(info["entry_m"], dtype=float), np.array(info["target_m"], dtype=float)
    runs = [(str(r["layer"]), float(r["start_m"]), float(r["end_m"])) for r in layers]
    return breakthrough_depth_from_runs(
        runs, float(np.linalg.norm(target - entry)), float(info["burr_radius_m"]), float(info["path_layer_step_m"])
    )


def drive_surgeon(client: TraineeClient, surgeon: SurgeonController, duration_s: float) -> tuple[int, float]:
    """Runs ``surgeon`` against the client's session at 1 kHz on absolute deadlines until it
    stops or ``duration_s`` (s) have passed; returns (poses sent, wall time in s). Forces that
    answer poses sent before this call (a reset's stragglers) are not felt: until the first
    force for one of its own poses arrives, the surgeon feels a resting drill at A."""
    a = surgeon.path.entry_m
    resting = (a[0], a[1], a[2], START_S_M, 0.0, _BODY_C, 0, False, 0, False, 0.0)
    first_seq = (client.sent_seq + 1) & 0xFFFFFFFF
    period_ns = 1_000_000
    t0 = time.monotonic_ns()
    end_ns = t0 + int(duration_s * 1e9)
    sent = 0
    fresh = False
    while True:
        now = time.monotonic_ns()
        if now >= end_ns:
            break
        latest = client.force
        if latest is not None and not fresh:
            # Sequence numbers wrap at 2^32: "ours" is within the span this call has sent.
            fresh = ((latest["pose_seq"] - first_seq) & 0xFFFFFFFF) < max(sent, 1)
        if not fresh:
            latest = None
        fb = feedback_tuple(latest) if latest is not None else resting
        force = latest["force_n"] if latest is not None else (0.0, 0.0, 0.0)
        cue = latest["guidance_n"] if latest is not None else (0.0, 0.0, 0.0)
        row = surgeon.step(fb, force, cue)
        if row is None:
            break
        client.send_row(row)
        sent += 1
        deadline = t0 + sent * period_ns
        pause = deadline - time.monotonic_ns()
        if pause > 0:
            time.sleep(pause * 1e-9)
    return sent, (time.monotonic_ns() - t0) * 1e-9


def wait_for_last_state(client: TraineeClient, timeout_s: float = 2.0) -> bool:
    """Waits until a state at or after the last force's tick has arrived, so an attempt's records
    reach its end: the session ticks on without poses, so its next 10 Hz record comes within
    0.1 s of the last pose. Gives up after ``timeout_s`` (s; a closed session sends none);
    returns whether it came."""
    force = client.force
    if force is None:
        return True
    due_s = force["tick"] * TICK_S
    deadline = time.monotonic() + timeout_s
    while True:
        states = client.states
        if states and states[-1]["time_s"] >= due_s:
            return True
        if time.monotonic() >= deadline:
            return False
        time.sleep(0.005)


def live_metrics(client: TraineeClient, surgeon: SurgeonController, states: list[dict[str, Any]]) -> dict[str, Any]:
    """Skill metrics (:func:`dhg.core.skill.skill_metrics`, plus ``reached_target`` and
    ``buzz_felt_s``, the seconds a vibration was felt in the guidance) of the attempt
    ``surgeon`` drilled through the client's session, from the server's ``states`` of it."""
    records = state_records(states)
    last = states[-1] if states else None
    feedback = client.force
    metrics = skill_metrics(
        records,
        surgeon.path,
        surgeon.rules,
        final_tip_m=np.array(feedback["tip_m"]) if feedback else surgeon.path.entry_m,
        drilling_s=surgeon.drilling_s,
        plunge_depth_m=surgeon.max_plunge,
        peak_temperature_c=last["peak_temperature_c"] if last else _BODY_C,
        time_above_47_s=last["time_above_47_s"] if last else 0.0,
    )
    metrics["reached_target"] = bool(surgeon.phase == "done")
    metrics["buzz_felt_s"] = surgeon.buzz_felt_s
    return metrics


def run_trainee(
    client: TraineeClient,
    skill: Literal["expert", "novice"] = "novice",
    guidance_gain: float = 1.0,
    duration_s: float = 20.0,
    seed: int = 0,
    rules: TaskRules | None = None,
    burr_radius_m: float | None = None,
    cue_follow_per_s: float | None = None,
    breakthrough_depth_m: float | None = None,
    guidance_mode: str | None = None,
    on_start: Callable[[str], None] | None = None,
) -> TraineeRun:
    """Creates the client's session (with ``guidance_gain``; 0 = unguided), drills for up to
    ``duration_s`` (s) or until the surgeon stops at B, and returns metrics and latencies.
    The surgeon's style and noise come from ``seed``, so two runs with one seed are paired.
    ``burr_radius_m`` (m) swaps the session's burr first; ``None`` keeps the server's.
    ``cue_follow_per_s`` (1/s) overrides how briskly the surgeon leans into the guidance cue
    (:attr:`dhg.core.surgeon.SurgeonStyle.cue_follow_per_s`); 0 is a passive hand that only feels it.
    ``breakthrough_depth_m`` (m) is where the trainee's plan says the first cortex gives
    (:func:`dhg.bone.planning.planned_breakthrough_depth_m`); ``None`` reads it off the planned layers
    the server reports for the session (``path_layers``), or, where it reports none, uses the
    surgeons' generic 2.2 mm."""
    return run_course(
        client,
        1,
        skill,
        guidance_gain,
        duration_s,
        seed,
        rules=rules,
        burr_radius_m=burr_radius_m,
        cue_follow_per_s=cue_follow_per_s,
        breakthrough_depth_m=breakthrough_depth_m,
        guidance_mode=guidance_mode,
        on_start=on_start,
    )[0]


def _drill_attempt(
    client: TraineeClient,
    surgeon: SurgeonController,
    duration_s: float,
    info: dict[str, Any],
    *,
    skill: Literal["expert", "novice"],
    gain: float,
    mode: str,
    attempt: int,
    breakthrough_depth_m: float | None,
) -> TraineeRun:
    """One attempt of :func:`run_course`: ``surgeon`` drills the client's session (created or
    reset with the reply ``info``) for up to ``duration_s`` (s), and the attempt is returned with
    its metrics, latencies and 10 Hz records (``breakthrough_depth_m``: the depth the surgeon
    planned for, as :attr:`TraineeRun.planned_breakthrough_depth_m` reports it)."""
    schedule = info.get("fading")
    sent, wall_s = drive_surgeon(client, surgeon, duration_s)
    wait_for_last_state(client)
    states = states_since_reset(list(client.states))
    metrics = live_metrics(client, surgeon, states)
    return TraineeRun(
        session_id=client.session_id,
        skill=skill,
        guidance_gain=gain,
        metrics=metrics,
        latency=client.latency_summary(),
        records=state_records(states),
        guidance=list(client.guidance),
        states=states,
        poses_sent=sent,
        wall_s=wall_s,
        burr_radius_m=float(info["burr_radius_m"]),
        planned_breakthrough_depth_m=breakthrough_depth_m,
        guidance_mode=mode,
        attempt=attempt,
        probe=bool(schedule and schedule.get("probe")),
        fading=schedule,
    )


def run_course(
    client: TraineeClient,
    attempts: int,
    skill: Literal["expert", "novice"] = "novice",
    guidance_gain: float = 1.0,
    duration_s: float = 20.0,
    seed: int = 0,
    fading: dict[str, Any] | None = None,
    rules: TaskRules | None = None,
    burr_radius_m: float | None = None,
    cue_follow_per_s: float | None = None,
    breakthrough_depth_m: float | None = None,
    guidance_mode: str | None = None,
    on_start: Callable[[str], None] | None = None,
    on_attempt: Callable[[TraineeRun], None] | None = None,
) -> list[TraineeRun]:
    """``attempts`` attempts of one trainee at the client's session, as :func:`run_trainee` drills
    one: the session is created for the first and reset before each next (a recorder starts a new
    episode for each). The trainee learns between attempts from the plunge and deviation it
    experienced (:class:`dhg.operators.models.Learner`, as the novices of ``dhg study`` do), so later
    attempts are not repeats of the first.

    With ``fading`` (the schedule params of ``set_fading``; ``{}`` for the server's defaults) the
    server sets each attempt's gain from the last attempt's errors, and every ``probe_every``-th
    attempt is guidance-free (``TraineeRun.probe``); ``guidance_gain`` is then the first
    attempt's. ``on_attempt`` is called with each finished attempt."""
    from dhg.operators.models import Learner

    if attempts < 1:
        raise InvalidInputError(f"attempts must be at least 1, got {attempts}")
    rules = rules or TaskRules()
    if cue_follow_per_s is not None and not (math.isfinite(cue_follow_per_s) and cue_follow_per_s >= 0):
        raise InvalidInputError(f"cue_follow_per_s must be a finite rate >= 0 (1/s), got {cue_follow_per_s!r}")
    info = client.create(guidance_gain=guidance_gain, burr_radius_m=burr_radius_m, guidance_mode=guidance_mode)
    if fading is not None:
        info = client.set_fading({"start_gain": guidance_gain, **fading})
    mode = str(info["guidance_mode"])
    if on_start is not None:
        on_start(mode)
    path = PlannedPath(np.array(info["entry_m"]), np.array(info["target_m"]))
    if breakthrough_depth_m is None:
        breakthrough_depth_m = planned_depth_from_info(info)
    rng = np.random.default_rng(seed)
    style = sample_style(skill, rng)
    if cue_follow_per_s is not None:
        style = dataclasses.replace(style, cue_follow_per_s=float(cue_follow_per_s))
    # Told what the cue means: match the expert's force (the paper's cue) or yield to it (the others).
    cue: CueMeaning = "match" if mode == "paper" else "yield"
    learner = Learner()
    runs: list[TraineeRun] = []
    for attempt in range(attempts):
        if attempt > 0:
            info = client.control("reset")  # ends the last attempt: a fading schedule sets this one's gain
            rng = np.random.default_rng([seed, attempt])
        gain = float(info.get("guidance_gain", guidance_gain))
        client.states.clear()
        client.guidance.clear()
        surgeon = SurgeonController(
            path, learner.style(style), rng, rules, breakthrough_depth_m=breakthrough_depth_m, cue_meaning=cue
        )
        run = _drill_attempt(
            client,
            surgeon,
            duration_s,
            info,
            skill=skill,
            gain=gain,
            mode=mode,
            attempt=attempt,
            breakthrough_depth_m=breakthrough_depth_m,
        )
        learner.update(float(run.metrics["plunge_depth_m"]), float(run.metrics["max_deviation_m"]))
        runs.append(run)
        if on_attempt is not None:
            on_attempt(run)
    return runs
