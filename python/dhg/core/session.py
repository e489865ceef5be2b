"""Drilling sessions: the 1 kHz haptic simulation a trainee (or a virtual surgeon) drives.

A session owns a copy-on-write view of a shared :class:`~dhg.Volume` and a planned path. Each
1 ms tick takes the stylus pose and returns the force for the device (N, world frame), always
finite and within the device profile. Every 100 ticks it also returns the paper's 10 Hz record
(:mod:`dhg.core.features`). Use :meth:`DrillingSession.step` for many ticks per call (offline
simulation: a 60 s run at 1 kHz takes a fraction of a second) and :meth:`DrillingSession.tick`
for one.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import asdict, dataclass, field, fields
from typing import TYPE_CHECKING, Any, Literal

import numpy as np
import numpy.typing as npt

from dhg import _bone_sim
from dhg.core.errors import InvalidInputError, ShapeError
from dhg.core.features import POSE_COLUMNS
from dhg.core.layers import Layer
from dhg.core.path import PlannedPath
from dhg.core.volume import Volume, XRayViews, as_points

if TYPE_CHECKING:
    from dhg.core.surgeon import SurgeonController

__all__ = [
    "FADING_DEFAULTS",
    "GUIDANCE_DEFAULTS",
    "GUIDANCE_MODES",
    "MAX_GAIN",
    "MAX_BURR_RADIUS_M",
    "MIN_BURR_RADIUS_M",
    "MAX_POSITION_M",
    "MAX_SPINDLE_RPM",
    "CuttingLaw",
    "DeviceProfile",
    "DrillingSession",
    "SessionConfig",
    "SessionState",
    "StepResult",
    "ThermalParams",
    "poses",
]


GuidanceMode = Literal["paper", "corridor", "brake", "shaped"]
GUIDANCE_MODES: tuple[GuidanceMode, ...] = tuple(_bone_sim.GUIDANCE_MODES)
"""The guidance modes, as the core defines them (``crates/bone_sim/src/guidance/``)."""
MAX_GAIN: float = float(_bone_sim.MAX_GAIN)
"""The largest guidance gain a session takes (from the core)."""

MAX_SPINDLE_RPM: float = float(_bone_sim.MAX_SPINDLE_RPM)
"""Fastest spindle speed a pose may ask for (rpm); a faster one is refused and counted (the
cutting and thermal laws are fitted up to about 1800 rpm). Defined in the core."""
MAX_POSITION_M: float = float(_bone_sim.MAX_POSITION_M)
"""Largest coordinate (m) of a pose's position; a pose beyond it is refused and counted."""

MIN_BURR_RADIUS_M: float = float(_bone_sim.MIN_BURR_RADIUS_M)
"""Smallest burr radius (m) a session takes (a 0.5 mm drill); defined in the core."""
MAX_BURR_RADIUS_M: float = float(_bone_sim.MAX_BURR_RADIUS_M)
"""Largest burr radius (m) a session takes (a 40 mm drill); defined in the core."""
GUIDANCE_DEFAULTS: dict[str, Any] = _bone_sim.defaults()["guidance"]
"""The core's guidance laws and their defaults (``GuidanceParams``; :meth:`DrillingSession.set_guidance_params`)."""

FADING_DEFAULTS: dict[str, Any] = _bone_sim.defaults()["fading"]
"""The core's fading schedule defaults (``FadingParams``): tolerances in m, gains (1)."""

_DEFAULTS: dict[str, Any] = _bone_sim.defaults()["session"]
"""The core's ``SessionConfig::default()`` (nested): the one place the defaults below are defined."""


@dataclass(frozen=True)
class DeviceProfile:
    """Force limits of the haptic device. Defaults: the 3D Systems (Geomagic) Touch (3.3 N peak,
    0.88 N continuous, 0.4 N/mm stiffness); the motors' 20 s thermal time constant and the
    200 N/s rate limit are this project's choices (``docs/frames.md``, "Device limits")."""

    peak_force_n: float = _DEFAULTS["device"]["peak_force_n"]
    continuous_force_n: float = _DEFAULTS["device"]["continuous_force_n"]
    thermal_time_constant_s: float = _DEFAULTS["device"]["thermal_time_constant_s"]
    max_stiffness_n_per_m: float = _DEFAULTS["device"]["max_stiffness_n_per_m"]
    max_force_rate_n_per_s: float = _DEFAULTS["device"]["max_force_rate_n_per_s"]
    stale_after_s: float = _DEFAULTS["device"]["stale_after_s"]


