"""Bone layers: the label stored per voxel and reported as the paper's "bone layer" feature.

The ids are defined once, in the Rust core (``Layer`` in ``crates/bone_sim/src/volume/layer.rs``);
this enum mirrors them and checks at import that it still does. They are part of the data format:
never renumber them.
"""

from __future__ import annotations

from enum import IntEnum

from dhg import _bone_sim

__all__ = ["Layer"]


class Layer(IntEnum):
    """Tissue class of a voxel."""

    OUTSIDE = 0
    """Air, soft tissue, or bone that has been drilled away (no drillable material)."""
    CORTICAL = 1
    """Cortical (compact) bone."""
    CANCELLOUS = 2
    """Cancellous (trabecular) bone."""
    MARROW = 3
    """Marrow in the medullary canal."""
    NECROSIS = 4
    """Necrotic bone: a lesion with a sclerotic rim around a lucent core."""


if tuple(layer.name.lower() for layer in Layer) != tuple(_bone_sim.LAYER_NAMES):
    raise ImportError(f"dhg.Layer is out of step with the native core's {_bone_sim.LAYER_NAMES}")
