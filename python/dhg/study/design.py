"""What a study compares: its arms (a guidance mode at a gain, or none), the metrics it reports and
the protocol every novice follows (:mod:`dhg.study.runner` runs it)."""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

from dhg.core.errors import InvalidInputError
from dhg.core.session import GUIDANCE_MODES, MAX_GAIN, GuidanceMode

__all__ = ["ARMS", "METRICS", "PHASES", "Arm", "Protocol", "parse_arms"]


@dataclass(frozen=True)
class Arm:
    """One way of training: a guidance mode at a gain, or ``mode=None`` for no guidance;
    ``fading``: the gain follows the core's assist-as-needed schedule from ``gain``."""

    name: str
    mode: GuidanceMode | None
    gain: float = 1.0
    fading: bool = False


ARMS: dict[str, Arm] = (
    {"none": Arm("none", None, 0.0)}
    | {m: Arm(m, m) for m in GUIDANCE_MODES}
    | {"shaped-fading": Arm("shaped-fading", "shaped", 1.0, fading=True)}
)
"""The arms ``dhg study`` knows: ``none``, one per guidance mode at gain 1, and ``shaped-fading``."""

PHASES = ("pre", "train", "post")
"""The protocol's phases."""


@dataclass(frozen=True)
class Protocol:
    """Attempts per novice and arm: one guidance-free pre-test, ``train`` guided attempts, one
    guidance-free post-test; at most ``duration_s`` (s) each. Each test is measured as the mean of
    ``test_replicates`` replicates (:mod:`dhg.study.runner`)."""

    train: int = 6
    duration_s: float = 150.0
    probe_every: int = 3
    """For fading arms: every this many training attempts one is a guidance-free probe."""
    burr_radius_m: float | None = None
    """The drill's burr radius (m) for every attempt; None: the core's default (1.25 mm, a 2.5 mm
    drill). A 4.5 mm drill (2.25 mm) heats the bone enough to test the 47 °C target."""
    test_replicates: int = 1
    """Each pre- and post-test is drilled this many times from the same learned state, each with
    its own hand noise, and reported as their mean; the novice learns from the first only (the
    protocol's test attempt). A measurement's precision, not more practice."""
    guidance: tuple[tuple[str, float], ...] = ()
    """Changes to the core's guidance laws for every attempt, as (name, value) pairs of
    :attr:`dhg.DrillingSession.guidance_params` (e.g. ``("corridor_deadband_m", 0.25e-3)``); offline
    only (a server's laws are its own)."""

    def validate(self) -> None:
        from dhg.core.session import GUIDANCE_DEFAULTS, MAX_BURR_RADIUS_M, MIN_BURR_RADIUS_M

        if self.burr_radius_m is not None and not (MIN_BURR_RADIUS_M <= self.burr_radius_m <= MAX_BURR_RADIUS_M):
            raise InvalidInputError(
                f"burr radius {self.burr_radius_m} m outside [{MIN_BURR_RADIUS_M}, {MAX_BURR_RADIUS_M}] m"
            )
        known = GUIDANCE_DEFAULTS
        for name, _ in self.guidance:
            if name not in known:
                raise InvalidInputError(f"unknown guidance parameter {name!r}; known: {', '.join(sorted(known))}")
        if self.train < 1:
            raise InvalidInputError(f"a protocol needs at least one training attempt, got {self.train}")
        from dhg.core.surgeon import MAX_ATTEMPT_S

        if not (math.isfinite(self.duration_s) and 0 < self.duration_s <= MAX_ATTEMPT_S):
            raise InvalidInputError(f"duration must be positive and at most {MAX_ATTEMPT_S:g} s, got {self.duration_s}")
        if not 1 <= self.test_replicates <= 64:
            raise InvalidInputError(f"test_replicates must be within 1..64, got {self.test_replicates}")
        if self.probe_every < 0:
            raise InvalidInputError(f"probe_every must be 0 (none) or more, got {self.probe_every}")


METRICS: tuple[tuple[str, str, float, bool], ...] = (
    ("plunge_depth_m", "plunge (mm)", 1e3, True),
    ("max_deviation_m", "max deviation (mm)", 1e3, True),
    ("max_lateral_deviation_m", "max across (mm)", 1e3, True),
    ("mean_deviation_m", "mean deviation (mm)", 1e3, True),
    ("target_distance_m", "to B (mm)", 1e3, True),
    ("completion_time_s", "time (s)", 1.0, True),
    ("time_above_47_s", "> 47 °C (s)", 1.0, True),
    ("peak_temperature_c", "peak (°C)", 1.0, True),
    ("reached_target", "reached B", 1.0, False),
    # Seconds a vibration was felt in the guidance: shaped's heat cue, or a cue read as one (a
    # surgeon told what the heat cue means pauses for it). Not a skill: what the arm made felt.
    ("buzz_felt_s", "buzz felt (s)", 1.0, True),
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
            if not (math.isfinite(g) and 0 <= g <= MAX_GAIN):
                raise InvalidInputError(f"arm {item!r}: the gain must be within 0..{MAX_GAIN:g}")
            arm = dataclasses.replace(arm, name=item, gain=g)
        arms.append(arm)
    if not arms or arms[0].mode is not None:
        raise InvalidInputError("the first arm must be 'none', the baseline the others are compared with")
    if len({a.name for a in arms}) != len(arms):
        raise InvalidInputError(f"arms repeat: {text!r}")
    return arms
