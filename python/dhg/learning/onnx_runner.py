"""The exported model run by ONNX Runtime instead of TorchScript, for the model service on CPU.

One forward pass of the 2 × 256 LSTM over a 20-record window is what the model costs a session,
ten times a second. On CPU, ONNX Runtime's LSTM kernel does the same arithmetic in a third of
TorchScript's time after the 100 ms between one trainee's queries (``bench_inference.py --onnx``:
1.1 against 2.9 ms, docs/benchmarks.md), with predictions equal to float32 rounding.

The ONNX graph is made when the model is loaded, from the same ``model.ts`` (so there is one model
file): TorchScript in, so torch's TorchScript-based exporter, which needs the ``onnx`` package.
Before it is used, its predictions are compared with TorchScript's on windows spread over the
model's input ranges; a graph that differs by more than :data:`MAX_DIFFERENCE_N` is refused.
"""

from __future__ import annotations

import io
import os
import warnings

import numpy as np
import numpy.typing as npt
import torch

from dhg.core.features import FEATURE_NAMES

__all__ = ["MAX_DIFFERENCE_N", "OnnxRunner", "onnx_available"]

MAX_DIFFERENCE_N = 1e-4
"""Largest difference (N) allowed between the ONNX graph's prediction and TorchScript's for any
check window (measured: 4.8e-7 N, float32 rounding)."""

_FEATURES = len(FEATURE_NAMES)

CHECK_BATCHES = (1, 3, 16)
"""Batch sizes the check runs (a lone query, a small burst, a class)."""


def _thread_ids() -> set[int]:
    """Native ids of this process's unnamed threads (Linux ``/proc``; empty elsewhere): those
    that carry the process's own name, as ONNX Runtime's pool threads do. Threads that name
    themselves, such as Zenoh's, are left out, so one started meanwhile is not taken for the pool's."""
    try:
        own = _comm("/proc/self/comm")
        return {int(t) for t in os.listdir("/proc/self/task") if _comm(f"/proc/self/task/{t}/comm") == own}
    except OSError:
        return set()


def _comm(path: str) -> str | None:
    try:
        with open(path) as fh:
            return fh.read().strip()
    except OSError:  # a thread that ended meanwhile
        return None


def onnx_available() -> bool:
    """Whether ``onnx`` and ``onnxruntime`` can be imported."""
    try:
        import onnx  # noqa: F401
        import onnxruntime  # noqa: F401
    except ImportError:
        return False
    return True


class OnnxRunner:
    """A TorchScript model (``module``, windows (B, window, 9) → forces (B, 3) N) exported to ONNX
    and run by ONNX Runtime on CPU with ``threads`` intra-op threads (the calling thread alone
    when 1; more start a pool, :attr:`pool_threads`). Raises :class:`ValueError` when the graph's
    predictions differ from the module's by more than :data:`MAX_DIFFERENCE_N` on windows spread
    over the ranges the model was trained on (its input scaling; fixed seed)."""

    def __init__(self, module: torch.jit.ScriptModule, window: int, threads: int = 1):
        import onnxruntime as ort

        buf = io.BytesIO()
        with warnings.catch_warnings():
            # The TorchScript-based exporter announces its deprecation and warns that an LSTM
            # exported at one batch size may fail at another; the check below runs several.
            warnings.simplefilter("ignore")
            torch.onnx.export(
                module,
                (torch.zeros(2, window, _FEATURES),),
                buf,  # type: ignore[arg-type]  # a file-like object is documented; the stub says path only
                dynamo=False,
                input_names=["windows"],
                output_names=["force"],
                dynamic_axes={"windows": {0: "batch"}, "force": {0: "batch"}},
                opset_version=17,
            )
        opts = ort.SessionOptions()
        opts.intra_op_num_threads = max(1, int(threads))
        opts.inter_op_num_threads = 1
        opts.log_severity_level = 3  # errors only: its notes would print at every start
        # Idle pool threads would spin for the next pass: CPU a shared 2-core host needs elsewhere.
        opts.add_session_config_entry("session.intra_op.allow_spinning", "0")
        before = _thread_ids()
        self._session = ort.InferenceSession(buf.getvalue(), opts, providers=["CPUExecutionProvider"])
        self.pool_threads = sorted(_thread_ids() - before)
        """Native ids of the intra-op threads ONNX Runtime started for this session (none with one
        thread: the pass runs on the caller's). They do part of every pass, so whoever lowers the
        passes' priority lowers theirs too (:class:`dhg.live.services.ModelService`)."""
        self.threads = opts.intra_op_num_threads
        buffers = dict(module.named_buffers())
        self._scaling = (
            (buffers["in_idx"].numpy(), buffers["in_lo"].numpy(), buffers["in_span"].numpy())
            if {"in_idx", "in_lo", "in_span"} <= buffers.keys()
            else None
        )
        self.max_difference_n = self._check(module, self._check_windows(window))

    def _check_windows(self, window: int) -> np.ndarray:
        """16 windows spread uniformly over the model's input ranges ([0, 1] without a scaling)."""
        lo, span = np.zeros(_FEATURES, np.float32), np.ones(_FEATURES, np.float32)
        if self._scaling is not None:
            idx, in_lo, in_span = self._scaling
            lo[idx], span[idx] = in_lo, in_span
        rng = np.random.default_rng(0)
        return (lo + span * rng.random((max(CHECK_BATCHES), window, _FEATURES))).astype(np.float32)

    def _check(self, module: torch.jit.ScriptModule, windows: np.ndarray) -> float:
        worst = 0.0
        for b in CHECK_BATCHES:
            x = windows[:b]
            with torch.no_grad():
                want = module(torch.from_numpy(np.ascontiguousarray(x))).double().numpy()
            got = self(x)
            if got.shape != want.shape:
                raise ValueError(f"the ONNX graph answered shape {got.shape} for a batch of {b}, expected {want.shape}")
            if not np.all(np.isfinite(got)):  # (max() would drop a NaN difference)
                raise ValueError(f"the ONNX graph answered NaN or infinite forces for a batch of {b}")
            worst = max(worst, float(np.max(np.abs(got - want))))
        if not worst <= MAX_DIFFERENCE_N:
            raise ValueError(
                f"the ONNX graph's predictions differ from TorchScript's by up to {worst:.3g} N "
                f"(allowed {MAX_DIFFERENCE_N:g} N)"
            )
        return worst

    def __call__(self, windows: npt.NDArray[np.float32]) -> npt.NDArray[np.float64]:
        """Forces (B, 3) in N for windows (B, window, 9) float32, checked by the caller."""
        w = np.ascontiguousarray(windows, dtype=np.float32)
        out = np.asarray(self._session.run(None, {"windows": w})[0], dtype=np.float64)
        if self._scaling is not None:
            # A window whose scaled values overflow float32 makes TorchScript answer NaN, which the
            # model service refuses; ONNX Runtime's LSTM saturates to a finite force instead. The
            # same rows answer NaN here, so both executors refuse the same windows.
            idx, lo, span = self._scaling
            with np.errstate(over="ignore", invalid="ignore"):
                overflow = ~np.isfinite((w[:, :, idx] - lo) / span).all(axis=(1, 2))
            out[overflow] = np.nan
        return out
