"""The model's data, training, export and CLI contract (tiny preset on a tiny dataset)."""

from __future__ import annotations

import dataclasses
import json
import os
import subprocess
import sys
import zipfile
from pathlib import Path

import numpy as np
import pytest
import torch

from dhg import InvalidInputError, ShapeError
from dhg.data.dataset import load_dataset, write_dataset
from dhg.data.synth import synthesize
from dhg.learning.network import ForcePredictor, LSTMRegressor, MinMaxScaler, ModelConfig, preset
from dhg.learning.torchscript import ModelFileError, export_model, load_model, read_model_meta
from dhg.learning.train import TrainConfig, make_windows, split_windows, train

BIN = Path(sys.executable).parent


@pytest.fixture(scope="module")
def data(coarse_phantom, tmp_path_factory):
    episodes, card = synthesize(coarse_phantom.volume, coarse_phantom.path, subjects=2, attempts=1, novices=0, seed=5)
    return write_dataset(tmp_path_factory.mktemp("data") / "ds", episodes, card)


@pytest.fixture(scope="module")
def run(data, tmp_path_factory):
    out = tmp_path_factory.mktemp("run") / "tiny"
    result = train(data, out, "tiny", TrainConfig(max_epochs=2))
    return out, result


def test_windows_never_straddle_episodes(data):
    ds = load_dataset(data)
    x, y, ids = make_windows(ds, 20)
    assert x.shape[1:] == (20, 9) and y.shape == (len(x), 9)
    for ep in ds.episodes:
        rows = np.flatnonzero(ids == ep.episode_id)
        assert len(rows) == len(ep.times_s) - 20
        np.testing.assert_array_equal(x[rows[0]], ep.features[:20])
        np.testing.assert_array_equal(y[rows[-1]], ep.features[-1])
    same = ids[1:] == ids[:-1]
    np.testing.assert_array_equal(x[1:][same][:, :-1], x[:-1][same][:, 1:])


def test_a_horizon_sets_targets_further_ahead_within_the_episode(data, run, tmp_path):
    ds = load_dataset(data)
    x, y, ids = make_windows(ds, 20, horizon=5)
    for ep in ds.episodes:
        rows = np.flatnonzero(ids == ep.episode_id)
        assert len(rows) == len(ep.times_s) - 24
        np.testing.assert_array_equal(y[rows[0]], ep.features[24])  # 0.5 s after the window's last record
        np.testing.assert_array_equal(x[rows[-1]], ep.features[-25:-5])  # its last record 5 before the end
        np.testing.assert_array_equal(y[rows[-1]], ep.features[-1])
    with pytest.raises(InvalidInputError, match="horizon must be 1 to 50"):
        TrainConfig(horizon=0)
    result = train(data, tmp_path / "h3", "tiny", TrainConfig(max_epochs=1, horizon=3))
    assert result.metrics["train_config"]["horizon"] == 3
    assert load_model(tmp_path / "h3" / "model.ts").horizon == 3
    assert load_model(run[0] / "model.ts").horizon == 1  # the paper's next record


def test_chronological_split_with_gaps():
    s = split_windows(1000, 20, 0.135, 0.1)
    assert s.train.start == 0 and s.train.stop + 20 == s.val.start and s.val.stop + 20 == s.test.start
    assert s.test.stop == 1000 and s.sizes()["test"] == 135
    with pytest.raises(InvalidInputError, match="too few"):
        split_windows(30, 20, 0.135, 0.1)


def test_training_outputs_and_scaler_fitted_on_train_only(run, data):
    out, result = run
    for name in ("model.ts", "metrics.json", "loss.png", "forces.png", "checkpoint.pt"):
        assert (out / name).is_file(), name
    m = json.loads((out / "metrics.json").read_text())
    assert m["preset"] == "tiny" and m["epochs"] == 2
    assert len(m["test"]["rmse_n_per_axis"]) == 3 and m["test"]["rmse_n"] > 0
    assert m["samples"]["test"] > 0 and m["train_config"]["learning_rate"] == 0.004
    ds = load_dataset(data)
    x, y, _ = make_windows(ds, 20)
    split = split_windows(len(x), 20, 0.135, 0.1)
    train_rows = np.concatenate([x[split.train].reshape(-1, 9), y[split.train]])
    all_rows = np.concatenate([x.reshape(-1, 9), y])
    module = load_model(out / "model.ts").module
    lo, hi = module.in_lo.numpy(), module.in_lo.numpy() + module.in_span.numpy()
    np.testing.assert_allclose(lo, train_rows.min(axis=0), rtol=1e-6, atol=1e-9)
    np.testing.assert_allclose(hi, train_rows.max(axis=0), rtol=1e-5, atol=1e-9)
    np.testing.assert_allclose(module.force_lo.numpy(), train_rows[:, 0:3].min(axis=0), rtol=1e-6, atol=1e-9)
    del all_rows


