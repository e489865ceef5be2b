"""The bundled TorchScript model on CUDA: how its LSTM weights can be loaded, whether cuDNN then
warns that it repacks them on every call, and what a batch of 16 windows costs each way
(python/dhg/learning/torchscript.py, load_model). Needs a CUDA device.

    python tests/benchmarks/cuda_lstm_packing.py [--calls 50]
"""

from __future__ import annotations

import argparse
import time
import warnings

import torch

from dhg.learning.weights import default_model_path


def trial(name: str, model: torch.jit.ScriptModule, x: torch.Tensor, calls: int) -> torch.Tensor:
    with warnings.catch_warnings(record=True) as seen:
        warnings.simplefilter("always")
        for _ in range(3):
            model(x)
        torch.cuda.synchronize()
        t0 = time.perf_counter()
        for _ in range(calls):
            y = model(x)
        torch.cuda.synchronize()
    print(f"{name}: {len(seen)} warnings, {(time.perf_counter() - t0) / calls * 1e3:.3f} ms per batch of 16")
    return y.detach()


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--calls", type=int, default=50)
    args = p.parse_args()
    if not torch.cuda.is_available():
        raise SystemExit("needs a CUDA device")
    path = str(default_model_path())
    x = torch.rand(16, 20, 9, device="cuda")
    ref = trial("jit.load map_location=cuda", torch.jit.load(path, map_location="cuda"), x, args.calls)
    trial("jit.load on the CPU, then .to(cuda)", torch.jit.load(path, map_location="cpu").to("cuda"), x, args.calls)
    with torch.backends.cudnn.flags(enabled=False):
        y = trial("cuDNN off", torch.jit.load(path, map_location="cuda"), x, args.calls)
    print(f"cuDNN off against on: largest difference {float((y - ref).abs().max()):.2e} N")


if __name__ == "__main__":
    main()
