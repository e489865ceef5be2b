"""What each offline ``dhg`` subcommand does (the parsers are in :mod:`dhg.cli.main`; the live
ones, ``trainee``, ``record`` and ``live-demo``, in :mod:`dhg.cli.serve`). Each ``cmd_*`` takes the
parsed arguments and returns an exit code of :mod:`dhg.cli.common`."""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

from dhg.cli.common import EXIT_BAD_INPUT, EXIT_OK, EXIT_USAGE, finite_float
from dhg.cli.common import load_volume as _load_volume
from dhg.cli.common import progress as _progress

__all__ = [
    "cmd_ablate",
    "cmd_ct_import",
    "cmd_demo",
    "cmd_evaluate",
    "cmd_inspect",
    "cmd_lab_config",
    "cmd_phantom",
    "cmd_study",
    "cmd_synth",
    "cmd_train",
    "cmd_xray",
]


def _mm(point_m) -> str:
    return "(" + ", ".join(f"{float(v) * 1e3:.1f}" for v in point_m) + ")"


def cmd_xray(args: argparse.Namespace) -> int:
    from dhg.bone.xray import render_views, write_views

    vol, path = _load_volume(args.ct, args.voxel_mm)
    images = render_views(vol, vol.xray(), path if not args.no_path else None)
    for name, p in write_views(images, args.out).items():
        print(f"{name:5s} {p}")
    return EXIT_OK


def cmd_demo(args: argparse.Namespace) -> int:
    from dhg.bone.planning import layer_runs
    from dhg.bone.xray import auto_windows, render_views, write_views
    from dhg.core.session import MAX_SPINDLE_RPM, DrillingSession, SessionConfig, StepResult
    from dhg.core.surgeon import MAX_ATTEMPT_S
    from dhg.data.plots import plot_drilling
    from dhg.operators.scripted import scripted_stylus

    if not args.feed_mm_s > 0:
        raise ValueError(f"--feed-mm-s must be a feed rate > 0 mm/s, got {args.feed_mm_s}")
    if not 0 < args.rpm <= MAX_SPINDLE_RPM:
        raise ValueError(f"--rpm must be a spindle speed in (0, {MAX_SPINDLE_RPM:g}] rpm, got {args.rpm}")
    t0 = time.perf_counter()
    vol, path = _load_volume(args.ct, args.voxel_mm)
    if path is None:
        print("error: this volume has no planned path; use the phantom or a volume saved with one", file=sys.stderr)
        return EXIT_BAD_INPUT
    print(f"volume   {vol}  built in {time.perf_counter() - t0:.2f} s, {vol.memory_bytes / 1e6:.1f} MB shared")
    print(f"path     A = {_mm(path.entry_m)} mm  →  B = {_mm(path.target_m)} mm  ({path.length_m * 1e3:.1f} mm)")
    session = DrillingSession(vol, path, SessionConfig(burr_radius_m=args.burr_mm * 1e-3 / 2))
    windows = auto_windows(vol.xray())
    duration_s = (path.length_m + 5e-3) / (args.feed_mm_s * 1e-3) + 5.0
    if duration_s > MAX_ATTEMPT_S:
        slowest = (path.length_m + 5e-3) / (MAX_ATTEMPT_S - 5.0) * 1e3
        raise ValueError(
            f"--feed-mm-s {args.feed_mm_s:g} would drill for longer than an attempt may last "
            f"({MAX_ATTEMPT_S:g} s): at least {slowest:.3f} mm/s on this path"
        )
    rows = scripted_stylus(path, duration_s, feed_m_s=args.feed_mm_s * 1e-3, spindle_rpm=args.rpm)
    prog, update = _progress("drilling A→B at 1 kHz")
    t1 = time.perf_counter()
    chunks = []
    with prog:
        for start in range(0, len(rows), 1000):
            chunks.append(session.step(rows[start : start + 1000]))
            update(min(start + 1000, len(rows)), len(rows))
    result = StepResult(np.concatenate([c.forces_n for c in chunks]), np.concatenate([c.records for c in chunks]))
    st = session.state
    wall_s = time.perf_counter() - t1
    print(
        f"drilled  {len(rows)} ticks of 1 ms ({len(rows) / 1000:.1f} s simulated) in {wall_s:.2f} s wall; "
        f"tip at {st.depth_m * 1e3:.1f} mm of {path.length_m * 1e3:.1f} mm, {st.deviation_m * 1e3:.2f} mm off the path"
    )
    print(
        f"felt     device force up to {np.linalg.norm(result.forces_n, axis=1).max():.2f} N; "
        f"peak tip temperature {st.peak_temperature_c:.1f} °C, {st.time_above_47_s:.1f} s above 47 °C; "
        f"removed {st.removed_mass_kg * 1e6:.0f} mg; breakthroughs {st.breakthroughs}"
    )
    print("layers along A→B:")
    for name, lo, hi in layer_runs(vol.drill(), path):
        if name == "outside" and hi - lo < 0.5e-3:
            continue  # A sits on the bone surface: the first sample is just outside
        print(f"  {name:10s} {lo * 1e3:6.1f} – {hi * 1e3:6.1f} mm")
    out = Path(args.out)
    images = render_views(vol, session.xray(), path, tip_m=st.tip_m, windows=windows)
    for name, p in write_views(images, out).items():
        print(f"{name:5s} {p}")
    plot = plot_drilling(result, out / "drilling.png", title="Scripted drill along the planned path (phantom femur)")
    print(f"plot  {plot}")
    return EXIT_OK