def test_the_scaler_never_sees_the_test_windows(coarse_phantom, tmp_path):
    """The last attempt's final records (the test split) run 30 °C hotter than anything before:
    a scaler fitted on the training windows alone does not reach them."""
    import dataclasses

    episodes, card = synthesize(coarse_phantom.volume, coarse_phantom.path, subjects=2, attempts=1, novices=0, seed=5)
    records = episodes[-1].records.copy()
    records[-len(records) // 5 :, 9] += 30.0  # temperature_c
    episodes[-1] = dataclasses.replace(episodes[-1], records=records)
    data = write_dataset(tmp_path / "ds", episodes, card)
    train(data, tmp_path / "run", "tiny", TrainConfig(max_epochs=1))
    module = load_model(tmp_path / "run" / "model.ts").module
    hot = float(records[:, 9].max())
    hi = float(module.in_lo[8] + module.in_span[8])
    assert hi < hot - 20.0, (hi, hot)


def test_resume_continues_from_the_checkpoint(run, data, tmp_path):
    import shutil

    out = tmp_path / "resumed"
    shutil.copytree(run[0], out)
    result = train(data, out, "tiny", TrainConfig(max_epochs=4), resume=True)
    assert [h["epoch"] for h in result.history] == [0, 1, 2, 3]
    assert result.history[:2] == run[1].history
    fresh = train(data, tmp_path / "fresh", "tiny", TrainConfig(max_epochs=4))
    np.testing.assert_allclose(
        [h["val_rmse"] for h in fresh.history], [h["val_rmse"] for h in result.history], rtol=1e-5
    )
    with pytest.raises(InvalidInputError, match="was trained with"):
        train(data, out, "fusion-1x128", TrainConfig(max_epochs=5), resume=True)


def test_eager_and_torchscript_agree(tmp_path):
    torch.manual_seed(0)
    for name in ("tiny", "force-only-2x256", "all-2x256"):
        cfg = preset(name)
        scaler = MinMaxScaler().fit(torch.rand(100, 9) * torch.tensor([3, 3, 3, 0.1, 0.1, 0.1, 4, 0.09, 60]))
        eager = ForcePredictor(LSTMRegressor(cfg), scaler, cfg).eval()
        path = export_model(eager, cfg, {}, tmp_path / f"{name}.ts")
        loaded = load_model(path)
        windows = np.random.default_rng(1).normal(size=(8, 20, 9)).astype(np.float32)
        with torch.no_grad():
            ref = eager(torch.from_numpy(windows)).numpy()
        got = loaded.predict(windows)
        assert got.shape == (8, 3)
        np.testing.assert_allclose(got, ref, atol=1e-5)


def test_onnx_runtime_predicts_what_torchscript_does(run):
    """The model service's default executor on CPU: the same model.ts exported to ONNX when
    loaded, checked against TorchScript, predicting the same forces (float32 rounding) for lone
    windows and batches, and refusing the same bad windows."""
    from dhg.learning.weights import default_model_path

    for path in (run[0] / "model.ts", default_model_path()):
        ts = load_model(path)
        ort = load_model(path, executor="onnxruntime")
        assert (ts.executor, ort.executor) == ("torchscript", "onnxruntime")
        assert ort.runner.max_difference_n < 1e-4 and ort.runner.threads == torch.get_num_threads()
        rng = np.random.default_rng(2)
        for batch in (1, 2, 7, 33):
            windows = rng.normal(size=(batch, ts.window, 9)).astype(np.float32) * [
                1,
                1,
                1,
                0.05,
                0.05,
                0.05,
                1,
                0.04,
                30,
            ]
            got, want = ort.predict(windows), ts.predict(windows)
            assert got.shape == (batch, 3) and got.dtype == np.float64
            np.testing.assert_allclose(got, want, atol=1e-4, rtol=0)
        bad = np.zeros((2, ts.window, 9))
        bad[1, 5, 8] = np.inf
        with pytest.raises(InvalidInputError, match="NaN or infinite"):
            ort.predict(bad)
        with pytest.raises(ShapeError):
            ort.predict(np.zeros((1, ts.window + 1, 9)))
        # A window whose scaled values overflow float32: TorchScript answers NaN (and the service
        # refuses it); ONNX Runtime's LSTM would saturate to a finite force, so it answers NaN too.
        huge = np.zeros((3, ts.window, 9), dtype=np.float32)
        huge[1] = 3e38
        for m in (ts, ort):
            with pytest.raises(InvalidInputError, match=r"window\(s\) \[1\] is not finite"):
                m.predict(huge)
    # auto: ONNX Runtime on CPU (installed with DHG's pinned dependencies).
    assert load_model(run[0] / "model.ts", executor="auto").executor == "onnxruntime"
    with pytest.raises(InvalidInputError, match="executor must be one of"):
        load_model(run[0] / "model.ts", executor="tensorrt")


def test_onnx_runtime_refuses_a_graph_that_predicts_otherwise(run, monkeypatch):
    """The check against TorchScript is real: a graph whose answers differ is refused when asked
    for by name, and 'auto' falls back to TorchScript."""
    from dhg.learning import onnx_runner

    real_call = onnx_runner.OnnxRunner.__call__
    monkeypatch.setattr(onnx_runner.OnnxRunner, "__call__", lambda self, w: real_call(self, w) + 0.01)
    with pytest.raises(ModelFileError, match=r"differ from TorchScript's by up to 0\.01 N"):
        load_model(run[0] / "model.ts", executor="onnxruntime")
    assert load_model(run[0] / "model.ts", executor="auto").executor == "torchscript"
    # A graph answering NaN is refused too (a NaN difference must not pass for none).
    monkeypatch.setattr(onnx_runner.OnnxRunner, "__call__", lambda self, w: real_call(self, w) * np.nan)
    with pytest.raises(ModelFileError, match="NaN or infinite forces"):
        load_model(run[0] / "model.ts", executor="onnxruntime")


def test_loader_refuses_bad_windows_and_files(run, tmp_path):
    model = load_model(run[0] / "model.ts")
    assert model.predict(np.zeros((20, 9))).shape == (1, 3)
    with pytest.raises(ShapeError, match=r"\(batch, 20, 9\)"):
        model.predict(np.zeros((4, 19, 9)))
    with pytest.raises(ShapeError):
        model.predict(np.zeros((4, 20, 3)))
    bad = np.zeros((2, 20, 9))
    bad[1, 5, 8] = np.nan
    with pytest.raises(InvalidInputError, match="NaN"):
        model.predict(bad)
    with pytest.raises(ModelFileError, match="no such"):
        load_model(tmp_path / "absent.ts")
    (tmp_path / "junk.ts").write_bytes(b"not a zip")
    with pytest.raises(ModelFileError, match="unreadable"):
        load_model(tmp_path / "junk.ts")


def test_metadata_is_readable_without_torch(run):
    meta = read_model_meta(run[0] / "model.ts")
    assert meta["format"] == "dhg-model" and meta["window"] == 20 and meta["preset"] == "tiny"
    assert meta["input"]["units"][8] == "°C" and meta["output"]["units"] == ["N", "N", "N"]
    assert "records_sha256" in meta["data"] and "test" in meta["metrics"]
    with zipfile.ZipFile(run[0] / "model.ts") as z:
        assert any(n.endswith("/extra/dhg.json") for n in z.namelist())


def test_model_config_validation():
    with pytest.raises(InvalidInputError, match="unknown preset"):
        preset("huge")
    with pytest.raises(InvalidInputError, match="input_features"):
        ModelConfig("x", input_features=("bogus",))
    with pytest.raises(InvalidInputError, match="forces"):
        ModelConfig("x", output_features=("depth_m",))
    with pytest.raises(InvalidInputError, match="window"):
        ModelConfig("x", window=1)
    with pytest.raises(InvalidInputError, match="device"):
        TrainConfig(device="tpu")


def _cli(*args: str, env: dict[str, str] | None = None) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [str(BIN / "dhg"), *args], capture_output=True, text=True, timeout=600, env={**os.environ, **(env or {})}
    )


