"""The virtual surgeon's hand and decisions: the native 1 kHz controller and its style.

The virtual surgeon (:class:`SurgeonController`, driven by
:func:`dhg.operators.episodes.run_episode`): a human-like operator that drills the planned path
through a session at 1 kHz. It models a hand holding the stylus: a mass with arm damping, driven by the
push the surgeon intends and pushed back by the device force. At 1 kHz, what the surgeon *does*
depends on what they *perceived* one reaction delay ago. The phases are:

1. approach: a minimum-jerk reach (Flash & Hogan 1985) from a resting point to 3 mm before A;
2. align and spin up the drill;
3. feed: the push is regulated towards a preferred feed but never exceeds a layer-dependent
   ceiling (firm in cortical bone, light in cancellous bone and marrow); experts ease off as the
   cortex thins, having read from the planning CT where along the path it ends
   (:func:`dhg.bone.planning.planned_breakthrough_depth_m`), and stop to let the drill cool as the tip nears
   47 °C; novices hesitate;
4. breakthrough: once the surgeon feels the cortex give (after the reaction delay), they hold
   and pull back. A late reaction and a loose arm make a deeper plunge;
5. stop near B and switch the drill off.

The surgeon's 1 kHz step is the core's (``bone_sim::surgeon``, wrapped by
:class:`SurgeonController`), so an offline attempt runs at the core's speed
(:meth:`dhg.DrillingSession.drive`).

Guidance (``dhg trainee``): the server adds a cue to the rendered force, the predicted expert
force minus the trainee's (Fekri et al. 2021). Along the drill this is a force-matching cue: it
pushes back where the expert pressed harder and pulls in where the expert eased off. A purely
passive hand would read "press harder" as resistance and back away. So a trainee who has been
told what the cue means leans into it: after the reaction delay, the push grows while the cue
pushes back and shrinks while it pulls in, until the cue is nulled
(:attr:`SurgeonStyle.cue_follow_per_s`).

Human motor behaviour: physiological tremor of 8–12 Hz (Elble 1990), signal-dependent noise on
the push (Harris & Wolpert 1998), a reaction delay to force changes, and lateral drift from
limited steadiness.

Styles are drawn by :func:`dhg.operators.styles.sample_style`; operators without human behaviour
are in :mod:`dhg.operators.scripted`.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Literal

import numpy as np
import numpy.typing as npt

from dhg import _bone_sim
from dhg.core.path import PlannedPath, TaskRules

__all__ = [
    "AIM_FOLLOW_S",
    "CUE_LEAK_PER_S",
    "MAX_ATTEMPT_S",
    "START_S_M",
    "GENERIC_BREAKTHROUGH_DEPTH_M",
    "HAND_MASS_KG",
    "LATERAL_STIFFNESS_N_PER_M",
    "MAX_PUSH_N",
    "PUSH_MARGIN_N",
    "TRACK_STIFFNESS_N_PER_M",
    "YIELD_SETTLE_S",
    "CueMeaning",
    "Skill",
    "SurgeonController",
    "SurgeonStyle",
    "axis_quaternion",
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
MAX_ATTEMPT_S: float = _CONSTANTS["MAX_ATTEMPT_S"]
"""The longest attempt a virtual surgeon takes (s); a longer ``max_duration_s`` is refused."""
START_S_M: float = _CONSTANTS["START_S_M"]
"""Where the surgeon's hand starts along A→B (m; negative: before the entry)."""


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


def axis_quaternion(d: npt.ArrayLike) -> tuple[float, float, float, float]:
    """The tool orientation (w, x, y, z) whose axis points along ``d`` (the core's rule)."""
    q = _bone_sim.axis_quaternion([float(x) for x in np.asarray(d, dtype=float).ravel()])
    return (q[0], q[1], q[2], q[3])


class SurgeonController:
    """The virtual surgeon's decisions and hand, one 1 kHz tick at a time (the core's
    ``bone_sim::surgeon``; this wraps it).

    :meth:`step` takes what the stylus reports this tick (the session feedback tuple: tip x, y, z
    (m), depth (m), deviation (m), temperature (°C), layer id, cutting, breakthroughs, plunging,
    plunge depth (m)) and the force felt (N), and returns the next pose row, or ``None`` once the
    surgeon has finished. The surgeon acts on what it perceived one reaction delay ago. It drives
    a local session (:func:`dhg.operators.episodes.run_episode`, through
    :meth:`dhg.DrillingSession.drive`) and a remote server (``dhg trainee``) alike.

    ``breakthrough_depth_m`` is the tip depth along A→B (m) at which the plan shows the burr
    leaving the first cortex (:func:`dhg.bone.planning.planned_breakthrough_depth_m`); anticipating surgeons ease
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
    def buzz_felt_s(self) -> float:
        """How long a vibration was felt in the cue so far (s): ``shaped``'s heat cue, or any
        other cue that swings fast enough to be read as one (which a surgeon told what the heat
        cue means pauses for, with the drill off)."""
        return float(self._c.buzz_felt_s)

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