def cmd_synth(args: argparse.Namespace) -> int:
    from dhg.data.dataset import load_dataset, write_dataset
    from dhg.data.synth import synthesize

    vol, path = _load_volume(args.ct, args.voxel_mm)
    if path is None:
        print("error: this volume has no planned path; use the phantom or a volume saved with one", file=sys.stderr)
        return EXIT_BAD_INPUT
    out = Path(args.out)
    if out.exists() and any(out.iterdir()) and not args.overwrite:
        print(f"error: {out} exists and is not empty; pass --overwrite to replace it", file=sys.stderr)
        return EXIT_BAD_INPUT
    prog, update = _progress("virtual surgeons drilling")
    t0 = time.perf_counter()
    with prog:
        episodes, card = synthesize(
            vol, path, args.subjects, args.attempts, args.novices, args.seed, keep_raw=args.raw, progress=update
        )
    write_dataset(out, episodes, card, overwrite=args.overwrite)
    ds = load_dataset(out)
    print(
        f"wrote {out}: {len(ds.episodes)} episodes, {ds.n_records} records at 10 Hz in {time.perf_counter() - t0:.1f} s"
    )
    print(f"  experts: {sum(len(e.times_s) for e in ds.select('expert'))} records; best attempts marked per subject")
    rows = [
        ("completion time (s)", "completion_time_s", 1.0),
        ("mean deviation (mm)", "mean_deviation_m", 1e3),
        ("max deviation (mm)", "max_deviation_m", 1e3),
        ("distance to B (mm)", "target_distance_m", 1e3),
        ("plunge depth (mm)", "plunge_depth_m", 1e3),
        ("peak temperature (°C)", "peak_temperature_c", 1.0),
        ("time above 47 °C (s)", "time_above_47_s", 1.0),
        ("force jerk (N/s)", "force_jerk_n_per_s", 1.0),
        ("completed (%)", "completed", 100.0),
    ]
    skills = [k for k in ("expert", "novice") if ds.select(k)]
    print(f"  {'metric (mean)':24s}" + "".join(f"{k:>10s}" for k in skills))
    for label, key, scale in rows:
        vals = [np.mean([float(e.metrics[key]) for e in ds.select(k)]) * scale for k in skills]
        print(f"  {label:24s}" + "".join(f"{v:10.2f}" for v in vals))
    return EXIT_OK


def _train_config(args: argparse.Namespace):
    from dhg.learning.presets import TrainConfig

    return TrainConfig(
        learning_rate=args.lr,
        batch_size=args.batch,
        max_epochs=args.epochs,
        patience=args.patience,
        seed=args.seed,
        device=args.device,
        best_only=args.best_only,
        horizon=args.horizon,
    )


