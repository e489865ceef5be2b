"""Exporting and loading the DHG model as TorchScript (``model.ts``).

The exported module takes raw windows (batch × window × 9, the features in
:data:`dhg.core.features.FEATURE_NAMES` order and their SI units) and returns the predicted expert
force (batch × 3) in newtons, with the scaling inside. Its metadata (feature order, units, window,
preset, data hash, metrics) is stored as the archive's extra file ``dhg.json``.
:func:`read_model_meta` (:mod:`dhg.learning.model_file`) reads it with :mod:`zipfile` alone, with no
torch needed.

TorchScript is deprecated from torch 2.10 on, in favour of ``torch.export``. The product's
contract names TorchScript, and TorchScript models still load from C++ (libtorch) without Python.
So the deprecation warnings of ``torch.jit`` are silenced here, in this one module, and nowhere
else. ``torch.export`` (``.pt2``) is the migration path once the serving side moves.
"""

from __future__ import annotations

import contextlib
import json
import os
import warnings
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt
import torch

from dhg.core.errors import InvalidInputError, ShapeError
from dhg.core.features import FEATURE_NAMES, FEATURE_UNITS
from dhg.core.version import __version__
from dhg.learning.model_file import META_NAME, MODEL_FORMAT, MODEL_VERSION, ModelFileError, read_model_meta
from dhg.learning.network import ForcePredictor, ModelConfig

__all__ = ["EXECUTORS", "GuidanceModel", "ModelFileError", "export_model", "load_model", "read_model_meta"]


@contextlib.contextmanager
def _quiet_jit() -> Iterator[None]:
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", category=FutureWarning, message=r".*torch\.jit.*deprecated.*")
        warnings.filterwarnings("ignore", category=DeprecationWarning, module=r"torch\.jit.*")
        yield


def export_model(
    predictor: ForcePredictor,
    cfg: ModelConfig,
    metrics: dict[str, Any],
    path: str | os.PathLike[str],
    profiles: dict[str, Any] | None = None,
) -> Path:
    """Scripts ``predictor`` and writes it with its metadata to ``path`` (atomically);
    ``profiles`` (:meth:`dhg.learning.profiles.DemoProfiles.to_dict`) go into the metadata too."""
    meta = {
        "format": MODEL_FORMAT,
        "version": MODEL_VERSION,
        "dhg_version": __version__,
        "input": {
            "shape": ["batch", cfg.window, len(FEATURE_NAMES)],
            "features": list(FEATURE_NAMES),
            "units": list(FEATURE_UNITS),
        },
        "output": {"shape": ["batch", 3], "features": list(FEATURE_NAMES[0:3]), "units": ["N", "N", "N"]},
        "window": cfg.window,
        "horizon_records": int(metrics.get("train_config", {}).get("horizon", 1)),
        "preset": cfg.preset,
        "model_config": cfg.to_dict(),
        "data": metrics.get("data", {}),
        "metrics": {k: metrics[k] for k in ("train", "val", "test", "samples", "epochs") if k in metrics},
    }
    if profiles is not None:
        meta["profiles"] = profiles
    path = Path(path)
    tmp = path.with_name(f".{path.name}.tmp")
    with _quiet_jit():
        scripted = torch.jit.script(predictor.eval())
        torch.jit.save(scripted, str(tmp), _extra_files={META_NAME: json.dumps(meta, indent=1)})
    os.replace(tmp, path)
    return path


