"""The model's configurations, the presets of the paper's Table 1 (see :mod:`dhg.learning.network`)
and the training settings, without torch: the CLI takes its flags' defaults from them and checks
them before anything heavy is imported."""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from typing import Any

from dhg.core.errors import InvalidInputError
from dhg.core.features import FEATURE_NAMES
from dhg.core.protocol import WINDOW_RECORDS

__all__ = ["FORCES", "PRESETS", "ModelConfig", "TrainConfig", "preset"]

FORCES = FEATURE_NAMES[0:3]


@dataclass(frozen=True)
class ModelConfig:
    """What the network sees and predicts, and its size."""

    preset: str
    input_features: tuple[str, ...] = FEATURE_NAMES
    output_features: tuple[str, ...] = FORCES
    layers: int = 2
    hidden: int = 256
    window: int = WINDOW_RECORDS
    """Time steps e of the input window (10 Hz records): the engine's window (``protocol/``)."""

    def __post_init__(self) -> None:
        for group, names in (("input_features", self.input_features), ("output_features", self.output_features)):
            unknown = [n for n in names if n not in FEATURE_NAMES]
            if unknown or not names or len(set(names)) != len(names):
                raise InvalidInputError(f"{group} must be distinct names from {FEATURE_NAMES}, got {names}")
        if not set(FORCES) <= set(self.output_features):
            raise InvalidInputError(f"output_features must include the forces {FORCES}")
        if self.layers < 1 or self.hidden < 1 or self.window < 2:
            raise InvalidInputError(
                f"layers >= 1, hidden >= 1 and window >= 2 required, got {self.layers}, {self.hidden}, {self.window}"
            )

    def index(self, names: tuple[str, ...]) -> list[int]:
        """Positions of ``names`` among the nine features."""
        return [FEATURE_NAMES.index(n) for n in names]

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready form."""
        return asdict(self)

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> ModelConfig:
        """Inverse of :meth:`to_dict`."""
        d = dict(d)
        d["input_features"] = tuple(d["input_features"])
        d["output_features"] = tuple(d["output_features"])
        return cls(**d)


PRESETS: dict[str, ModelConfig] = {
    "fusion-1x128": ModelConfig("fusion-1x128", layers=1, hidden=128),
    "fusion-2x256": ModelConfig("fusion-2x256", layers=2, hidden=256),
    "force-only-2x256": ModelConfig("force-only-2x256", input_features=FORCES, layers=2, hidden=256),
    "all-2x256": ModelConfig("all-2x256", output_features=FEATURE_NAMES, layers=2, hidden=256),
    "tiny": ModelConfig("tiny", layers=1, hidden=16),
}


def preset(name: str) -> ModelConfig:
    """The named preset (see the module docstring)."""
    if name not in PRESETS:
        raise InvalidInputError(f"unknown preset {name!r}; choose from {sorted(PRESETS)}")
    return PRESETS[name]


@dataclass(frozen=True)
class TrainConfig:
    """Optimisation settings (paper defaults where the paper gives them)."""

    learning_rate: float = 0.004
    batch_size: int = 50
    max_epochs: int = 60
    patience: int = 8
    """Epochs without a better validation RMSE before stopping."""
    test_fraction: float = 0.135
    val_fraction: float = 0.1
    seed: int = 0
    device: str = "cpu"
    """``cpu``, ``cuda`` or ``auto`` (CUDA when present)."""
    skill: str = "expert"
    """Which episodes to learn from (the paper learns from experts)."""
    best_only: bool = False
    """Only each subject's best attempt (the paper's selection)."""
    horizon: int = 1
    """Records ahead of the window's last that the target lies: 1 is the next record (the paper,
    0.1 s ahead); k predicts the expert's force k × 0.1 s ahead."""

    def __post_init__(self) -> None:
        for name, ok, want in (
            ("learning_rate", self.learning_rate > 0 and math.isfinite(self.learning_rate), "> 0"),
            ("batch_size", self.batch_size >= 1, "at least 1"),
            ("max_epochs", self.max_epochs >= 1, "at least 1"),
            ("patience", self.patience >= 1, "at least 1"),
        ):
            if not ok:
                raise InvalidInputError(f"training setting {name} must be {want}, got {getattr(self, name)!r}")
        if not (0 < self.test_fraction < 0.5 and 0 < self.val_fraction < 0.5):
            raise InvalidInputError("test_fraction and val_fraction must be in (0, 0.5)")
        if self.device not in ("cpu", "cuda", "auto"):
            raise InvalidInputError(f"device must be cpu, cuda or auto, got {self.device!r}")
        if not 1 <= self.horizon <= 50:
            raise InvalidInputError(f"horizon must be 1 to 50 records (0.1 to 5 s), got {self.horizon}")
