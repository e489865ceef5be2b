"""The DHG model (Fekri et al. 2021, section 2.3): an LSTM over a window of the 10 Hz record whose
last time step goes through a linear layer to the outputs, predicting the expert's next force.

Presets are the four rows of the paper's Table 1 (plus ``tiny`` for tests):

=================  ======  =======  ======  ======  ======================================
preset             inputs  outputs  layers  hidden  note
=================  ======  =======  ======  ======  ======================================
fusion-1x128       9       3        1       128
fusion-2x256       9       3        2       256     the DHG default
force-only-2x256   3       3        2       256     Khatami et al.'s force-only baseline
all-2x256          9       9        2       256     RMSE reported on the force part only
tiny               9       3        1       16      for tests
=================  ======  =======  ======  ======  ======================================
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Any

import torch
from torch import nn

from dhg.errors import InvalidInputError
from dhg.features import FEATURE_NAMES

__all__ = ["PRESETS", "ForcePredictor", "LSTMRegressor", "MinMaxScaler", "ModelConfig", "preset"]

FORCES = FEATURE_NAMES[0:3]


@dataclass(frozen=True)
class ModelConfig:
    """What the network sees and predicts, and its size."""

    preset: str
    input_features: tuple[str, ...] = FEATURE_NAMES
    output_features: tuple[str, ...] = FORCES
    layers: int = 2
    hidden: int = 256
    window: int = 20
    """Time steps e of the input window (10 Hz records)."""

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


class LSTMRegressor(nn.Module):
    """LSTM over normalised windows; the last step's hidden state → linear → outputs."""

    def __init__(self, cfg: ModelConfig) -> None:
        super().__init__()
        self.lstm = nn.LSTM(len(cfg.input_features), cfg.hidden, cfg.layers, batch_first=True)
        self.head = nn.Linear(cfg.hidden, len(cfg.output_features))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        out, _ = self.lstm(x)  # (B, T, H)
        return self.head(out[:, -1])  # (B, F_out)


class MinMaxScaler(nn.Module):
    """Min–max scaling of the nine features to [0, 1], fitted on training data only. Held as
    buffers so it travels inside the exported model."""

    def __init__(self) -> None:
        super().__init__()
        self.register_buffer("lo", torch.zeros(len(FEATURE_NAMES)))
        self.register_buffer("span", torch.ones(len(FEATURE_NAMES)))

    def fit(self, samples: torch.Tensor) -> MinMaxScaler:
        """Fits on (N, 9) samples; a constant feature gets span 1."""
        lo = samples.amin(dim=0)
        span = samples.amax(dim=0) - lo
        self.lo.copy_(lo)
        self.span.copy_(torch.where(span > 0, span, torch.ones_like(span)))
        return self

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return (x - self.lo) / self.span  # (..., 9)


class ForcePredictor(nn.Module):
    """What is exported: raw windows (B, T, 9) in the documented SI units → expert force (B, 3) in N,
    with the scaling inside."""

    def __init__(self, net: LSTMRegressor, scaler: MinMaxScaler, cfg: ModelConfig) -> None:
        super().__init__()
        self.net = net
        in_idx = torch.tensor(cfg.index(cfg.input_features), dtype=torch.long)
        force_pos = torch.tensor([cfg.output_features.index(n) for n in FORCES], dtype=torch.long)
        self.register_buffer("in_idx", in_idx)
        self.register_buffer("force_pos", force_pos)
        self.register_buffer("in_lo", scaler.lo[in_idx].clone())
        self.register_buffer("in_span", scaler.span[in_idx].clone())
        self.register_buffer("force_lo", scaler.lo[0:3].clone())
        self.register_buffer("force_span", scaler.span[0:3].clone())

    def forward(self, windows: torch.Tensor) -> torch.Tensor:
        x = (windows.index_select(2, self.in_idx) - self.in_lo) / self.in_span  # (B, T, F_in)
        y = self.net(x)  # (B, F_out), normalised
        return y.index_select(1, self.force_pos) * self.force_span + self.force_lo  # (B, 3) in N
