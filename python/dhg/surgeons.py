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

import math
from collections.abc import Callable, Generator, Iterable
from dataclasses import asdict, dataclass, field
from typing import Literal

import numpy as np
import numpy.typing as npt

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

HAND_MASS_KG = 0.4
"""Effective mass of hand and stylus (kg)."""
TRACK_STIFFNESS_N_PER_M = 300.0
"""How stiffly the arm follows an intended position (N/m), for approach and holding."""
LATERAL_STIFFNESS_N_PER_M = 250.0
"""How stiffly the arm holds the drill on the path laterally (N/m)."""
GENERIC_BREAKTHROUGH_DEPTH_M = 2.2e-3
"""Tip depth at which a surgeon without a plan expects the first cortex to give (m)."""
EXPERT_ARM_N_PER_M = (210.0, 260.0)
"""Range of the experts' arm stiffness (N/m); see :attr:`SurgeonStyle.arm_stiffness_n_per_m`."""
NOVICE_ARM_N_PER_M = (100.0, 130.0)
"""Range of the novices' arm stiffness (N/m): a looser arm."""
AIM_FOLLOW_S = 0.5
"""Time constant (s) with which the arm's aim follows the felt hand position."""
PUSH_MARGIN_N = 0.4
"""How much harder than the resistance they feel (N, one reaction delay ago) a subject pushes."""
MAX_PUSH_N = 3.0
"""Most axial push any subject applies, however strongly a guidance cue asks for more (N)."""
YIELD_SETTLE_S = 0.2
"""How fast a surgeon who yields to the guidance settles onto what it asks (s)."""
CUE_LEAK_PER_S = 0.2
"""How fast the lean a cue built up fades once the cue is gone (1/s): a remembered instruction
fades, and a model biased in one direction cannot wind the push up for ever."""


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


def _min_jerk(t: float, duration: float) -> float:
    """Minimum-jerk position profile from 0 to 1 (Flash & Hogan 1985)."""
    x = min(max(t / duration, 0.0), 1.0)
    return x**3 * (10.0 - 15.0 * x + 6.0 * x * x)


def _floats(v: npt.ArrayLike) -> tuple[float, ...]:
    return tuple(float(x) for x in np.asarray(v, dtype=float).ravel())


