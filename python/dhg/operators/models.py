"""Operator models for guidance studies: how a virtual trainee's hand answers the device, and how
the trainee learns across attempts.

Two operators drive :class:`dhg.core.surgeon.SurgeonController` in ``dhg study``:

- ``impedance``: the arm answers every device force, guidance included, only through its
  mechanical impedance; the trainee is told nothing about the cue. The arm's mass, damping and
  stiffness are those measured at the handle of a haptic device held in a relaxed posture
  (van Beek, Bergmann Tiest & Kappers 2015, *Sci. Rep.* 5:18004: M = 0.554 kg, B = 6.45 N·s/m,
  K = 135 N/m in their example fit, one trial of one participant, not a population mean), drawn
  ±20 % per trainee; a novice's reaction delay to a change in force is drawn from 150–250 ms, a
  range chosen above the 100 ms after which voluntary responses to a force perturbation begin
  (Pruszynski & Scott 2012, *Exp. Brain Res.* 218:341; the bounds themselves have no source).
- ``instructed``: today's trainee (the novices of ``dhg synth``), who was told what the cue means:
  they lean into the paper's force-matching cue, yield to the shaping modes' cues, and pause with
  the drill off while they feel ``shaped``'s heat cue, a vibration in the handle
  (:class:`~dhg.core.surgeon.SurgeonController`, ``cue_meaning``).

:class:`Learner` carries a trainee's skill from one attempt to the next with the single-state
error-based update with forgetting of Emken, Benitez, Sideris, Bobrow & Reinkensmeyer 2007
(*J. Neurophysiol.* 97:3997): ``x ← f·x + g·e``, where ``e`` is the error the trainee
experienced in the attempt. Forgetting (``f < 1``) is the effort term of their model: where the
guidance keeps the error small, what was learned decays, so a study can see a trainee come to
depend on guidance (the guidance hypothesis, Schmidt & Bjork 1992). Two skills are learned:
easing off and bracing before the planned breakthrough, from the plunge experienced, and holding the line,
from the lateral deviation experienced. The coefficients are not fitted to drilling data (none
is published); they are within the range Emken et al. show the model needs (0 < f < 1, g > 0)
so that a novice who plunges 3 mm, unguided, learns 0.3, 0.54, 0.73 of the skill in three attempts.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Literal

import numpy as np

from dhg.core.surgeon import CueMeaning, SurgeonStyle

__all__ = [
    "ARM_DAMPING_N_S_PER_M",
    "ARM_MASS_KG",
    "ARM_STIFFNESS_N_PER_M",
    "NOVICE_REACTION_S",
    "OPERATORS",
    "Learner",
    "Operator",
    "cue_meaning",
    "operator_style",
]

Operator = Literal["impedance", "instructed"]
OPERATORS: tuple[Operator, ...] = ("impedance", "instructed")
"""The operator models ``dhg study`` can run."""

ARM_MASS_KG = 0.554
"""Effective arm mass at a haptic handle (kg): van Beek et al. 2015's example fit (one trial)."""
ARM_DAMPING_N_S_PER_M = 6.45
"""Arm damping at a haptic handle (N·s/m): van Beek et al. 2015's example fit (one trial)."""
ARM_STIFFNESS_N_PER_M = 135.0
"""Arm stiffness at a haptic handle (N/m): van Beek et al. 2015's example fit (one trial)."""
ARM_SPREAD = 0.2
"""Per-trainee spread of the arm's impedance, ± this fraction (uniform)."""
NOVICE_REACTION_S = (0.15, 0.25)
"""Range of a novice's reaction delay to a change in force (s): chosen above the 0.1 s after which
voluntary responses to a force perturbation begin (Pruszynski & Scott 2012). The demonstrators of
``dhg synth`` react in 0.25–0.40 s (:func:`dhg.operators.styles.sample_style`), another choice."""