@dataclass(frozen=True)
class CuttingLaw:
    """Thrust and torque ``= ref · (n/n₀)^a · (f/f₀)^b · (ρ/ρ₀)^c · (d/d₀)^e``: a 2.5 mm drill in
    dense cortex at 1250 rpm and 1.5 mm/s needs 21 N and 32 N·mm. The thrust's speed exponent is
    fitted to Orelaja et al. (2020); the sources of every constant are in the core's
    ``cutting.rs`` and ``docs/fidelity.md``. The drill diameter ``d`` is the burr's; ``e`` is 0.8
    for thrust and 1.8 for torque (Shaw & Oxford 1957)."""

    thrust_ref_n: float = _DEFAULTS["cutting"]["thrust_ref_n"]
    torque_ref_n_m: float = _DEFAULTS["cutting"]["torque_ref_n_m"]
    reference_rpm: float = _DEFAULTS["cutting"]["reference_rpm"]
    reference_feed_m_s: float = _DEFAULTS["cutting"]["reference_feed_m_s"]
    reference_density_kg_m3: float = _DEFAULTS["cutting"]["reference_density_kg_m3"]
    thrust_speed_exponent: float = _DEFAULTS["cutting"]["thrust_speed_exponent"]
    torque_speed_exponent: float = _DEFAULTS["cutting"]["torque_speed_exponent"]
    feed_exponent: float = _DEFAULTS["cutting"]["feed_exponent"]
    density_exponent: float = _DEFAULTS["cutting"]["density_exponent"]
    max_feed_m_s: float = _DEFAULTS["cutting"]["max_feed_m_s"]
    reference_diameter_m: float = _DEFAULTS["cutting"]["reference_diameter_m"]
    diameter_thrust_exponent: float = _DEFAULTS["cutting"]["diameter_thrust_exponent"]
    diameter_torque_exponent: float = _DEFAULTS["cutting"]["diameter_torque_exponent"]


@dataclass(frozen=True)
class ThermalParams:
    """Lumped drill-tip thermal model ``C·dT/dt = η(M·ω + F·v) − (T − T_body)/R_th``."""

    heat_capacity_j_per_k: float = _DEFAULTS["thermal"]["heat_capacity_j_per_k"]
    thermal_resistance_k_per_w: float = _DEFAULTS["thermal"]["thermal_resistance_k_per_w"]
    heat_fraction: float = _DEFAULTS["thermal"]["heat_fraction"]
    body_temperature_c: float = _DEFAULTS["thermal"]["body_temperature_c"]
    necrosis_threshold_c: float = _DEFAULTS["thermal"]["necrosis_threshold_c"]


@dataclass(frozen=True)
class SessionConfig:
    """Everything configurable about a session (SI units). ``coupling_stiffness_n_per_m=None``
    uses the device's maximum stiffness."""

    burr_radius_m: float = _DEFAULTS["burr_radius_m"]
    coupling_stiffness_n_per_m: float | None = None
    coupling_damping_n_s_per_m: float = _DEFAULTS["coupling_damping_n_s_per_m"]
    physical_full_scale_n: float = _DEFAULTS["physical_full_scale_n"]
    lateral_cut_reference_n: float = _DEFAULTS["lateral_cut_reference_n"]
    max_proxy_speed_m_s: float = _DEFAULTS["max_proxy_speed_m_s"]
    device: DeviceProfile = field(default_factory=DeviceProfile)
    cutting: CuttingLaw = field(default_factory=CuttingLaw)
    thermal: ThermalParams = field(default_factory=ThermalParams)

    def to_native(self) -> dict[str, Any]:
        """The nested dict the core takes (its ``SessionConfig``'s serde form)."""
        return {k: v for k, v in asdict(self).items() if v is not None}

    def to_flat_dict(self) -> dict[str, float]:
        """``{"burr_radius_m": ..., "device.peak_force_n": ..., ...}``: the flat form dataset cards
        store (:meth:`to_native` is what the core takes)."""
        flat: dict[str, float] = {}
        for f in fields(self):
            value = getattr(self, f.name)
            if isinstance(value, DeviceProfile | CuttingLaw | ThermalParams):
                flat.update({f"{f.name}.{k}": float(v) for k, v in asdict(value).items()})
            elif value is not None:
                flat[f.name] = float(value)
        return flat

    @classmethod
    def from_flat_dict(cls, flat: dict[str, float]) -> SessionConfig:
        """Inverse of :meth:`to_flat_dict`; unknown keys are an :class:`InvalidInputError`."""
        nested: dict[str, dict[str, float]] = {"device": {}, "cutting": {}, "thermal": {}}
        top: dict[str, Any] = {}
        known = {f.name for f in fields(cls)}
        for key, value in flat.items():
            group, _, name = key.partition(".")
            if not ((name and group in nested) or key in known):
                raise InvalidInputError(f"unknown session config key {key!r}")
            try:
                number = float(value)
            except (TypeError, ValueError):
                raise InvalidInputError(f"session config {key!r} must be a number, got {value!r}") from None
            if name and group in nested:
                nested[group][name] = number
            else:
                top[key] = number
        try:
            return cls(
                **top,
                device=DeviceProfile(**nested["device"]),
                cutting=CuttingLaw(**nested["cutting"]),
                thermal=ThermalParams(**nested["thermal"]),
            )
        except TypeError as exc:
            raise InvalidInputError(f"unknown session config key: {exc}") from None


