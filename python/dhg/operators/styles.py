"""The virtual surgeons' styles: an expert's or a novice's motor parameters, drawn per subject.

The ranges are the virtual surgeons' design, the project's choice so that the two groups differ
(the paper records experts and novices but publishes no motor parameters for either), not measured
values: no published distribution was found for them. Where a published figure bounds one it is named: a
reaction to a force perturbation is voluntary from about 0.1 s (Pruszynski & Scott 2012), below the
experts' 0.10–0.16 s upper end and the novices' 0.25–0.40 s; the arm stiffnesses are of the order
of van Beek et al. 2015's 135 N/m at a haptic handle (one trial)."""

from __future__ import annotations

import numpy as np

from dhg.core.surgeon import Skill, SurgeonStyle

__all__ = ["EXPERT_ARM_N_PER_M", "NOVICE_ARM_N_PER_M", "sample_style"]

EXPERT_ARM_N_PER_M = (210.0, 260.0)
"""Range of the experts' arm stiffness (N/m); see :attr:`SurgeonStyle.arm_stiffness_n_per_m`."""
NOVICE_ARM_N_PER_M = (100.0, 130.0)
"""Range of the novices' arm stiffness (N/m): a looser arm."""


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
