"""Models that ship with DHG.

``default.ts`` is the fusion-2x256 preset trained on the default synthetic dataset. It is
reproduced by (see ``docs/model.md``)::

    dhg synth --out data/default            # 6 experts x 3 attempts + 2 novices, seed 0
    dhg train --data data/default --out runs/default --preset fusion-2x256
    cp runs/default/model.ts python/dhg/learning/weights/default.ts
"""

from __future__ import annotations

from pathlib import Path

__all__ = ["default_model_path"]


def default_model_path() -> Path:
    """Path of the bundled default model (``model.ts`` format, see :mod:`dhg.learning.torchscript`)."""
    return Path(__file__).with_name("default.ts")