@dataclass
class GuidanceModel:
    """A loaded model: checks its input and predicts expert forces (N)."""

    path: Path
    meta: dict[str, Any]
    module: torch.jit.ScriptModule
    device: str = "cpu"
    """Where the module runs (``cpu`` or ``cuda``)."""
    runner: Any = None
    """What runs the forward pass instead of :attr:`module` (an
    :class:`dhg.learning.onnx_runner.OnnxRunner`), or None for TorchScript."""

    @property
    def executor(self) -> str:
        """``onnxruntime`` or ``torchscript``: what runs the forward passes."""
        return "torchscript" if self.runner is None else "onnxruntime"

    @property
    def window(self) -> int:
        """Records per input window."""
        return int(self.meta["window"])

    @property
    def horizon(self) -> int:
        """Records ahead of the window's last that the prediction is for (1: the next record,
        0.1 s; models from before this setting predict the next record)."""
        return int(self.meta.get("horizon_records", 1))

    @property
    def profiles(self) -> Any:
        """The demonstration profiles stored with the model (:class:`dhg.learning.profiles.DemoProfiles`),
        or None for a model trained before they were stored, or on data without a planned path."""
        from dhg.learning.profiles import DemoProfiles

        d = self.meta.get("profiles")
        return None if d is None else DemoProfiles.from_dict(d)

    def predict(self, windows: npt.ArrayLike, check_output: bool = True) -> npt.NDArray[np.float64]:
        """Expert force (B, 3) in N for windows (B, window, 9) or one window (window, 9), in the
        documented feature order and SI units. Wrong shapes and NaN/inf are refused; so is a
        window whose prediction is not finite (values far outside what the model was trained on
        overflow its scaling), unless ``check_output`` is False (the model service checks each
        row of a batch itself)."""
        try:
            w = np.asarray(windows, dtype=np.float32)
        except (TypeError, ValueError) as exc:
            raise TypeError(f"windows must be numeric: {exc}") from None
        if w.ndim == 2:
            w = w[None]
        expected = (self.window, len(FEATURE_NAMES))
        if w.ndim != 3 or w.shape[1:] != expected or w.shape[0] == 0:
            raise ShapeError(f"windows must have shape (batch, {expected[0]}, {expected[1]}), got {np.shape(windows)}")
        if not np.all(np.isfinite(w)):
            raise InvalidInputError("windows contain NaN or infinite values")
        if self.runner is not None:
            out = self.runner(w)
        else:
            with torch.no_grad():
                x = torch.from_numpy(np.ascontiguousarray(w)).to(self.device)
                out = self.module(x).double().cpu().numpy()
        if check_output and not np.all(np.isfinite(out)):
            rows = np.flatnonzero(~np.all(np.isfinite(out), axis=1))
            raise InvalidInputError(
                f"the prediction for window(s) {rows.tolist()} is not finite: their values lie far outside "
                "the ranges the model was trained on"
            )
        return out


EXECUTORS = ("torchscript", "onnxruntime", "auto")
"""What may run a loaded model's forward passes (:func:`load_model`)."""


def load_model(path: str | os.PathLike[str], device: str = "cpu", executor: str = "torchscript") -> GuidanceModel:
    """Loads an exported ``model.ts`` (checking its metadata first) onto ``device``: ``cpu``,
    ``cuda``, or ``auto`` (CUDA when present). ``executor`` runs its forward passes:
    ``torchscript`` (the default: studies and evaluations stay bit for bit what they were);
    ``onnxruntime`` (CPU only; the same model exported to ONNX when loaded and checked against
    TorchScript, about three times cheaper a lone pass, :mod:`dhg.learning.onnx_runner`); or
    ``auto``, ONNX Runtime on CPU when it is installed and the check passes, else TorchScript
    (``dhg-serve``'s default)."""
    if executor not in EXECUTORS:
        raise InvalidInputError(f"executor must be one of {', '.join(EXECUTORS)}, got {executor!r}")
    if device == "auto":
        device = "cuda" if torch.cuda.is_available() else "cpu"
    if device.startswith("cuda"):
        # A TorchScript LSTM cannot keep its weights in cuDNN's one flat buffer, whatever the
        # loading (map_location, .to(), re-packing them: tried on an H200), so cuDNN packs them
        # on every call and warns each time. Measured there, a batch of 16 windows: 2.0 ms with
        # cuDNN packing per call, 3.1 ms with cuDNN off; the packing is the faster path, so the
        # warning is expected and silenced (it would print on every model query).
        # tests/benchmarks/cuda_lstm_packing.py measures it.
        warnings.filterwarnings("ignore", message="RNN module weights are not part of single contiguous chunk")
    p = Path(path)
    meta = read_model_meta(p)
    try:
        with _quiet_jit():
            module = torch.jit.load(str(p), map_location=device)
    except (RuntimeError, OSError, ValueError) as exc:
        raise ModelFileError(f"{p}: TorchScript could not load it ({exc})") from None
    module.eval()
    model = GuidanceModel(p, meta, module, device)
    if executor == "onnxruntime" or (executor == "auto" and device == "cpu"):
        model.runner = _onnx_runner(model, required=executor == "onnxruntime")
    return model


def _onnx_runner(model: GuidanceModel, required: bool) -> Any:
    """The model's :class:`~dhg.learning.onnx_runner.OnnxRunner`; without ``required``, None where
    ONNX Runtime is not installed, and None with a warning in the log where the graph fails its
    check."""
    import logging

    from dhg.learning.onnx_runner import OnnxRunner, onnx_available

    if model.device != "cpu":
        raise InvalidInputError(f"the onnxruntime executor runs on cpu only, not {model.device}")
    if not onnx_available():
        if required:
            raise InvalidInputError("the onnxruntime executor needs the onnx and onnxruntime packages")
        return None
    try:
        return OnnxRunner(model.module, model.window, threads=torch.get_num_threads())
    except Exception as exc:  # the exporter or the runtime refusing this graph
        if required:
            raise ModelFileError(f"{model.path}: cannot run under ONNX Runtime: {exc}") from None
        logging.getLogger(__name__).warning("%s: ONNX Runtime refused (%s); running TorchScript", model.path, exc)
        return None