def _basis(d: npt.NDArray[np.float64]) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.float64]]:
    helper = np.array([1.0, 0.0, 0.0]) if abs(d[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    e1 = np.cross(d, helper)
    e1 /= np.linalg.norm(e1)
    return e1, np.cross(d, e1)


def _axis_quaternion(d: npt.NDArray[np.float64]) -> tuple[float, float, float, float]:
    z = np.array([0.0, 0.0, 1.0])
    q = np.array([1.0 + z @ d, *np.cross(z, d)])
    n = np.linalg.norm(q)
    q = q / n if n > 1e-9 else np.array([0.0, 1.0, 0.0, 0.0])
    return (float(q[0]), float(q[1]), float(q[2]), float(q[3]))


class SurgeonController:
    """The virtual surgeon's decisions and hand, one 1 kHz tick at a time.

    :meth:`step` takes what the stylus reports this tick (the session feedback tuple: tip x, y, z
    (m), depth (m), deviation (m), temperature (°C), layer id, cutting, breakthroughs, plunging,
    plunge depth (m)) and the force felt (N), and returns the next pose row, or ``None`` once the
    surgeon has finished. The surgeon acts on what it perceived one reaction delay ago. It drives
    a local session (:func:`run_episode`) and a remote server (``dhg trainee``) alike.

    ``breakthrough_depth_m`` is the tip depth along A→B (m) at which the plan shows the burr
    leaving the first cortex (:func:`planned_breakthrough_depth_m`); anticipating surgeons ease
    off :attr:`SurgeonStyle.anticipation_m` before it.

    ``cue_meaning`` is what the surgeon was told the guidance means: ``"match"`` (the paper's
    force-matching cue: lean into a cue that pushes the drill back, ease off one that pulls it in),
    ``"yield"`` (guidance that shapes the motion, as the corridor, brake and shaped modes do:
    ease off where it resists, go with it where it pulls) or ``"felt"`` (nothing: the cue acts
    on the hand only through the arm's impedance, as any other force does).
    """

    def __init__(
        self,
        path: PlannedPath,
        style: SurgeonStyle,
        rng: np.random.Generator,
        rules: TaskRules | None = None,
        breakthrough_depth_m: float | None = None,
        cue_meaning: CueMeaning = "match",
    ) -> None:
        if cue_meaning not in ("match", "yield", "felt"):
            raise ValueError(f"cue_meaning must be 'match', 'yield' or 'felt', got {cue_meaning!r}")
        self.style, self.rng, self.path = style, rng, path
        # "match": the paper's force-matching cue (lean into a cue that pushes back); "yield": a cue
        # that shapes the motion (corridor, brake, warning), so ease off where it resists.
        self.yields = cue_meaning == "yield"
        self.reads_cue = cue_meaning != "felt"
        # Where the plan says the cortex gives (tip depth, m); without a plan, ~3.5 mm of cortex and a 2.5 mm burr.
        self.breakthrough_depth_m = (
            GENERIC_BREAKTHROUGH_DEPTH_M if breakthrough_depth_m is None else float(breakthrough_depth_m)
        )
        self.rules = rules or TaskRules()
        # Plain float tuples, not arrays: step() reads them every tick, and indexing a float
        # tuple is several times cheaper than indexing an ndarray (same values, same results).
        self.a = _floats(path.entry_m)
        self.d = _floats(path.direction)
        e1, e2 = _basis(np.asarray(path.direction, dtype=float))
        self.e1, self.e2 = _floats(e1), _floats(e2)
        self.q = _axis_quaternion(np.asarray(path.direction, dtype=float))
        self.length = path.length_m
        self.dt = 1e-3
        self.max_ticks = int(self.rules.max_duration_s / self.dt)
        self.delay = max(1, int(round(style.reaction_delay_s / self.dt)))
        # Hand state in path coordinates: s along A→B, (u, v) across.
        self.start_s = -25e-3
        u0, v0 = rng.normal(0.0, 3e-3, size=2)
        self.u0, self.v0 = float(u0), float(v0)
        self.s, self.u, self.v = self.start_s, self.u0, self.v0
        self.vs = self.vu = self.vv = 0.0
        self.approach_s = float(rng.uniform(1.2, 2.0))
        self.align_s = float(rng.uniform(0.3, 0.7))
        self.tremor_phase = _floats(rng.uniform(0.0, 2 * math.pi, size=3))
        self.w_tremor = 2 * math.pi * style.tremor_hz
        self.drift_u = self.drift_v = 0.0
        self.drift_tau = 1.5  # s: how slowly the aim wanders
        self._k_ou = self.dt / self.drift_tau
        self._ou_kick = style.drift_m * math.sqrt(2 * self._k_ou)
        self.noise_state = 0.0
        self.push = 0.0
        self.stop_s = 0.0
        self.phase = "approach"
        self.phase_t0 = 0.0
        self.hold_s: float | None = None
        self.pause_until = -1.0
        self.cooling = False
        self.retract_until = -1.0
        self.seen_breakthroughs = 0
        self.drill_on = False
        self.drill_on_t: float | None = None
        self.drill_off_t: float | None = None
        self.max_plunge = 0.0
        self.fb_hist: list[tuple] = []
        self.s_hist: list[float] = []  # the hand's position along A→B (m), one per tick
        self.f_ax_hist: list[float] = []  # the device force along A→B (N), one per tick
        self.aim_s = self.s  # where the arm pushes towards (m along A→B)
        self.cue_hist: list[float] = []
        self.lean = 0.0  # N: push added in response to the guidance cue
        self.tick = 0

    @property
    def done(self) -> bool:
        """Whether the surgeon has finished (stopped at B, or ran out of time)."""
        return self.phase == "done" or self.tick >= self.max_ticks

    @property
    def drilling_s(self) -> float:
        """Time from drill start to drill stop (s), as far as the run has come."""
        end = self.drill_off_t if self.drill_off_t is not None else self.tick * self.dt
        return end - (self.drill_on_t or 0.0)

    def step(
        self,
        feedback: tuple,
        force_n: tuple[float, float, float],
        cue_n: tuple[float, float, float] = (0.0, 0.0, 0.0),
    ) -> tuple[float, ...] | None:
        """The pose row (x, y, z, qw, qx, qy, qz, drill_on, spindle_rpm) for this tick, or None.

        ``force_n`` is the whole force the device renders (N, world frame); ``cue_n`` is the
        guidance share of it (N), which the surgeon also reads as an instruction (see the module
        docs). Without guidance it is zero."""
        if self.done:
            return None
        style, rng, dt, tick = self.style, self.rng, self.dt, self.tick
        d, e1, e2 = self.d, self.e1, self.e2
        t = tick * dt
        self.fb_hist.append(feedback)
        self.cue_hist.append(cue_n[0] * d[0] + cue_n[1] * d[1] + cue_n[2] * d[2])
        seen = self.fb_hist[max(0, tick - self.delay)]
        _, _, _, p_depth, _, p_temp, p_layer, _, p_bt, _, _ = seen
        self.max_plunge = max(self.max_plunge, feedback[10])
        # Aim wander (Ornstein-Uhlenbeck) and signal-dependent push noise (low-passed ~5 Hz).
        k_ou, kick = self._k_ou, self._ou_kick
        self.drift_u += -k_ou * self.drift_u + kick * rng.standard_normal()
        self.drift_v += -k_ou * self.drift_v + kick * rng.standard_normal()
        self.noise_state += 0.03 * (rng.standard_normal() - self.noise_state)

        intent_s: float | None = None  # a position the arm tracks, or None: push with `push`
        if self.phase == "approach":
            intent_s = self.start_s + (-3e-3 - self.start_s) * _min_jerk(t - self.phase_t0, self.approach_s)
            if t - self.phase_t0 >= self.approach_s:
                self.phase, self.phase_t0 = "align", t
        elif self.phase == "align":
            intent_s = -3e-3
            self.drill_on = True
            if t - self.phase_t0 >= self.align_s:
                self.phase, self.phase_t0, self.push = "feed", t, 0.0
                self.drill_on_t = t
        elif self.phase == "feed":
            # Perceived tip speed over the last 50 ms (as of one reaction delay ago).
            back = self.fb_hist[max(0, tick - self.delay - 50)]
            speed = (p_depth - back[3]) / 0.05
            ceiling = style.push_cortical_n if p_layer == Layer.CORTICAL else style.push_soft_n
            easing = p_depth > self.breakthrough_depth_m - style.anticipation_m
            if style.anticipates_breakthrough and p_layer == Layer.CORTICAL and easing:
                ceiling = style.ease_fraction * style.push_cortical_n  # the cortex is thinning: ease off
            if p_bt > self.seen_breakthroughs:
                self.seen_breakthroughs = p_bt
                self.retract_until = t + 0.25
            if p_temp > style.caution_temp_c:
                self.cooling = True
            elif self.cooling and p_temp < style.caution_temp_c - 2.0:
                self.cooling = False
            if style.hesitations_per_s > 0 and t > self.pause_until and rng.random() < style.hesitations_per_s * dt:
                self.pause_until = t + style.hesitation_s
            if t < self.retract_until or self.cooling or t < self.pause_until:
                # Hold still (pulled 1 mm back after a breakthrough): a pausing hand does not go limp.
                if self.hold_s is None:
                    self.hold_s = self.s - (1e-3 if t < self.retract_until else 0.0)
                intent_s = self.hold_s
                self.push = self.lean = 0.0
            else:
                self.hold_s = None
                # Integral control of the push towards the preferred feed, within the ceiling.
                self.push += 2.4 * style.feed_gain * (style.feed_m_s - speed) / style.feed_m_s * dt * ceiling
                self.push = min(max(self.push, 0.0), ceiling)
                # Lean into the cue as perceived a reaction delay ago: a cue along -d (pushing the
                # drill back) means the expert pressed harder.
                cue_seen = self.cue_hist[max(0, tick - self.delay)]
                if not self.reads_cue:
                    pass  # felt only: the cue is in force_n, which the arm's impedance answers
                elif self.yields:
                    # Yielding: give way by what the cue asks, after the reaction delay (a hand
                    # settling onto the new force within about 0.2 s), not more.
                    self.lean += (cue_seen - self.lean) * dt / YIELD_SETTLE_S
                else:
                    self.lean += (-style.cue_follow_per_s * cue_seen - CUE_LEAK_PER_S * self.lean) * dt
            self.drill_on = not self.cooling
            if p_depth >= self.length - style.stop_margin_m:
                self.phase, self.phase_t0 = "stop", t
                self.hold_s = self.s
                self.stop_s = self.s
        elif self.phase == "stop":
            intent_s = self.stop_s
            self.drill_on = False
            if self.drill_off_t is None:
                self.drill_off_t = t
            if t - self.phase_t0 >= 0.5:
                self.phase = "done"
                return None

        # Hand dynamics (semi-implicit Euler at 1 kHz).
        fx, fy, fz = force_n
        f_ax = fx * d[0] + fy * d[1] + fz * d[2]
        self.f_ax_hist.append(f_ax)
        f_u = fx * e1[0] + fy * e1[1] + fz * e1[2]
        f_v = fx * e2[0] + fy * e2[1] + fz * e2[2]
        self.s_hist.append(self.s)
        if intent_s is not None:
            drive = TRACK_STIFFNESS_N_PER_M * (intent_s - self.s)
            self.aim_s = self.s
        else:
            # Nobody pushes much harder than the resistance they feel: a push that meets no
            # resistance (a device that has derated, a bone that gave way) is not kept up. The
            # lean into a guidance cue comes on top: it is what the subject was told to do.
            felt_resistance = max(-self.f_ax_hist[max(0, tick - self.delay)], 0.0)
            own = min(self.push, felt_resistance + PUSH_MARGIN_N)
            push = min(max(own + self.lean, 0.0), MAX_PUSH_N)
            push *= 1.0 + style.noise_fraction * self.noise_state * 5.0
            # The arm pushes towards an aim that moves on at the preferred feed and follows, slowly,
            # where the hand was felt one reaction delay ago: its stiffness resists travel ahead of
            # the aim, so a sudden give is caught after about push / stiffness. (An aim that
            # followed the felt position at once would make a delayed, unstable loop.)
            felt_s = self.s_hist[max(0, tick - self.delay)]
            self.aim_s += style.feed_m_s * dt + (felt_s - self.aim_s) * dt / AIM_FOLLOW_S
            drive = push - style.arm_stiffness_n_per_m * max(self.s - self.aim_s, 0.0)
        damping = style.hand_damping_n_s_per_m
        mass, k_lat = style.hand_mass_kg, style.lateral_stiffness_n_per_m
        self.vs += (drive + f_ax - damping * self.vs) / mass * dt
        aim_u = self.drift_u + style.tremor_m * math.sin(self.w_tremor * t + self.tremor_phase[0])
        aim_v = self.drift_v + style.tremor_m * math.sin(self.w_tremor * t + self.tremor_phase[1])
        if self.phase == "approach":
            frac = 1.0 - _min_jerk(t - self.phase_t0, self.approach_s)
            aim_u += self.u0 * frac
            aim_v += self.v0 * frac
        self.vu += (k_lat * (aim_u - self.u) + f_u - damping * self.vu) / mass * dt
        self.vv += (k_lat * (aim_v - self.v) + f_v - damping * self.vv) / mass * dt
        self.s += self.vs * dt
        self.u += self.vu * dt
        self.v += self.vv * dt
        s_axial = self.s + style.tremor_m * 0.3 * math.sin(self.w_tremor * t + self.tremor_phase[2])
        a = self.a
        x = a[0] + s_axial * d[0] + self.u * e1[0] + self.v * e2[0]
        y = a[1] + s_axial * d[1] + self.u * e1[1] + self.v * e2[1]
        z = a[2] + s_axial * d[2] + self.u * e1[2] + self.v * e2[2]
        self.tick += 1
        on = self.drill_on
        return (x, y, z, *self.q, 1.0 if on else 0.0, style.spindle_rpm if on else 0.0)


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
) -> Episode:
    """Drills the session's planned path once with a surgeon of ``style``. The session is reset
    first. Deterministic for the generator's state.

    With a ``predictor`` (a window of the last 20 records' nine features, (20, 9), to the predicted
    expert force (3,) in N; ``dhg.export.load_model(...).predict`` on one window), the model is
    queried at every 10 Hz record, as ``dhg-serve`` queries it, and the session renders guidance
    in whatever mode and gain it was given (:meth:`DrillingSession.set_guidance`); the window is
    padded at the front with the first record until 20 exist, as the server pads it. Offline, the
    reply is applied at once (the server's takes the model's latency, about 5–10 ms). The surgeon
    feels the guidance and reads it as ``cue_meaning`` says (:class:`SurgeonController`).

    :func:`drill_episode` is the same attempt as a generator, for callers that answer the model's
    queries of many attempts at once."""
    steps = drill_episode(session, style, rng, subject, attempt, rules, keep_raw, predictor is not None, cue_meaning)
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
) -> Generator[npt.NDArray[np.float64], npt.NDArray[np.float64], Episode]:
    """:func:`run_episode` as a generator: when ``guided``, it yields the model's window (20, 9)
    at every 10 Hz record and takes the predicted expert force (3,) in N by ``send``; its return
    value (``StopIteration.value``) is the :class:`Episode`. The yielded array is reused: copy it
    to keep it past the next ``send``."""
    rules = rules or TaskRules()
    session.reset()
    native = session._s
    path: PlannedPath = session.path
    planned = planned_breakthrough_depth_m(session.volume, path, session.config.burr_radius_m)
    surgeon = SurgeonController(path, style, rng, rules, breakthrough_depth_m=planned, cue_meaning=cue_meaning)
    max_ticks = surgeon.max_ticks
    records: list[npt.NDArray[np.float64]] = []
    raw_poses = np.empty((max_ticks, 9)) if keep_raw else None
    raw_forces = np.empty((max_ticks, 3)) if keep_raw else None
    force = (0.0, 0.0, 0.0)
    cue = (0.0, 0.0, 0.0)
    end_tick = max_ticks
    window = np.empty((WINDOW_RECORDS, 9))
    for tick in range(max_ticks):
        row = surgeon.step(native.feedback(), force, cue)
        if row is None:
            end_tick = tick
            break
        f, record = native.tick(row)
        force = (float(f[0]), float(f[1]), float(f[2]))
        if guided:
            cue = native.guidance_share()
        if keep_raw:
            raw_poses[tick] = row
            raw_forces[tick] = force
        if record is not None:
            records.append(record)
            if guided:
                recent = records[-WINDOW_RECORDS:]
                pad = WINDOW_RECORDS - len(recent)
                window[:pad] = recent[0][1:10]
                for i, r in enumerate(recent):
                    window[pad + i] = r[1:10]
                predicted = yield window
                native.set_prediction((float(predicted[0]), float(predicted[1]), float(predicted[2])))
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
        forces_n=raw_forces[:end_tick] if keep_raw else None,
    )
    return Episode(
        subject=subject,
        skill=style.skill,
        attempt=attempt,
        style=style,
        records=rec,
        metrics=metrics,
        raw_poses=raw_poses[:end_tick] if keep_raw else None,
        raw_forces_n=raw_forces[:end_tick] if keep_raw else None,
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
