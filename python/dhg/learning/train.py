"""Training the DHG model (the paper's section 3.1 defaults: Adam, learning rate 0.004, batch 50,
RMSE loss, min–max scaling, a chronological split).

Data: windows of ``e`` consecutive records of one episode predict the next record (windows never
straddle two episodes), or with ``horizon`` k the record k steps after the window's last (the
expert's force k × 0.1 s ahead, a cue that leads). The windows are ordered as the dataset is
(episode by episode, in time) and split chronologically without shuffling. The last
``test_fraction`` of the windows (≈ 13.5 %, the paper's share) form the test set, and the last
``val_fraction`` of the rest the validation set for early stopping. One window's worth of windows
(plus the horizon) is dropped at each boundary, so no record is in two sets. The scaler is fitted
on the training windows only.

Runs on CPU by default and on CUDA when asked (``device="cuda"`` or ``"auto"``). Under ``torchrun``
it trains with DistributedDataParallel; rank 0 writes everything.
"""

from __future__ import annotations

import json
import math
import os
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F

from dhg.core.errors import InvalidInputError
from dhg.core.features import FEATURE_NAMES
from dhg.data.dataset import Dataset, load_dataset
from dhg.learning.network import ForcePredictor, LSTMRegressor, MinMaxScaler, ModelConfig, preset
from dhg.learning.presets import TrainConfig

__all__ = ["Split", "TrainConfig", "make_windows", "set_seed", "split_windows", "train"]


def make_windows(ds: Dataset, window: int, skill: str | None = "expert", best_only: bool = False, horizon: int = 1):
    """Windows (N, window, 9) and their targets (N, 9), the record ``horizon`` steps after each
    window's last (1: the next record), in dataset order; none straddles two episodes. Returns
    (windows, targets, episode_ids)."""
    if horizon < 1:
        raise InvalidInputError(f"horizon must be at least 1 record, got {horizon}")
    xs, ys, ids = [], [], []
    for ep in ds.select(skill, best_only):
        f = ep.features
        n = len(f) - window - horizon + 1
        if n <= 0:
            continue
        idx = np.arange(window)[None, :] + np.arange(n)[:, None]
        xs.append(f[idx])  # (n, window, 9)
        ys.append(f[window + horizon - 1 :])  # (n, 9)
        ids.append(np.full(n, ep.episode_id))
    if not xs:
        raise InvalidInputError(
            f"no {skill or 'any'} episode is longer than the window of {window} records plus the horizon of {horizon}"
        )
    return np.concatenate(xs), np.concatenate(ys), np.concatenate(ids)


@dataclass
class Split:
    """Index ranges of the chronological split."""

    train: slice
    val: slice
    test: slice

    def sizes(self) -> dict[str, int]:
        """Samples per set."""
        return {k: v.stop - v.start for k, v in asdict(self).items()}


def split_windows(n: int, window: int, test_fraction: float, val_fraction: float) -> Split:
    """Chronological train/val/test ranges over ``n`` ordered windows, with a gap of ``window``
    windows before each boundary so that no record is shared between sets (pass the window plus
    the horizon less one when targets lie further ahead)."""
    n_test = int(round(n * test_fraction))
    test_start = n - n_test
    train_val_end = test_start - window
    n_val = int(round(train_val_end * val_fraction))
    val_start = train_val_end - n_val
    train_end = val_start - window
    if train_end < 1 or n_val < 1 or n_test < 1:
        raise InvalidInputError(f"{n} windows are too few to split (need train, validation and test sets)")
    return Split(slice(0, train_end), slice(val_start, train_val_end), slice(test_start, n))


def _device(name: str) -> torch.device:
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if name == "cuda" and not torch.cuda.is_available():
        raise InvalidInputError("device 'cuda' was asked for but no CUDA device is available")
    return torch.device(name)


@dataclass
class TrainResult:
    """What a training run produced."""

    run_dir: Path
    metrics: dict[str, Any]
    history: list[dict[str, float]] = field(default_factory=list)