@pytest.mark.slow  # make test-all (and CI) runs it; make test leaves it out
def test_cli_train_evaluate_and_ablate(data, tmp_path):
    r = _cli("train", "--data", str(data), "--out", str(tmp_path / "r"), "--preset", "tiny", "--epochs", "1")
    assert r.returncode == 0, r.stderr
    assert "RMSE" in r.stdout and (tmp_path / "r" / "model.ts").is_file()
    r = _cli("evaluate", "--model", str(tmp_path / "r" / "model.ts"), "--data", str(data))
    assert r.returncode == 0, r.stderr
    result = json.loads(r.stdout)
    assert result["windows"] > 100 and len(result["rmse_n_per_axis"]) == 3
    r = _cli("evaluate", "--model", str(tmp_path / "nothing.ts"), "--data", str(data))
    assert r.returncode == 3 and "no such model file" in r.stderr
    from dhg.learning.ablation import ablate

    results = ablate(data, tmp_path / "ab", TrainConfig(max_epochs=1), presets=("tiny",), seeds=(0, 1))
    table = (tmp_path / "ab" / "table.md").read_text()
    assert "| configuration | input | output | time steps |" in table and "| tiny | 9 | 3 | 20 | 1 | 16 |" in table
    assert "| 2 |" in table and " ± " in table
    saved = json.loads((tmp_path / "ab" / "results.json").read_text())
    assert len(saved["runs"]["tiny"]) == 2 and saved["persistence_baseline"]["rmse_n"] > 0
    assert "Persistence baseline" in table
    assert results["tiny"][0]["train_config"]["seed"] == 0 and results["tiny"][1]["train_config"]["seed"] == 1


