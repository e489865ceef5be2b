"""The bundled default model: present, small, the documented preset, and stable (golden outputs)."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

from dhg.export import load_model, read_model_meta
from dhg.features import FEATURE_NAMES
from dhg.models import default_model_path

sys.path.insert(0, str(Path(__file__).parent / "data"))
from make_golden import golden_windows  # noqa: E402


def test_bundled_model_is_the_documented_one():
    path = default_model_path()
    assert path.is_file(), "python/dhg/models/default.ts ships with the package"
    assert path.stat().st_size <= 4 * 1024 * 1024, "the bundled model must stay within 4 MB"
    meta = read_model_meta(path)
    assert meta["preset"] == "fusion-2x256" and meta["window"] == 20
    assert meta["input"]["features"] == list(FEATURE_NAMES)
    assert meta["metrics"]["test"]["rmse_n"] < 0.2, "trained, not random"


def test_golden_outputs():
    golden = np.load(Path(__file__).parent / "data" / "golden_model.npz")
    windows = golden_windows()
    np.testing.assert_array_equal(windows, golden["windows"])
    got = load_model(default_model_path()).predict(windows)
    np.testing.assert_allclose(got, golden["forces_n"], atol=1e-5)
    assert str(golden["data_sha256"]) == read_model_meta(default_model_path())["data"]["records_sha256"]
    assert np.all(np.abs(got) < 4.0), "predicted device forces stay in the device's range"
