"""What the planning CT shows along the planned path: the layers crossed and where the first
cortex ends, as a surgeon reads them before drilling."""

from __future__ import annotations

from collections.abc import Iterable

from dhg.core.layers import Layer
from dhg.core.path import PLAN_STEP_M, PlannedPath
from dhg.core.volume import DrilledVolume, Volume

__all__ = ["breakthrough_depth_from_runs", "layer_runs", "planned_breakthrough_depth_m"]


def layer_runs(bone: DrilledVolume, path: PlannedPath, step_m: float = PLAN_STEP_M) -> list[tuple[str, float, float]]:
    """The pristine layers along A→B as runs (name, start depth (m), end depth (m))."""
    return _layer_runs(bone.volume, path, step_m)


def _layer_runs(volume: Volume, path: PlannedPath, step_m: float) -> list[tuple[str, float, float]]:
    runs = volume.layer_runs(path.entry_m, path.target_m, step_m)
    return [(Layer(layer).name.lower(), start, end) for layer, start, end in runs]


def planned_breakthrough_depth_m(
    volume: Volume, path: PlannedPath, burr_radius_m: float, step_m: float = PLAN_STEP_M
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
