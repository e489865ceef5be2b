"""Operators that drive the drill through the simulator.

Virtual surgeons (:func:`run_episode`): a human-like operator that drills the planned path through
a session at 1 kHz. It models a hand holding the stylus: a mass with arm damping, driven by the
push the surgeon intends and pushed back by the device force. At 1 kHz, what the surgeon *does*
depends on what they *perceived* one reaction delay ago. The phases are:

1. approach: a minimum-jerk reach (Flash & Hogan 1985) from a resting point to 3 mm before A;
2. align and spin up the drill;
3. feed: the push is regulated towards a preferred feed but never exceeds a layer-dependent
   ceiling (firm in cortical bone, light in cancellous bone and marrow); experts ease off as the
   cortex thins, having read from the planning CT where along the path it ends
   (:func:`planned_breakthrough_depth_m`), and stop to let the drill cool as the tip nears
   47 °C; novices hesitate;
4. breakthrough: once the surgeon feels the cortex give (after the reaction delay), they hold
   and pull back. A late reaction and a loose arm make a deeper plunge;
5. stop near B and switch the drill off.

The surgeon's 1 kHz step is the core's (``bone_sim::surgeon``, wrapped by
:class:`SurgeonController`), so an offline attempt runs at the core's speed
(:meth:`dhg.DrillingSession.drive`); the styles are drawn here (:func:`sample_style`).

Guidance (``dhg trainee``): the server adds a cue to the rendered force, the predicted expert
force minus the trainee's (Fekri et al. 2021). Along the drill this is a force-matching cue: it
pushes back where the expert pressed harder and pulls in where the expert eased off. A purely
passive hand would read "press harder" as resistance and back away. So a trainee who has been
told what the cue means leans into it: after the reaction delay, the push grows while the cue
pushes back and shrinks while it pulls in, until the cue is nulled
(:attr:`SurgeonStyle.cue_follow_per_s`).

Human motor behaviour: physiological tremor of 8–12 Hz (Elble 1990), signal-dependent noise on
the push (Harris & Wolpert 1998), a reaction delay to force changes, and lateral drift from
limited steadiness. Styles are drawn per subject (:func:`sample_style`).

Also here are two operators without human behaviour: :func:`straight_line_drill` erodes along
the path without force feedback, and :func:`scripted_stylus` pushes a stylus along the path.
"""

from __future__ import annotations

from collections.abc import Callable, Generator, Iterable
from dataclasses import asdict, dataclass, field
from typing import Literal

import numpy as np
import numpy.typing as npt

from dhg import _bone_sim
from dhg.errors import InvalidInputError
from dhg.layers import Layer
from dhg.protocol import WINDOW_RECORDS
from dhg.session import DrillingSession
from dhg.task import PlannedPath, TaskRules
from dhg.volume import DrilledVolume, Volume

__all__ = [
    "DrillRun",
    "Episode",
    "SurgeonController",
    "SurgeonStyle",
    "breakthrough_depth_from_runs",
    "layer_runs",
    "planned_breakthrough_depth_m",
    "run_episode",
    "sample_style",
    "scripted_stylus",
    "skill_metrics",
    "straight_line_drill",
]

Skill = Literal["expert", "novice"]
CueMeaning = Literal["match", "yield", "felt"]

_CONSTANTS = _bone_sim.surgeon_constants()
HAND_MASS_KG: float = _CONSTANTS["HAND_MASS_KG"]
"""Effective mass of hand and stylus (kg); defined in the core (``bone_sim::surgeon``)."""
TRACK_STIFFNESS_N_PER_M: float = _CONSTANTS["TRACK_STIFFNESS_N_PER_M"]
"""How stiffly the arm follows an intended position (N/m), for approach and holding."""
LATERAL_STIFFNESS_N_PER_M: float = _CONSTANTS["LATERAL_STIFFNESS_N_PER_M"]
"""How stiffly the arm holds the drill on the path laterally (N/m)."""
GENERIC_BREAKTHROUGH_DEPTH_M: float = _CONSTANTS["GENERIC_BREAKTHROUGH_DEPTH_M"]
"""Tip depth at which a surgeon without a plan expects the first cortex to give (m)."""
AIM_FOLLOW_S: float = _CONSTANTS["AIM_FOLLOW_S"]
"""Time constant (s) with which the arm's aim follows the felt hand position."""
PUSH_MARGIN_N: float = _CONSTANTS["PUSH_MARGIN_N"]
"""How much harder than the resistance they feel (N, one reaction delay ago) a subject pushes."""
MAX_PUSH_N: float = _CONSTANTS["MAX_PUSH_N"]
"""Most axial push any subject applies, however strongly a guidance cue asks for more (N)."""
YIELD_SETTLE_S: float = _CONSTANTS["YIELD_SETTLE_S"]
"""How fast a surgeon who yields to the guidance settles onto what it asks (s)."""
CUE_LEAK_PER_S: float = _CONSTANTS["CUE_LEAK_PER_S"]
"""How fast the lean a cue built up fades once the cue is gone (1/s)."""
EXPERT_ARM_N_PER_M = (210.0, 260.0)
"""Range of the experts' arm stiffness (N/m); see :attr:`SurgeonStyle.arm_stiffness_n_per_m`."""
NOVICE_ARM_N_PER_M = (100.0, 130.0)
"""Range of the novices' arm stiffness (N/m): a looser arm."""


