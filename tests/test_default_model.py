"""The bundled default model: present, small, the documented preset, accurate on data made here
(not only by the figures its file stores), and stable (golden outputs)."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

from dhg.bone.phantom import default_phantom
from dhg.core.features import FEATURE_NAMES
from dhg.data.synth import synthesize
from dhg.learning.torchscript import load_model, read_model_meta
from dhg.learning.weights import default_model_path

sys.path.insert(0, str(Path(__file__).parent / "data"))
from make_golden import golden_windows  # noqa: E402


def test_bundled_model_is_the_documented_one():
    path = default_model_path()
    assert path.is_file(), "python/dhg/learning/weights/default.ts ships with the package"
    assert path.stat().st_size <= 4 * 1024 * 1024, "the bundled model must stay within 4 MB"
    meta = read_model_meta(path)
    assert meta["preset"] == "fusion-2x256" and meta["window"] == 20
    assert meta["input"]["features"] == list(FEATURE_NAMES)


def test_bundled_model_predicts_fresh_expert_drilling_as_well_as_its_file_says():
    """Two virtual experts the model never saw (seed 11; the default dataset is seed 0) drill the
    default phantom here; the model's next-record force predictions are scored on them. They
    must be trained-model good (under 0.2 N, well under predicting no force, better than holding
    the last force), and no worse than twice the test RMSE the model file claims."""
    ph = default_phantom()
    episodes, _ = synthesize(ph.volume, ph.path, subjects=2, attempts=1, novices=0, seed=11)
    model = load_model(default_model_path())
    w = model.window
    xs, ys = [], []
    for ep in episodes:
        f = ep.records[:, 1:10]  # the nine features, in FEATURE_NAMES order
        idx = np.arange(w)[None, :] + np.arange(len(f) - w)[:, None]
        xs.append(f[idx])
        ys.append(f[w:, 0:3])  # the force of the record after each window
    x, y = np.concatenate(xs).astype(np.float32), np.concatenate(ys)
    assert len(x) > 500, f"only {len(x)} windows"
    pred = model.predict(x)
    assert pred.shape == y.shape
    rmse = float(np.sqrt(((pred - y) ** 2).mean()))
    no_force = float(np.sqrt((y**2).mean()))
    hold_last = float(np.sqrt(((x[:, -1, 0:3] - y) ** 2).mean()))
    stored = read_model_meta(default_model_path())["metrics"]["test"]["rmse_n"]
    print(f"rmse {rmse:.4f} N (file: {stored:.4f} N), no force {no_force:.4f} N, hold last {hold_last:.4f} N")
    assert rmse < 0.2, f"RMSE {rmse:.3f} N: not a trained model"
    assert rmse < 0.25 * no_force, f"RMSE {rmse:.3f} N vs {no_force:.3f} N for predicting no force"
    assert rmse < hold_last, f"RMSE {rmse:.3f} N vs {hold_last:.3f} N for holding the last force"
    assert rmse <= 2.0 * stored, f"RMSE {rmse:.3f} N on fresh experts, the file claims {stored:.3f} N"


def test_golden_outputs():
    golden = np.load(Path(__file__).parent / "data" / "golden_model.npz")
    windows = golden_windows()
    np.testing.assert_array_equal(windows, golden["windows"])
    got = load_model(default_model_path()).predict(windows)
    np.testing.assert_allclose(got, golden["forces_n"], atol=1e-5)
    assert str(golden["data_sha256"]) == read_model_meta(default_model_path())["data"]["records_sha256"]
    assert np.all(np.abs(got) < 4.0), "predicted device forces stay in the device's range"