@pytest.mark.slow  # make test-all (and CI) runs it; make test leaves it out
def test_distributed_training_with_two_cpu_processes(data, tmp_path):
    """torchrun with 2 processes and the gloo backend on CPU (DistributedDataParallel)."""
    out = tmp_path / "ddp"
    cmd = [
        str(BIN / "torchrun"),
        "--standalone",
        "--nproc_per_node",
        "2",
        "-m",
        "dhg.cli.main",
        "train",
        "--data",
        str(data),
        "--out",
        str(out),
        "--preset",
        "tiny",
        "--epochs",
        "2",
    ]
    r = subprocess.run(cmd, capture_output=True, text=True, timeout=600, env={**os.environ, "OMP_NUM_THREADS": "1"})
    assert r.returncode == 0, r.stderr[-2000:]
    m = json.loads((out / "metrics.json").read_text())
    assert m["epochs"] == 2 and (out / "model.ts").is_file()
    load_model(out / "model.ts").predict(np.zeros((1, 20, 9)))


@pytest.mark.gpu  # make test-all (and CI) selects it; it skips without CUDA
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_training_on_a_gpu_exports_a_model_a_cpu_server_loads(data, tmp_path):
    """``dhg train --device cuda``: the run trains on the GPU, learns as well as the same run on
    the CPU (same seed; the two differ only by floating-point order), and writes a TorchScript
    file that a CPU-only ``dhg-serve`` loads and that predicts what the trained network does."""
    cfg = TrainConfig(max_epochs=3)
    gpu = train(data, tmp_path / "gpu", "tiny", dataclasses.replace(cfg, device="cuda"))
    cpu = train(data, tmp_path / "cpu", "tiny", cfg)
    assert gpu.metrics["device"].startswith("cuda") and cpu.metrics["device"] == "cpu"
    g, c = gpu.metrics["test"]["rmse_n"], cpu.metrics["test"]["rmse_n"]
    assert 0.5 < g / c < 2.0, f"test RMSE on the GPU {g:.4f} N against {c:.4f} N on the CPU"
    windows = np.random.default_rng(0).uniform(0.0, 1.0, (4, 20, 9))
    served = load_model(tmp_path / "gpu" / "model.ts", device="cpu").predict(windows)
    on_gpu = load_model(tmp_path / "gpu" / "model.ts", device="cuda").predict(windows)
    assert served.shape == (4, 3) and np.all(np.isfinite(served))
    # cuDNN's LSTM (TF32 on Hopper) and the CPU's agree to about 0.2 mN on forces of about 1 N.
    np.testing.assert_allclose(served, on_gpu, rtol=0, atol=2e-3)


def test_a_trained_model_carries_the_experts_demonstration_profiles(run, data):
    """dhg train stores the profiles of its dataset's experts in the model file, so a server
    given the model has them (dhg.learning.profiles)."""
    from dhg.learning.profiles import build_profiles

    out, _ = run
    p = load_model(out / "model.ts").profiles
    assert p is not None and p.episodes == 2
    assert p == build_profiles(load_dataset(data)), "the stored profiles are not the dataset's"
    assert len(p.breakthrough_depths_m) == 2 and all(0 < b < 10e-3 for b in p.breakthrough_depths_m)
    assert max(p.thrust_mean_n) > 0.5, "no thrust in the cortex"