@dataclass(frozen=True)
class SurgeonStyle:
    """One subject's style and motor parameters (SI units; forces are device newtons)."""

    skill: Skill
    push_cortical_n: float
    """Most the subject pushes in cortical bone (N on the device)."""
    push_soft_n: float
    """Most the subject pushes in cancellous bone and marrow (N)."""
    feed_m_s: float
    """Preferred feed rate where the bone allows it (m/s)."""
    feed_gain: float
    """How briskly the push is adjusted towards the preferred feed (1 = an expert's)."""
    reaction_delay_s: float
    """Delay between a change in what they feel and their response (s)."""
    hand_damping_n_s_per_m: float
    """Arm co-contraction: damping of sudden hand motion (N·s/m)."""
    tremor_m: float
    """Amplitude of physiological tremor (m)."""
    tremor_hz: float
    """Tremor frequency (Hz), 8–12."""
    noise_fraction: float
    """Signal-dependent noise: SD of the push as a fraction of the push."""
    drift_m: float
    """Lateral wander of the aim (SD, m): steadiness."""
    anticipates_breakthrough: bool
    """Eases off to the light push as the cortex thins (experts)."""
    anticipation_m: float
    """How far before the planned breakthrough depth the subject eases off (m)."""
    hesitations_per_s: float
    """Rate of pauses while feeding (1/s)."""
    hesitation_s: float
    """Length of a pause (s)."""
    caution_temp_c: float
    """Above this tip temperature the subject stops feeding to let the drill cool (°C)."""
    stop_margin_m: float
    """How far before B the subject aims to stop (m; negative = past B)."""
    spindle_rpm: float
    """Spindle speed used (rpm)."""
    cue_follow_per_s: float = 0.0
    """How briskly the subject leans into a guidance cue (1/s): a cue pushing the drill back
    (the expert pressed harder) adds push, one pulling it in takes push away, at this rate times
    the cue (N) per second, until the cue is nulled. 0 = a passive hand that only feels the cue."""
    arm_stiffness_n_per_m: float = TRACK_STIFFNESS_N_PER_M
    """Stiffness of the arm around the point it pushes towards (N/m). The push is made by aiming
    the hand just ahead of where it was felt one reaction delay ago (an equilibrium point,
    Feldman 1986; Bizzi et al. 1992), so when the bone gives the hand travels about push /
    stiffness before the reaction stops it."""
    ease_fraction: float = 1.0
    """Fraction of the cortical push kept while easing off before the planned breakthrough."""
    hand_mass_kg: float = HAND_MASS_KG
    """Effective mass of hand, arm and stylus at the stylus tip (kg)."""
    lateral_stiffness_n_per_m: float = LATERAL_STIFFNESS_N_PER_M
    """How stiffly the arm holds the drill on its aim across the path (N/m)."""

    def to_dict(self) -> dict[str, float | str | bool]:
        """JSON-ready form."""
        return asdict(self)


