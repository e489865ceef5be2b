"""TorchScript inference of the DHG model on CPU: single-window latency and batched throughput.

Usage: python tests/benchmarks/bench_model.py [MODEL.ts]   (default: the bundled model)
"""

from __future__ import annotations

import platform
import sys
import time

import numpy as np
import torch

from dhg.learning.torchscript import load_model
from dhg.learning.weights import default_model_path


def main() -> None:
    path = sys.argv[1] if len(sys.argv) > 1 else default_model_path()
    model = load_model(path)
    rng = np.random.default_rng(0)
    print(
        f"model {path} ({model.meta['preset']}), torch {torch.__version__}, {torch.get_num_threads()} threads, "
        f"{platform.machine()}"
    )
    print("| batch (windows) | latency p50 | latency p99 | throughput |\n|---|---|---|---|")
    for batch in (1, 8, 64, 256):
        w = rng.normal(size=(batch, model.window, 9)).astype(np.float32)
        for _ in range(10):
            model.predict(w)
        times = []
        for _ in range(200 if batch <= 64 else 50):
            t = time.perf_counter()
            model.predict(w)
            times.append(time.perf_counter() - t)
        p50, p99 = np.median(times), np.percentile(times, 99)
        print(f"| {batch} | {p50 * 1e3:.2f} ms | {p99 * 1e3:.2f} ms | {batch / p50:,.0f} windows/s |")


if __name__ == "__main__":
    main()