@dataclass(frozen=True)
class SessionState:
    """A session's state after its last tick (SI units; forces on the device unless physical)."""

    time_s: float
    ticks: int
    device_m: np.ndarray
    tip_m: np.ndarray
    axis: np.ndarray
    drill_on: bool
    spindle_rpm: float
    in_contact: bool
    cutting: bool
    layer: Layer
    depth_m: float
    deviation_m: float
    feed_m_s: float
    thrust_n: float
    """Physical thrust estimate (N)."""
    torque_n_m: float
    """Physical torque estimate (N·m)."""
    cutting_density_kg_m3: float
    force_n: np.ndarray
    temperature_c: float
    peak_temperature_c: float
    time_above_47_s: float
    breakthroughs: int
    plunging: bool
    plunge_depth_m: float
    removed_mass_kg: float
    stale: bool
    rejected_poses: int
    guidance_n: np.ndarray
    """The guidance share added to the bone's force this tick (N)."""
    feedback_n: np.ndarray
    """The bone's part of the rendered force, ``force_n − guidance_n`` (N); records hold this."""
    model_available: bool
    """Whether a model reply younger than the guidance timeout is in use."""
    registration_offset_m: np.ndarray
    """How far the stylus sits ahead of where the tip's motion put it (m), from stretches the
    bone stopped holding; the tip follows ``device_m − registration_offset_m``."""
    device_thermal_load: float
    """The device motors' thermal load, 0..1 (1: only the continuous force is allowed)."""

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> SessionState:
        """From the native state dict."""
        vec = {"device_m", "tip_m", "axis", "force_n", "registration_offset_m", "guidance_n", "feedback_n"}
        values: dict[str, Any] = {k: (np.asarray(v, dtype=float) if k in vec else v) for k, v in d.items()}
        values["layer"] = Layer(int(values["layer"]))
        return cls(**values)


@dataclass(frozen=True)
class StepResult:
    """What :meth:`DrillingSession.step` produced."""

    forces_n: npt.NDArray[np.float64]
    """Force sent to the device at each tick, (N, 3) in N."""
    records: npt.NDArray[np.float64]
    """The 10 Hz records produced, (M, 11): columns :data:`dhg.core.features.RECORD_COLUMNS`."""

    @property
    def features(self) -> npt.NDArray[np.float64]:
        """The records' nine features, (M, 9)."""
        return self.records[:, 1:10]

    @property
    def times_s(self) -> npt.NDArray[np.float64]:
        """The records' times (s)."""
        return self.records[:, 0]


