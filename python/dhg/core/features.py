"""The paper's 10 Hz record: nine features in one fixed order, read from the native core (where
it is defined once: ``crates/bone_sim/src/record.rs``). See ``docs/frames.md``.

=====  ===============  ====  ===============================================
index  name             unit  meaning
=====  ===============  ====  ===============================================
0-2    force_{x,y,z}_n  N     feedback force on the device (guidance excluded), world frame
3-5    tip_{x,y,z}_m    m     drill tip (burr centre, proxy), world frame
6      layer            1     anatomical layer id at the burr's front point
7      depth_m          m     penetration depth along A→B, from A
8      temperature_c    °C    drill-tip temperature
=====  ===============  ====  ===============================================
"""

from __future__ import annotations

from dhg import _bone_sim

__all__ = [
    "FEATURE_INDEX",
    "FEATURE_NAMES",
    "FEATURE_UNITS",
    "FORCE_SLICE",
    "POSE_COLUMNS",
    "RECORD_COLUMNS",
    "RECORD_INDEX",
    "RECORD_PERIOD_S",
    "TICK_S",
]

FEATURE_NAMES: tuple[str, ...] = tuple(_bone_sim.FEATURE_NAMES)
"""The nine feature names, in record order."""
FEATURE_UNITS: tuple[str, ...] = tuple(_bone_sim.FEATURE_UNITS)
"""Their SI units ("1" for the layer id)."""
FEATURE_INDEX: dict[str, int] = {name: i for i, name in enumerate(FEATURE_NAMES)}
"""A feature's column in a feature vector, by name (``FEATURE_INDEX["temperature_c"]``)."""
FORCE_SLICE = slice(0, 3)
"""Where the three force components sit in a feature vector."""
TICK_S: float = float(_bone_sim.TICK_S)
"""The session tick (s): 1 kHz."""
RECORD_PERIOD_S: float = _bone_sim.RECORD_PERIOD_TICKS * TICK_S
"""Time between records (s): 10 Hz."""
RECORD_COLUMNS: tuple[str, ...] = ("time_s", *FEATURE_NAMES, "drill_on")
"""Columns of the record arrays that :meth:`dhg.DrillingSession.step` returns."""
RECORD_INDEX: dict[str, int] = {name: i for i, name in enumerate(RECORD_COLUMNS)}
"""A column of a record array, by name (``RECORD_INDEX["drill_on"]``)."""
POSE_COLUMNS: tuple[str, ...] = ("x_m", "y_m", "z_m", "qw", "qx", "qy", "qz", "drill_on", "spindle_rpm")
"""Columns of a pose row: burr centre (m, world), orientation quaternion (w, x, y, z; the tool's +z
is the drill axis, pointing in the drilling direction), drill on (> 0.5) and spindle speed (rpm)."""

if len(RECORD_COLUMNS) != _bone_sim.RECORD_COLUMNS or len(POSE_COLUMNS) != _bone_sim.POSE_COLUMNS:
    raise ImportError("dhg.core.features is out of step with the native core")