def sample_style(skill: Skill, rng: np.random.Generator) -> SurgeonStyle:
    """Draws a subject of the given skill. Experts push firmly in cortex and ease off before it
    gives, react in 0.10–0.16 s and hold steady. Novices push timidly, do not anticipate the
    breakthrough, react in 0.25–0.40 s with a loose arm, wander, hesitate and ignore heat."""
    u = rng.uniform
    if skill == "expert":
        return SurgeonStyle(
            skill="expert",
            push_cortical_n=u(2.2, 2.7),
            push_soft_n=u(0.25, 0.4),
            feed_m_s=u(1.8e-3, 2.6e-3),
            feed_gain=u(0.9, 1.1),
            reaction_delay_s=u(0.10, 0.16),
            hand_damping_n_s_per_m=u(17.0, 25.0),
            tremor_m=u(0.05e-3, 0.12e-3),
            tremor_hz=u(8.0, 12.0),
            noise_fraction=u(0.04, 0.08),
            drift_m=u(0.1e-3, 0.3e-3),
            anticipates_breakthrough=True,
            hesitations_per_s=0.0,
            hesitation_s=0.0,
            caution_temp_c=u(44.0, 46.0),
            stop_margin_m=u(0.3e-3, 1.2e-3),
            spindle_rpm=u(1100.0, 1400.0),
            cue_follow_per_s=3.0,
            anticipation_m=u(0.2e-3, 0.6e-3),  # drawn last: the draws above stay as they were
            arm_stiffness_n_per_m=u(EXPERT_ARM_N_PER_M[0], EXPERT_ARM_N_PER_M[1]),
            ease_fraction=u(0.78, 0.92),
        )
    if skill == "novice":
        return SurgeonStyle(
            skill="novice",
            push_cortical_n=u(1.65, 2.15),
            push_soft_n=u(0.3, 0.45),
            feed_m_s=u(0.7e-3, 1.1e-3),
            feed_gain=u(0.3, 0.5),
            reaction_delay_s=u(0.25, 0.40),
            hand_damping_n_s_per_m=u(7.0, 11.0),
            tremor_m=u(0.2e-3, 0.4e-3),
            tremor_hz=u(8.0, 12.0),
            noise_fraction=u(0.15, 0.30),
            drift_m=u(0.8e-3, 1.6e-3),
            anticipates_breakthrough=False,
            hesitations_per_s=u(0.05, 0.10),
            hesitation_s=u(1.5, 3.0),
            caution_temp_c=u(55.0, 60.0),
            stop_margin_m=u(-2.5e-3, 0.0),
            spindle_rpm=u(900.0, 1600.0),
            cue_follow_per_s=2.0,
            anticipation_m=0.0,
            arm_stiffness_n_per_m=u(NOVICE_ARM_N_PER_M[0], NOVICE_ARM_N_PER_M[1]),
        )
    raise ValueError(f"skill must be 'expert' or 'novice', got {skill!r}")


@dataclass
class Episode:
    """One drilling attempt: its 10 Hz records, optional 1 kHz stream, and skill metrics."""

    subject: str
    skill: Skill
    attempt: int
    style: SurgeonStyle
    records: npt.NDArray[np.float64]
    """(M, 11): columns :data:`dhg.features.RECORD_COLUMNS`."""
    metrics: dict[str, float | bool]
    raw_poses: npt.NDArray[np.float64] | None = None
    """(N, 9) 1 kHz poses (:data:`dhg.features.POSE_COLUMNS`), if kept."""
    raw_forces_n: npt.NDArray[np.float64] | None = None
    """(N, 3) 1 kHz device forces (N), if kept."""
    extra: dict[str, float] = field(default_factory=dict)


def _axis_quaternion(d: npt.ArrayLike) -> tuple[float, float, float, float]:
    q = _bone_sim.axis_quaternion([float(x) for x in np.asarray(d, dtype=float).ravel()])
    return (q[0], q[1], q[2], q[3])


