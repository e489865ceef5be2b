"""Regenerates tests/data/golden_model.npz: fixed input windows and the bundled model's outputs.

Run after replacing python/dhg/learning/weights/default.ts (and say why in the commit):

    .venv/bin/python tests/data/make_golden.py
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from dhg.learning.torchscript import load_model, read_model_meta
from dhg.learning.weights import default_model_path


def golden_windows() -> np.ndarray:
    """16 deterministic windows (16, 20, 9) spanning the features' typical ranges (SI units)."""
    rng = np.random.default_rng(20211)
    lo = np.array([-1.5, -1.5, -1.5, -0.015, -0.012, 0.048, 0, -0.005, 37.0])
    hi = np.array([1.5, 1.5, 1.5, 0.052, 0.004, 0.103, 4, 0.086, 48.0])
    w = lo + (hi - lo) * rng.random((16, 20, 9))
    w[:, :, 6] = np.round(w[:, :, 6])  # layer ids are integers
    return w.astype(np.float32)


def main() -> None:
    model = load_model(default_model_path())
    windows = golden_windows()
    out = Path(__file__).with_name("golden_model.npz")
    np.savez(
        out,
        windows=windows,
        forces_n=model.predict(windows),
        data_sha256=np.array(read_model_meta(default_model_path())["data"]["records_sha256"]),
    )
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
