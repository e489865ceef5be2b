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

# No `from __future__ import annotations` here: TorchScript reads the buffers' class annotations
# (which tell type checkers they are tensors) and cannot resolve them as strings.
import torch
from torch import nn

from dhg.core.features import FEATURE_NAMES
from dhg.learning.presets import FORCES, PRESETS, ModelConfig, preset

__all__ = ["PRESETS", "ForcePredictor", "LSTMRegressor", "MinMaxScaler", "ModelConfig", "preset"]


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

    lo: torch.Tensor
    span: torch.Tensor

    def __init__(self) -> None:
        super().__init__()
        self.register_buffer("lo", torch.zeros(len(FEATURE_NAMES)))
        self.register_buffer("span", torch.ones(len(FEATURE_NAMES)))

    def fit(self, samples: torch.Tensor) -> "MinMaxScaler":
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

    in_idx: torch.Tensor
    force_pos: torch.Tensor
    in_lo: torch.Tensor
    in_span: torch.Tensor
    force_lo: torch.Tensor
    force_span: torch.Tensor

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