def poses(
    positions_m: npt.ArrayLike,
    orientations_wxyz: npt.ArrayLike = (1.0, 0.0, 0.0, 0.0),
    drill_on: npt.ArrayLike = False,
    spindle_rpm: npt.ArrayLike = 0.0,
) -> npt.NDArray[np.float64]:
    """Builds the (N, 9) pose array :meth:`DrillingSession.step` takes. Orientations, drill state and
    speed broadcast: give one for all ticks or one per tick. A row of NaN means "no pose arrived".
    """
    pos = as_points(positions_m, "positions_m")
    n = pos.shape[0]
    try:
        q = np.broadcast_to(np.asarray(orientations_wxyz, dtype=float), (n, 4))
        on = np.broadcast_to(np.asarray(drill_on, dtype=float), (n,))
        rpm = np.broadcast_to(np.asarray(spindle_rpm, dtype=float), (n,))
    except ValueError as exc:
        raise ShapeError(f"orientations, drill_on and spindle_rpm must broadcast to {n} ticks: {exc}") from None
    return np.ascontiguousarray(np.column_stack([pos, q, on, rpm]))


class DrillingSession:
    """A trainee's drilling session on a shared :class:`~dhg.Volume` along a planned path."""

    def __init__(self, volume: Volume, path: PlannedPath, config: SessionConfig | None = None) -> None:
        if not isinstance(volume, Volume):
            raise InvalidInputError(f"volume must be a dhg.Volume, got {type(volume).__name__}")
        if not isinstance(path, PlannedPath):
            raise InvalidInputError(f"path must be a dhg.PlannedPath(entry_m, target_m), got {type(path).__name__}")
        if config is not None and not isinstance(config, SessionConfig):
            raise InvalidInputError(f"config must be a SessionConfig, got {type(config).__name__}")
        self.config = config or SessionConfig()
        """The configuration."""
        self.volume = volume
        """The shared volume."""
        self._path = path
        self._s = _bone_sim.DrillingSession(
            volume._vol, tuple(path.entry_m), tuple(path.target_m), self.config.to_native()
        )

    @property
    def path(self) -> PlannedPath:
        """The planned path (m)."""
        return self._path

    @path.setter
    def path(self, path: PlannedPath) -> None:
        self._s.set_path(tuple(path.entry_m), tuple(path.target_m))
        self._path = path

    def tick(
        self,
        position_m: npt.ArrayLike | None,
        orientation_wxyz: npt.ArrayLike = (1.0, 0.0, 0.0, 0.0),
        drill_on: bool = False,
        spindle_rpm: float = 0.0,
    ) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.float64] | None]:
        """Advances one 1 ms tick with this pose (``position_m=None``: no pose arrived). Returns the
        force for the device (3,) in N and, every 100th tick, the record (11,)."""
        if position_m is None:
            return self._s.tick(None)
        row = poses(position_m, orientation_wxyz, drill_on, spindle_rpm)
        if row.shape[0] != 1:
            raise ShapeError(f"tick takes one position (3,), got shape {np.shape(position_m)}")
        return self._s.tick(tuple(row[0]))

    def step(self, pose_rows: npt.ArrayLike) -> StepResult:
        """Runs one tick per row of ``pose_rows`` (N, 9), columns :data:`dhg.core.features.POSE_COLUMNS`
        (build them with :func:`poses`). Invalid rows are counted and treated as no pose."""
        try:
            arr = np.asarray(pose_rows, dtype=np.float64)
        except (TypeError, ValueError) as exc:
            raise TypeError(f"pose_rows must be numeric (N, 9) rows: {exc}") from None
        if arr.ndim != 2 or arr.shape[1] != len(POSE_COLUMNS):
            raise ShapeError(f"pose_rows must have shape (N, {len(POSE_COLUMNS)}), got {arr.shape}")
        forces, records = self._s.step(np.ascontiguousarray(arr))
        return StepResult(forces, records)

    @property
    def state(self) -> SessionState:
        """The state after the last tick."""
        return SessionState.from_dict(self._s.state())

    def xray(self) -> XRayViews:
        """X-ray views of the bone as this session has drilled it."""
        return XRayViews(*self._s.xray())

    def set_guidance(self, mode: GuidanceMode, gain: float) -> None:
        """Renders guidance in ``mode`` at ``gain`` (0 to :data:`MAX_GAIN`; 0: none) from now on. Modes:
        ``"paper"`` (the paper's force-matching cue: predicted expert force − the trainee's),
        ``"corridor"`` (a lateral spring–damper towards the planned line beyond a deadband, no force
        along the drill), ``"brake"`` (a hold along the axis the moment the cortex gives, decaying,
        plus the model's cue where it resists: never a push forward), ``"shaped"`` (corridor +
        brake + a soft resistance ramp before the planned breakthrough). See ``docs/protocol.md``.
        Guidance needs model replies (:meth:`set_prediction`, at 10 Hz); without them it fades out."""
        if mode not in GUIDANCE_MODES:
            raise InvalidInputError(f"guidance mode must be one of {', '.join(GUIDANCE_MODES)}, got {mode!r}")
        self._s.set_guidance(mode, float(gain))

    @property
    def guidance(self) -> tuple[str, float]:
        """The guidance (mode, gain)."""
        return self._s.guidance()

    def set_corridor_profile(self, bin_m: float, stiffness_n_per_m: Sequence[float]) -> None:
        """The corridor's stiffness per depth bin of ``bin_m`` (m) along A→B (N/m; the last bin
        holds beyond B), as :mod:`dhg.learning.profiles` derives it from the experts' lateral spread; an
        empty sequence restores the fixed 400 N/m."""
        self._s.set_corridor_profile(float(bin_m), [float(k) for k in stiffness_n_per_m])

    @property
    def guidance_params(self) -> dict[str, Any]:
        """Every guidance limit and force law of the core (``GuidanceParams`` in
        ``crates/bone_sim/src/guidance/``: device newtons, SI units), e.g. ``corridor_deadband_m``,
        ``brake_hold_n``, ``warning_n``."""
        return self._s.guidance_params()

    def set_guidance_params(self, **changes: Any) -> None:
        """Changes guidance limits and force laws by name (the keys of :attr:`guidance_params`);
        an unknown name or a value out of range is an :class:`InvalidInputError`."""
        self._s.set_guidance_params(self.guidance_params | changes)

    def set_fading(self, params: dict[str, Any] | None = None, *, enabled: bool = True) -> None:
        """Fades the guidance gain over attempts, assisting as needed
        (``crates/bone_sim/src/guidance/fading.rs``, ``Fading``): each :meth:`reset` after a drilled
        attempt sets the next attempt's gain from its largest plunge and lateral deviation, and
        every ``probe_every``-th attempt is guidance-free. ``params`` overrides the core's
        defaults (``start_gain``, ``max_gain``, ``forget``, ``learn``, ``plunge_tolerance_m``,
        ``deviation_tolerance_m`` (m), ``probe_every``); ``enabled=False`` stops fading."""
        self._s.set_fading(dict(params or {}) if enabled else None)

    @property
    def fading(self) -> dict[str, Any] | None:
        """The fading schedule (params, attempts, assistance, this attempt's gain, probe,
        last_error), or None when the gain does not fade."""
        return self._s.fading()

    def drive(self, surgeon: SurgeonController, guided: bool = False) -> npt.NDArray[np.float64] | None:
        """Lets a virtual surgeon (:class:`dhg.core.surgeon.SurgeonController`) drill this session, one
        1 ms tick after another in the core, until the next 10 Hz record (its 11 columns,
        :data:`dhg.core.features.RECORD_COLUMNS`) or until the surgeon finishes (``None``). With
        ``guided``, the surgeon reads the guidance share of each tick's force as its cue."""
        return self._s.drive(surgeon.native, guided)

    def set_prediction(self, predicted_n: npt.ArrayLike) -> npt.NDArray[np.float64]:
        """A model reply: the predicted expert force (N, world frame). Returns the paper's guidance
        as mixed: gain × (predicted − the trainee's current force feedback), clamped (N)."""
        p = np.asarray(predicted_n, dtype=np.float64).reshape(-1)
        if p.shape != (3,):
            raise ShapeError(f"predicted_n must be a force (3,), got shape {np.shape(predicted_n)}")
        return self._s.set_prediction((float(p[0]), float(p[1]), float(p[2])))

    @property
    def planned_breakthrough_depth_m(self) -> float | None:
        """Tip depth along A→B (m) at which the planning CT shows the burr leaving the first
        cortex (the cortex's end less the burr radius), or None when the path crosses none."""
        return self._s.planned_breakthrough_depth_m

    def reset(self, rest_device: bool = False) -> None:
        """Restores the undrilled bone and a fresh state (guidance mode and gain are kept). The
        device goes on as it was: its force ramps down to rest at the device's rate limit (no
        step), and its motors keep their heat; with ``rest_device`` it starts at rest, with
        zero force and cold motors, as a new device would."""
        self._s.reset(rest_device)

    @property
    def memory_bytes(self) -> int:
        """Bytes the session's bone holds beyond the shared volume."""
        return self._s.memory_bytes