class SurgeonController:
    """The virtual surgeon's decisions and hand, one 1 kHz tick at a time (the core's
    ``bone_sim::surgeon``; this wraps it).

    :meth:`step` takes what the stylus reports this tick (the session feedback tuple: tip x, y, z
    (m), depth (m), deviation (m), temperature (°C), layer id, cutting, breakthroughs, plunging,
    plunge depth (m)) and the force felt (N), and returns the next pose row, or ``None`` once the
    surgeon has finished. The surgeon acts on what it perceived one reaction delay ago. It drives
    a local session (:func:`run_episode`, through :meth:`dhg.DrillingSession.drive`) and a remote server
    (``dhg trainee``) alike.

    ``breakthrough_depth_m`` is the tip depth along A→B (m) at which the plan shows the burr
    leaving the first cortex (:func:`planned_breakthrough_depth_m`); anticipating surgeons ease
    off :attr:`SurgeonStyle.anticipation_m` before it.

    ``cue_meaning`` is what the surgeon was told the guidance means: ``"match"`` (the paper's
    force-matching cue: lean into a cue that pushes the drill back, ease off one that pulls it in),
    ``"yield"`` (guidance that shapes the motion, as the corridor, brake and shaped modes do:
    ease off where it resists, go with it where it pulls) or ``"felt"`` (nothing: the cue acts
    on the hand only through the arm's impedance, as any other force does).

    Every random draw of the attempt comes from one seed taken from ``rng``.
    """

    def __init__(
        self,
        path: PlannedPath,
        style: SurgeonStyle,
        rng: np.random.Generator,
        rules: TaskRules | None = None,
        breakthrough_depth_m: float | None = None,
        cue_meaning: CueMeaning = "match",
        keep_raw: bool = False,
    ) -> None:
        if cue_meaning not in ("match", "yield", "felt"):
            raise ValueError(f"cue_meaning must be 'match', 'yield' or 'felt', got {cue_meaning!r}")
        self.style, self.path = style, path
        self.rules = rules or TaskRules()
        self._c = _bone_sim.SurgeonController(
            [float(x) for x in path.entry_m],
            [float(x) for x in path.target_m],
            style.to_dict(),
            int(rng.integers(0, 2**63)),
            float(self.rules.max_duration_s),
            None if breakthrough_depth_m is None else float(breakthrough_depth_m),
            cue_meaning,
            keep_raw,
        )

    @property
    def done(self) -> bool:
        """Whether the surgeon has finished (stopped at B, or ran out of time)."""
        return bool(self._c.done)

    @property
    def phase(self) -> str:
        """``approach``, ``align``, ``feed``, ``stop`` or ``done``."""
        return str(self._c.phase)

    @property
    def drilling_s(self) -> float:
        """Time from drill start to drill stop (s), as far as the run has come."""
        return float(self._c.drilling_s)

    @property
    def max_plunge(self) -> float:
        """The deepest plunge felt so far (m)."""
        return float(self._c.max_plunge_m)

    @property
    def push(self) -> float:
        """The push the surgeon means to make along A→B (N), before the lean into a cue."""
        return float(self._c.push_n)

    @property
    def lean(self) -> float:
        """The push added in response to the guidance cue (N)."""
        return float(self._c.lean_n)

    @property
    def max_ticks(self) -> int:
        """The most 1 ms ticks the attempt may last."""
        return int(self._c.max_ticks)

    def step(
        self,
        feedback: tuple,
        force_n: tuple[float, float, float],
        cue_n: tuple[float, float, float] = (0.0, 0.0, 0.0),
    ) -> tuple[float, ...] | None:
        """The pose row (x, y, z, qw, qx, qy, qz, drill_on, spindle_rpm) for this tick, or None.

        ``force_n`` is the whole force the device renders (N, world frame); ``cue_n`` is the
        guidance share of it (N), which the surgeon also reads as an instruction (see the class
        docs). Without guidance it is zero."""
        row = self._c.step(feedback, force_n, cue_n)
        return None if row is None else tuple(row)

    @property
    def native(self) -> _bone_sim.SurgeonController:
        """The core's controller, for :meth:`dhg.DrillingSession.drive`."""
        return self._c

    def raw(self) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.float64]] | None:
        """The attempt's 1 kHz pose rows (N, 9) and device forces (N, 3) in N, if kept."""
        return self._c.raw()


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
    expert force (3,) in N; ``dhg.export.load_model(...).predict`` on one window), the model is
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
    window = np.empty((WINDOW_RECORDS, 9))
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
        extra={"reached_target": float(surgeon.phase == "done")},
    )


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


@dataclass
class DrillRun:
    """Summary of a scripted drilling run (SI units)."""

    duration_s: float
    """Simulated time (s)."""
    ticks: int
    """1 ms ticks simulated."""
    mass_removed_kg: float
    """Bone mass removed (kg)."""
    voxels_removed: int
    """Voxels fully removed."""
    tip_m: np.ndarray
    """Final burr centre (m)."""
    layers: list[tuple[str, float, float]] = field(default_factory=list)
    """Layers crossed: (name, depth where it starts (m), depth where it ends (m)) along the path."""