def operator_style(style: SurgeonStyle, operator: Operator, rng: np.random.Generator) -> SurgeonStyle:
    """``style`` as the given operator: ``instructed`` leaves it as drawn; ``impedance`` gives the
    arm the literature's impedance (see the module docs), drawn from ``rng``."""
    if operator == "instructed":
        return style
    if operator != "impedance":
        raise ValueError(f"operator must be one of {', '.join(OPERATORS)}, got {operator!r}")
    lo, hi = 1.0 - ARM_SPREAD, 1.0 + ARM_SPREAD
    k = ARM_STIFFNESS_N_PER_M * rng.uniform(lo, hi)
    delay = rng.uniform(*NOVICE_REACTION_S) if style.skill == "novice" else style.reaction_delay_s
    return dataclasses.replace(
        style,
        hand_mass_kg=ARM_MASS_KG * rng.uniform(lo, hi),
        hand_damping_n_s_per_m=ARM_DAMPING_N_S_PER_M * rng.uniform(lo, hi),
        arm_stiffness_n_per_m=k,
        lateral_stiffness_n_per_m=k,
        reaction_delay_s=delay,
        cue_follow_per_s=0.0,
    )


def cue_meaning(operator: Operator, mode: str | None) -> CueMeaning:
    """How ``operator`` reads the cue of guidance ``mode`` (None: no guidance)."""
    if operator == "impedance" or mode is None:
        return "felt"
    return "match" if mode == "paper" else "yield"


@dataclass
class Learner:
    """One trainee's skill across attempts (Emken et al. 2007; see the module docs).

    ``anticipation`` and ``steadiness`` run from 0 (a novice as drawn) to 1 (the skill learned
    in full): at 1 the trainee eases off to ``1 − EASE_LEARNED`` of the cortical push
    ``ANTICIPATION_M`` before the planned breakthrough and braces the arm, as experts do, and
    wanders half as far off the line."""

    forget: float = 0.8
    """Fraction of a skill kept from one attempt to the next (f)."""
    learn: float = 0.3
    """Skill gained per unit of error experienced (g)."""
    plunge_ref_m: float = 3e-3
    """A plunge of this size (m) is an error of 1."""
    deviation_ref_m: float = 3e-3
    """A maximum lateral deviation of this size (m) is an error of 1."""
    anticipation: float = 0.0
    steadiness: float = 0.0

    EASE_LEARNED = 0.3
    ANTICIPATION_M = 0.5e-3
    BRACE_LEARNED = 0.8
    """At full anticipation the arm is braced: stiffness and damping up by this fraction. People
    learn to co-contract against an instability (Burdet et al. 2001, *Nature* 414:446; Franklin et
    al. 2008), and a cortex that gives is one; the experts here hold 210–260 N/m."""

    def style(self, base: SurgeonStyle) -> SurgeonStyle:
        """``base`` with what has been learned so far."""
        a, s = self.anticipation, self.steadiness
        return dataclasses.replace(
            base,
            anticipates_breakthrough=base.anticipates_breakthrough or a > 0.0,
            anticipation_m=max(base.anticipation_m, self.ANTICIPATION_M * (a > 0.0)),
            ease_fraction=min(base.ease_fraction, 1.0 - self.EASE_LEARNED * a),
            arm_stiffness_n_per_m=base.arm_stiffness_n_per_m * (1.0 + self.BRACE_LEARNED * a),
            hand_damping_n_s_per_m=base.hand_damping_n_s_per_m * (1.0 + self.BRACE_LEARNED * a),
            drift_m=base.drift_m * (1.0 - 0.5 * s),
        )

    def update(self, plunge_m: float, max_deviation_m: float) -> None:
        """After an attempt: the errors experienced in it (m) update both skills."""
        e_plunge = min(max(plunge_m, 0.0) / self.plunge_ref_m, 2.0)
        e_dev = min(max(max_deviation_m, 0.0) / self.deviation_ref_m, 2.0)
        self.anticipation = float(np.clip(self.forget * self.anticipation + self.learn * e_plunge, 0.0, 1.0))
        self.steadiness = float(np.clip(self.forget * self.steadiness + self.learn * e_dev, 0.0, 1.0))