def cmd_train(args: argparse.Namespace) -> int:
    from dhg.learning.train import train

    prog, update = _progress(f"training {args.preset}")
    task_desc = {"loss": ""}

    def progress(epoch: int, total: int, train_rmse: float, val_rmse: float) -> None:
        task_desc["loss"] = f"train {train_rmse:.4f} val {val_rmse:.4f}"
        update(epoch, total)
        prog.update(prog.task_ids[0], description=f"training {args.preset}: {task_desc['loss']}")

    with prog:
        result = train(args.data, args.out, args.preset, _train_config(args), resume=args.resume, progress=progress)
    m = result.metrics
    best = m["best_epoch"] + 1
    print(f"trained {args.preset} for {m['epochs']} epochs in {m['train_time_s']:.0f} s (best epoch {best})")
    for split in ("train", "val", "test"):
        axes = ", ".join(f"{v:.4f}" for v in m[split]["rmse_n_per_axis"])
        r = m[split]
        print(f"  {split:5s} RMSE {r['rmse_n']:.4f} N (x, y, z: {axes}), normalised {r['rmse_normalized']:.4f}")
    for name in ("model.ts", "metrics.json", "loss.png", "forces.png", "checkpoint.pt"):
        print(f"  {Path(args.out) / name}")
    return EXIT_OK


def cmd_evaluate(args: argparse.Namespace) -> int:
    import json

    from dhg.data.dataset import load_dataset
    from dhg.learning.torchscript import load_model
    from dhg.learning.train import make_windows

    model = load_model(args.model)
    ds = load_dataset(args.data)
    x, y, _ = make_windows(ds, model.window, None if args.skill == "all" else args.skill, horizon=model.horizon)
    pred = np.concatenate([model.predict(x[b : b + 2048]) for b in range(0, len(x), 2048)])
    err = pred - y[:, 0:3]
    per_axis = np.sqrt(np.mean(err**2, axis=0))
    result = {
        "model": str(args.model),
        "preset": model.meta.get("preset"),
        "data": str(args.data),
        "windows": int(len(x)),
        "rmse_n": float(np.sqrt(np.mean(err**2))),
        "rmse_n_per_axis": per_axis.tolist(),
    }
    print(json.dumps(result, indent=1))
    return EXIT_OK


def cmd_ablate(args: argparse.Namespace) -> int:
    from dhg.learning.ablation import ablate, markdown_table

    if args.seeds < 1:
        raise ValueError(f"--seeds is how many seeds each preset trains with: at least 1, got {args.seeds}")
    seeds = tuple(range(args.seed, args.seed + args.seeds))
    results = ablate(
        args.data,
        args.out,
        _train_config(args),
        seeds=seeds,
        on_start=lambda name, seed: print(f"training {name} (seed {seed}) ...", flush=True),
    )
    print(markdown_table(results))
    print(f"wrote {Path(args.out) / 'table.md'} and {Path(args.out) / 'results.json'}")
    return EXIT_OK


def cmd_inspect(args: argparse.Namespace) -> int:
    from rich.console import Console

    from dhg.data.report import episode_summaries, load_with_raw, plot_episode, summary_table

    ds, raw = load_with_raw(args.data)
    gen = ds.card.get("generator", {})
    rows = episode_summaries(ds, raw)
    if args.plot and not rows:
        raise ValueError("the dataset has no episodes to plot")
    plotted = None
    if args.plot:
        eid = rows[-1]["episode_id"] if args.episode is None else args.episode
        plotted = (eid, plot_episode(ds, eid, args.plot, raw))
    if args.json:
        import json

        print(json.dumps({"path": str(ds.path), "raw_ticks": None if raw is None else raw.num_rows, "episodes": rows}))
        return EXIT_OK
    print(f"{ds.path}: {gen.get('name', 'unknown generator')}, {len(rows)} episodes, {ds.n_records} records at 10 Hz")
    print(f"  1 kHz stream: {'none' if raw is None else f'{raw.num_rows} ticks'}")
    table = summary_table(rows)
    Console(width=200).print(table)
    if plotted is not None:
        print(f"plot of episode {plotted[0]}: {plotted[1]}")
    return EXIT_OK


def cmd_ct_import(args: argparse.Namespace) -> int:
    from dhg.bone import ct

    crop = None
    if args.crop_mm is not None:
        try:
            vals = [finite_float(v) * 1e-3 for v in args.crop_mm.split(",")]
        except argparse.ArgumentTypeError as exc:
            print(f"error: --crop-mm takes six numbers (xmin,ymin,zmin,xmax,ymax,zmax mm): {exc}", file=sys.stderr)
            return EXIT_USAGE
        if len(vals) != 6:
            print("error: --crop-mm takes six numbers: xmin,ymin,zmin,xmax,ymax,zmax", file=sys.stderr)
            return EXIT_USAGE
        crop = (vals[:3], vals[3:])
    vol = ct.prepare(args.src, voxel_m=args.voxel_mm * 1e-3, crop_m=crop)
    path = vol.save(args.out)
    print(f"{vol} → {path}")
    return EXIT_OK