def straight_line_drill(
    bone: DrilledVolume,
    path: PlannedPath,
    radius_m: float = 1.25e-3,
    feed_m_s: float = 1.5e-3,
    spindle_rpm: float = 1200.0,
    tick_s: float = 1e-3,
    start_before_m: float = 2e-3,
    chunk_ticks: int = 1000,
    progress: Callable[[int, int], None] | None = None,
) -> DrillRun:
    """Drills ``bone`` from ``start_before_m`` (m) before A to B at a constant feed (m/s).

    Each tick moves the burr centre ``feed_m_s · tick_s`` along the path and erodes for ``tick_s``.
    ``progress(done_ticks, total_ticks)`` is called after each chunk of ticks.
    """
    for name, v in (("radius_m", radius_m), ("feed_m_s", feed_m_s), ("tick_s", tick_s)):
        if not (np.isfinite(v) and v > 0):
            raise InvalidInputError(f"{name} must be > 0, got {v}")
    total_m = path.length_m + start_before_m
    ticks = int(np.ceil(total_m / (feed_m_s * tick_s)))
    depths = -start_before_m + np.linspace(feed_m_s * tick_s, total_m, ticks)
    centers = path.point_at(depths)
    mass = 0.0
    removed = 0
    for start in range(0, ticks, chunk_ticks):
        r = bone.remove_along(centers[start : start + chunk_ticks], radius_m, spindle_rpm, tick_s)
        mass += r.mass_removed_kg
        removed += r.voxels_removed
        if progress is not None:
            progress(min(start + chunk_ticks, ticks), ticks)
    return DrillRun(
        duration_s=ticks * tick_s,
        ticks=ticks,
        mass_removed_kg=mass,
        voxels_removed=removed,
        tip_m=centers[-1],
        layers=layer_runs(bone, path, step_m=0.25e-3),
    )


def layer_runs(bone: DrilledVolume, path: PlannedPath, step_m: float = 0.25e-3) -> list[tuple[str, float, float]]:
    """The pristine layers along A→B as runs (name, start depth (m), end depth (m))."""
    return _layer_runs(bone.volume, path, step_m)


def _layer_runs(volume: Volume, path: PlannedPath, step_m: float) -> list[tuple[str, float, float]]:
    runs = volume.layer_runs(path.entry_m, path.target_m, step_m)
    return [(Layer(layer).name.lower(), start, end) for layer, start, end in runs]


def planned_breakthrough_depth_m(
    volume: Volume, path: PlannedPath, burr_radius_m: float, step_m: float = 0.25e-3
) -> float | None:
    """The tip depth along A→B (m) at which a burr of ``burr_radius_m`` (m) leaves the first
    cortical layer on the path, as a surgeon reads it off the planning CT: the end of the first
    cortical run of the pristine bone, less the radius (the burr's front leads its centre).
    ``None`` when the path crosses no cortex."""
    return breakthrough_depth_from_runs(_layer_runs(volume, path, step_m), path.length_m, burr_radius_m, step_m)


def breakthrough_depth_from_runs(
    runs: Iterable[tuple[str, float, float]], path_length_m: float, burr_radius_m: float, step_m: float
) -> float | None:
    """:func:`planned_breakthrough_depth_m` from layer runs (name, start (m), end (m)) sampled
    every ``step_m`` (m) along a path of ``path_length_m`` (m), such as a server session's
    ``path_layers``. ``None`` when no run is cortical."""
    end = next((end for name, _, end in runs if name == "cortical"), None)
    if end is None:
        return None
    # The boundary lies between the run's last sample and the next one.
    return float(min(end + step_m / 2, path_length_m) - burr_radius_m)


def scripted_stylus(
    path: PlannedPath,
    duration_s: float,
    feed_m_s: float = 1.5e-3,
    lead_m: float = 4e-3,
    start_before_m: float = 5e-3,
    spindle_rpm: float = 1250.0,
) -> np.ndarray:
    """Pose rows (N, 9) for :meth:`dhg.DrillingSession.step`: a stylus commanded along the path at
    ``feed_m_s`` (m/s), ``lead_m`` (m) ahead of the planned feed, that stops at B.

    Against bone, the drill lags the command. The stylus then runs ahead of the tip, and the
    coupling force (the push) grows until the cutting law lets the tip keep up. It is a
    position-driven operator with no human behaviour (that comes with the virtual surgeons).
    """
    from dhg.session import poses

    n = int(round(duration_s * 1000))
    depth = np.minimum(-start_before_m + np.arange(n) * 1e-3 * feed_m_s + lead_m, path.length_m)
    return poses(path.point_at(depth), _axis_quaternion(path.direction), True, spindle_rpm)