def _rmse(pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    return torch.sqrt(F.mse_loss(pred, target) + 1e-12)


def set_seed(seed: int) -> None:
    """Seeds the generators training draws from (Python's and torch's, on CPU and every CUDA
    device), as lerobot's ``set_seed`` does: the one place a run's seed is applied. DHG's numpy
    code takes explicit ``np.random.default_rng(seed)`` generators, never the global one."""
    import random

    random.seed(seed)
    torch.manual_seed(seed)


@dataclass(frozen=True)
class _Ranks:
    """This process's place in a ``torchrun`` job (one rank, world 1, when not under one)."""

    ddp: bool
    rank: int
    world: int
    device: torch.device

    @classmethod
    def start(cls, device_name: str) -> _Ranks:
        """Joins the process group when ``WORLD_SIZE`` > 1 (NCCL on CUDA, else gloo)."""
        world = int(os.environ.get("WORLD_SIZE", "1"))
        rank = 0
        if world > 1:
            import torch.distributed as dist

            dist.init_process_group("nccl" if device_name != "cpu" and torch.cuda.is_available() else "gloo")
            rank = dist.get_rank()
        device = _device(device_name)
        if world > 1 and device.type == "cuda":
            device = torch.device("cuda", int(os.environ.get("LOCAL_RANK", "0")))
        return cls(world > 1, rank, world, device)

    def stop(self) -> None:
        if self.ddp:
            import torch.distributed as dist

            dist.destroy_process_group()

    def epoch_order(self, n: int, seed: int, epoch: int) -> torch.Tensor:
        """This rank's shuffled share of ``n`` training windows for ``epoch``: torch's
        ``DistributedSampler`` with ``drop_last``, so every rank runs the same number of batches
        (DDP's all-reduce would otherwise wait forever on a rank with one batch more)."""
        from torch.utils.data.distributed import DistributedSampler

        sampler: DistributedSampler[int] = DistributedSampler(
            range(n),  # type: ignore[arg-type]  # any sized sequence: only its length is used
            num_replicas=self.world,
            rank=self.rank,
            shuffle=True,
            seed=seed,
            drop_last=True,
        )
        sampler.set_epoch(epoch)
        return torch.tensor(list(sampler), dtype=torch.long)


@dataclass
class _Windows:
    """The dataset's windows, split and scaled for one model."""

    x: torch.Tensor
    """(N, T, 9) windows in SI units."""
    y: torch.Tensor
    """(N, 9) targets in SI units."""
    split: Split
    scaler: MinMaxScaler
    xn: torch.Tensor
    """(N, T, F_in) the model's inputs, scaled."""
    yn: torch.Tensor
    """(N, F_out) its outputs, scaled."""
    force_pos: torch.Tensor
    """Where the three force components lie among the outputs."""

    @classmethod
    def build(cls, ds: Dataset, mcfg: ModelConfig, cfg: TrainConfig) -> _Windows:
        x_all, y_all, _ = make_windows(ds, mcfg.window, cfg.skill, cfg.best_only, cfg.horizon)
        split = split_windows(len(x_all), mcfg.window + cfg.horizon - 1, cfg.test_fraction, cfg.val_fraction)
        x = torch.as_tensor(x_all, dtype=torch.float32)
        y = torch.as_tensor(y_all, dtype=torch.float32)
        scaler = MinMaxScaler().fit(torch.cat([x[split.train].reshape(-1, 9), y[split.train]]))
        in_idx = torch.tensor(mcfg.index(mcfg.input_features))
        out_idx = torch.tensor(mcfg.index(mcfg.output_features))
        force_pos = torch.tensor([mcfg.output_features.index(n) for n in FEATURE_NAMES[0:3]])
        xn = scaler(x).index_select(2, in_idx)
        yn = scaler(y).index_select(1, out_idx)
        return cls(x, y, split, scaler, xn, yn, force_pos)


def _train_epoch(
    model: torch.nn.Module,
    opt: torch.optim.Optimizer,
    x_tr: torch.Tensor,
    y_tr: torch.Tensor,
    order: torch.Tensor,
    batch_size: int,
    device: torch.device,
) -> float:
    """One pass over ``order``'s windows in batches; returns the mean training RMSE."""
    model.train()
    total, count = 0.0, 0
    for b in range(0, len(order), batch_size):
        idx = order[b : b + batch_size]
        xb, yb = x_tr[idx].to(device), y_tr[idx].to(device)
        opt.zero_grad(set_to_none=True)
        loss = _rmse(model(xb), yb)
        loss.backward()
        opt.step()
        total += float(loss.detach()) * len(idx)
        count += len(idx)
    return total / max(count, 1)


def _save_atomically(obj: Any, path: Path) -> None:
    """``torch.save`` to a temporary file, then an atomic rename: a crash leaves the old file."""
    tmp = path.with_suffix(".tmp")
    torch.save(obj, tmp)
    os.replace(tmp, path)


@dataclass
class _Progress:
    """Where a run stands: its epochs so far, the best validation RMSE and the weights that gave it,
    and the epochs since (for early stopping). What ``checkpoint.pt`` holds besides the model and
    the optimiser, so a resumed run goes on exactly where it stopped."""

    next_epoch: int = 0
    best_val: float = math.inf
    best_state: dict[str, torch.Tensor] | None = None
    history: list[dict[str, float]] = field(default_factory=list)
    bad_epochs: int = 0

    def record(self, epoch: int, train_rmse: float, val_rmse: float, net: torch.nn.Module) -> None:
        """Adds an epoch; keeps the weights when the validation RMSE improved by more than 1e-6."""
        self.history.append({"epoch": epoch, "train_rmse": train_rmse, "val_rmse": val_rmse})
        self.next_epoch = epoch + 1
        if val_rmse < self.best_val - 1e-6:
            self.best_val, self.bad_epochs = val_rmse, 0
            self.best_state = {k: v.detach().cpu().clone() for k, v in net.state_dict().items()}
        else:
            self.bad_epochs += 1

    def checkpoint(
        self, net: torch.nn.Module, opt: torch.optim.Optimizer, mcfg: ModelConfig, cfg: TrainConfig
    ) -> dict[str, Any]:
        """What ``checkpoint.pt`` holds after the last recorded epoch."""
        return {
            "model": net.state_dict(),
            "optimizer": opt.state_dict(),
            "model_config": mcfg.to_dict(),
            "train_config": asdict(cfg),
            "epoch": self.next_epoch - 1,
            "best_val": self.best_val,
            "best_state": self.best_state,
            "history": self.history,
            "bad_epochs": self.bad_epochs,
            "torch_rng": torch.get_rng_state(),
        }

    @classmethod
    def resume(
        cls,
        path: Path,
        net: torch.nn.Module,
        opt: torch.optim.Optimizer,
        mcfg: ModelConfig,
        device: torch.device,
    ) -> _Progress:
        """Loads ``path`` into ``net`` and ``opt`` (and torch's generator); refuses a checkpoint
        of another model configuration."""
        ckpt = torch.load(path, map_location=device, weights_only=False)
        if ckpt["model_config"] != mcfg.to_dict():
            raise InvalidInputError(f"{path} was trained with {ckpt['model_config']}, not {mcfg.to_dict()}")
        net.load_state_dict(ckpt["model"])
        opt.load_state_dict(ckpt["optimizer"])
        torch.set_rng_state(ckpt["torch_rng"])
        return cls(ckpt["epoch"] + 1, ckpt["best_val"], ckpt["best_state"], ckpt["history"], ckpt["bad_epochs"])


def train(
    data_dir: str | os.PathLike[str],
    run_dir: str | os.PathLike[str],
    model_cfg: ModelConfig | str = "fusion-2x256",
    cfg: TrainConfig | None = None,
    resume: bool = False,
    progress: Callable[[int, int, float, float], None] | None = None,
) -> TrainResult:
    """Trains a model on a dataset folder and writes the run folder: ``checkpoint.pt``,
    ``metrics.json``, ``loss.png``, ``forces.png`` and the exported ``model.ts``.
    ``progress(epoch, max_epochs, train_rmse, val_rmse)`` is called after each epoch."""
    cfg = cfg or TrainConfig()
    mcfg = preset(model_cfg) if isinstance(model_cfg, str) else model_cfg
    ranks = _Ranks.start(cfg.device)
    device = ranks.device
    run = Path(run_dir)
    if ranks.rank == 0:
        run.mkdir(parents=True, exist_ok=True)
    set_seed(cfg.seed)

    ds = load_dataset(data_dir)
    w = _Windows.build(ds, mcfg, cfg)
    net = LSTMRegressor(mcfg).to(device)
    model: torch.nn.Module = net
    if ranks.ddp:
        model = torch.nn.parallel.DistributedDataParallel(
            net, device_ids=[device.index] if device.type == "cuda" else None
        )
    opt = torch.optim.Adam(model.parameters(), lr=cfg.learning_rate)
    ckpt_path = run / "checkpoint.pt"
    done = _Progress()
    if resume and ckpt_path.is_file():
        done = _Progress.resume(ckpt_path, net, opt, mcfg, device)

    x_tr, y_tr = w.xn[w.split.train], w.yn[w.split.train]
    t0 = time.perf_counter()
    for epoch in range(done.next_epoch, cfg.max_epochs):
        if done.bad_epochs >= cfg.patience:
            break
        order = ranks.epoch_order(len(x_tr), cfg.seed, epoch)
        train_rmse = _train_epoch(model, opt, x_tr, y_tr, order, cfg.batch_size, device)
        val = _evaluate(net, w.xn[w.split.val], w.yn[w.split.val], w.force_pos, device)["rmse_normalized"]
        done.record(epoch, train_rmse, val, net)
        if ranks.rank == 0:
            _save_atomically(done.checkpoint(net, opt, mcfg, cfg), ckpt_path)
        if progress is not None:
            progress(epoch + 1, cfg.max_epochs, train_rmse, val)
    train_time = time.perf_counter() - t0
    history = done.history
    if done.best_state is not None:
        net.load_state_dict(done.best_state)
    net = net.cpu().eval()
    metrics: dict[str, Any] = {
        "preset": mcfg.preset,
        "model_config": mcfg.to_dict(),
        "train_config": asdict(cfg),
        "samples": w.split.sizes(),
        "epochs": len(history),
        "best_epoch": int(np.argmin([h["val_rmse"] for h in history])) if history else -1,
        "train_time_s": train_time,
        "device": str(device),
        "data": {"path": str(ds.path), "records_sha256": ds.card["files"]["records.parquet"]["sha256"]},
        "parameters": sum(p.numel() for p in net.parameters()),
    }
    for name, sl in (("train", w.split.train), ("val", w.split.val), ("test", w.split.test)):
        metrics[name] = _evaluate(net, w.xn[sl], w.yn[sl], w.force_pos, torch.device("cpu"), w.scaler.span[0:3])
    if ranks.rank == 0:
        _write_run(run, net, w, mcfg, metrics, history, ds)
    ranks.stop()
    return TrainResult(run, metrics, history)


def _write_run(
    run: Path,
    net: LSTMRegressor,
    w: _Windows,
    mcfg: ModelConfig,
    metrics: dict[str, Any],
    history: list[dict[str, float]],
    ds: Dataset,
) -> None:
    """The run folder's plots, the TorchScript model (with the demonstration profiles) and, last,
    ``metrics.json``: a run with it is finished (``dhg ablate`` reuses it), so it must have the rest."""
    from dhg.data.plots import plot_forces, plot_losses
    from dhg.learning.torchscript import export_model

    plot_losses(history, run / "loss.png", title=f"{mcfg.preset}: RMSE (normalised) per epoch")
    predictor = ForcePredictor(net, w.scaler, mcfg).eval()
    test_x = w.x[w.split.test][:1000]
    with torch.no_grad():
        predicted = predictor(test_x).numpy()
    plot_forces(w.y[w.split.test][:1000, 0:3].numpy(), predicted, run / "forces.png", title=f"{mcfg.preset}: test set")
    export_model(predictor, mcfg, metrics, run / "model.ts", profiles=_profiles(ds))
    tmp = run / "metrics.json.tmp"
    tmp.write_text(json.dumps(metrics, indent=1))
    os.replace(tmp, run / "metrics.json")


def _evaluate(
    net: LSTMRegressor,
    xn: torch.Tensor,
    yn: torch.Tensor,
    force_pos: torch.Tensor,
    device: torch.device,
    force_span: torch.Tensor | None = None,
) -> dict[str, Any]:
    """RMSE on the force outputs, normalised and (given the scaler's spans) in newtons per axis."""
    net.eval()
    preds = []
    with torch.no_grad():
        for b in range(0, len(xn), 1024):
            preds.append(net(xn[b : b + 1024].to(device)).cpu())
    pred = torch.cat(preds).index_select(1, force_pos)  # (N, 3) normalised
    ref = yn.index_select(1, force_pos)
    out: dict[str, Any] = {"rmse_normalized": float(torch.sqrt(F.mse_loss(pred, ref)))}
    if force_span is not None:
        err_n = (pred - ref) * force_span  # (N, 3) in N
        per_axis = torch.sqrt((err_n**2).mean(dim=0))
        out["rmse_n"] = float(torch.sqrt((err_n**2).mean()))
        out["rmse_n_per_axis"] = [float(v) for v in per_axis]
    return out


def _profiles(ds: Any) -> dict[str, Any] | None:
    """The dataset's expert demonstration profiles (:mod:`dhg.learning.profiles`), or None where it has no
    planned path or no experts (the model then guides with the fixed corridor)."""
    from dhg.learning.profiles import build_profiles

    try:
        return build_profiles(ds).to_dict()
    except InvalidInputError:
        return None