def cmd_phantom(args: argparse.Namespace) -> int:
    from dhg.bone import phantom

    p = phantom.femur(args.seed, args.voxel_mm * 1e-3)
    print(f"{p.volume} → {p.volume.save(args.out)}")
    return EXIT_OK


def cmd_lab_config(args: argparse.Namespace) -> int:
    from dhg.live.lab import load_lab, write_lab

    written = write_lab(args.lab, args.out, certs=args.make_certs)
    lab = load_lab(args.lab)
    print(f"wrote {len(written)} files to {args.out} (passwords inside: readable by you only)")
    print(
        f"  server: dhg-serve --zenoh-config {Path(args.out) / 'server.json5'} --listen {lab.listen} --lab {args.lab}"
    )
    for ident in lab.identities:
        conf = Path(args.out) / f"{ident.name}.json5"
        print(f"  {ident.role:12s} {ident.name:16s} --connect {lab.endpoint} --zenoh-config {conf}")
    return EXIT_OK


def cmd_study(args: argparse.Namespace) -> int:
    import json

    from dhg.learning.weights import default_model_path
    from dhg.study.design import Protocol, parse_arms
    from dhg.study.runner import run_study

    arms = parse_arms(args.arms)
    if args.seeds:
        try:
            seeds = [int(s) for s in args.seeds.split(",") if s.strip()]
        except ValueError:
            raise ValueError(f"--seeds takes integers, comma-separated, got {args.seeds!r}") from None
    else:
        if args.novices < 1:
            raise ValueError(f"--novices must be at least 1, got {args.novices}")
        seeds = list(range(1000, 1000 + args.novices))
    model = Path(args.model) if args.model else default_model_path()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    guidance = []
    for item in args.guidance_param:
        name, eq, value = item.partition("=")
        try:
            guidance.append((name.strip(), float(value)))
        except ValueError:
            eq = ""
        if not eq:
            raise ValueError(f"--guidance-param takes NAME=VALUE (a number in SI units), got {item!r}")
    protocol = Protocol(
        train=args.train,
        duration_s=args.duration,
        probe_every=args.probe_every,
        test_replicates=args.test_replicates,
        guidance=tuple(guidance),
        burr_radius_m=None if args.drill_mm is None else args.drill_mm / 2 * 1e-3,
    )
    prog, update = _progress(
        f"{len(seeds)} novices x {len(arms)} arms x {args.train + 2} attempts"
        + (f", tests x {args.test_replicates}" if args.test_replicates > 1 else "")
    )
    t0 = time.perf_counter()
    with prog:
        workers = args.workers if args.workers is not None else (len(arms) if args.live else 2)
        result = run_study(
            seeds,
            arms,
            model,
            protocol,
            args.operator,
            workers,
            progress=update,
            live=args.live,
            zenoh_config_file=args.zenoh_config,
        )
    table = result.markdown()
    header = (
        f"{len(seeds)} virtual novices (seeds {seeds[0]}..{seeds[-1]}), {args.operator} operator, "
        + (f"live through the server at {args.live}" if args.live else f"offline, model {model.name}")
        + f"; per arm a guidance-free pre-test, {args.train} training attempts in the arm's guidance and a "
        f"guidance-free post-test, each of at most {args.duration:g} s"
        + (
            f"; each test the mean of {args.test_replicates} replicates from the same learned state"
            if args.test_replicates > 1
            else ""
        )
        + (f", a {args.drill_mm:g} mm drill" if args.drill_mm is not None else "")
        + "".join(f", {n} = {v:g}" for n, v in guidance)
        + ". Each guided cell: mean (paired difference with 'none' [95 % interval]).\n\n"
    )
    (out / "results.md").write_text(header + table)
    (out / "results.json").write_text(json.dumps(result.to_json(), indent=1))
    png = result.plot(out / "study.png")
    print(header + table)
    print(f"wrote {out / 'results.md'}, {out / 'results.json'} and {png} in {time.perf_counter() - t0:.0f} s")
    return EXIT_OK
