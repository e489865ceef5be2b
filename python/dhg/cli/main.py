"""The ``dhg`` command line (one command, subcommands) and ``dhg-serve``.

Exit codes: 0 success; 1 unexpected internal error (a bug: please report it); 2 usage error
(bad arguments); 3 bad input (unreadable CT or volume file, invalid values); 4 the feature is not
built yet; 5 network trouble (endpoint in use, no server answering).
"""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from dhg.cli.common import EXIT_BAD_INPUT, EXIT_OK, EXIT_USAGE, run_command
from dhg.cli.common import load_volume as _load_volume
from dhg.cli.common import progress as _progress
from dhg.learning.presets import PRESETS

__all__ = ["build_parser", "main", "serve_main"]

_EPILOG = """\
exit codes: 0 success, 1 internal error, 2 usage error, 3 bad input, 5 network trouble.
units: SI throughout (m, s, kg); options ending in -mm take millimetres for convenience.
"""


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
    from dhg.core.session import DrillingSession, SessionConfig, StepResult
    from dhg.data.plots import plot_drilling
    from dhg.operators.scripted import scripted_stylus

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
    from dhg.learning.train import TrainConfig

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
        vals = [float(v) * 1e-3 for v in args.crop_mm.split(",")]
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


def build_parser() -> argparse.ArgumentParser:
    """The ``dhg`` argument parser."""
    parser = argparse.ArgumentParser(
        prog="dhg",
        description="DHG — Deep Haptic Guidance for training bone drilling. Builds and drills voxel bone "
        "from CT (or the built-in phantom femur) and renders X-ray views.",
        epilog=_EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)

    def add_source(p: argparse.ArgumentParser) -> None:
        p.add_argument(
            "--ct",
            metavar="PATH",
            help="a prepared volume (.npz from 'dhg ct-import' or 'dhg phantom'), "
            "a DICOM folder/file or a NIfTI file; default: the built-in phantom femur",
        )
        p.add_argument(
            "--voxel-mm",
            type=float,
            default=0.5,
            metavar="MM",
            help="isotropic voxel size used to build the phantom or resample a CT (default 0.5)",
        )

    p = sub.add_parser(
        "xray",
        help="write the top, front and side X-ray views as PNG",
        description="Writes top.png, front.png and side.png: digitally reconstructed radiographs "
        "(line integrals of X-ray attenuation) along the volume's z, y and x axes, with the planned "
        "path A→B drawn in green when the volume has one.",
        epilog=_EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("--out", required=True, metavar="DIR", help="folder for the PNG files (created if needed)")
    add_source(p)
    p.add_argument("--no-path", action="store_true", help="do not draw the planned path")
    p.set_defaults(func=cmd_xray)

    p = sub.add_parser(
        "demo",
        help="drill the planned path with a scripted straight-line drill and show the X-rays",
        description="Builds the phantom femur (or loads --ct) and drills the planned path A→B through the "
        "1 kHz haptic session with a scripted stylus that pushes along the path. Prints what the drill felt "
        "(force, temperature, breakthroughs) and the layers crossed, and writes the X-ray views of the drilled "
        "bone (tip and path drawn in) and drilling.png (force, temperature and depth over time).",
        epilog=_EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("--out", default="out/demo", metavar="DIR", help="folder for the PNG files (default out/demo)")
    add_source(p)
    p.add_argument("--burr-mm", type=float, default=2.5, metavar="MM", help="drill diameter (default 2.5)")
    p.add_argument("--feed-mm-s", type=float, default=1.5, metavar="MM_S", help="feed rate (default 1.5 mm/s)")
    p.add_argument("--rpm", type=float, default=1200.0, help="spindle speed (default 1200 rpm)")
    p.set_defaults(func=cmd_demo)

    p = sub.add_parser(
        "synth",
        help="generate demonstrations: virtual surgeons drilling the planned path, as a dataset",
        description="Virtual surgeons (experts and novices, each with their own style, tremor, reaction delay and "
        "habits) drill the planned path through the 1 kHz haptic session. Writes a dataset folder: records.parquet "
        "(the paper's nine features at 10 Hz, one row per record), card.json (units, feature order, volume, path, "
        "seed, per-episode skill metrics) and with --raw the 1 kHz stream. Deterministic for a seed; the default "
        "(6 experts x 3 attempts, 2 novices) gives about 11k expert records, the paper's size.",
        epilog=_EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("--out", required=True, metavar="DIR", help="dataset folder to write")
    p.add_argument("--subjects", type=int, default=6, help="expert subjects (default 6, like the paper)")
    p.add_argument("--attempts", type=int, default=3, help="attempts per subject (default 3)")
    p.add_argument("--novices", type=int, default=2, help="novice subjects (default 2)")
    p.add_argument("--seed", type=int, default=0, help="seed for styles and motor noise (default 0)")
    p.add_argument("--raw", action="store_true", help="also write the 1 kHz pose/force stream (raw.parquet)")
    p.add_argument("--overwrite", action="store_true", help="replace an existing dataset folder")
    add_source(p)
    p.set_defaults(func=cmd_synth)

    def add_training(p: argparse.ArgumentParser) -> None:
        p.add_argument("--data", required=True, metavar="DIR", help="dataset folder (from 'dhg synth' or 'dhg record')")
        p.add_argument("--epochs", type=int, default=60, help="most epochs (early stopping usually ends sooner; 60)")
        p.add_argument(
            "--patience", type=int, default=8, help="epochs without a better validation RMSE before stopping"
        )
        p.add_argument("--lr", type=float, default=0.004, help="Adam learning rate (paper: 0.004)")
        p.add_argument("--batch", type=int, default=50, help="batch size (paper: 50)")
        p.add_argument("--seed", type=int, default=0, help="seed (default 0)")
        p.add_argument("--device", choices=["cpu", "cuda", "auto"], default="cpu", help="where to train (default cpu)")
        p.add_argument("--best-only", action="store_true", help="only each subject's best attempt, as the paper did")
        p.add_argument(
            "--horizon",
            type=int,
            default=1,
            metavar="K",
            help="predict the expert's force K records (K x 0.1 s) after the window's last: 1 is the paper's "
            "next record; a larger K gives guidance that leads the expert's force (default 1)",
        )

    p = sub.add_parser(
        "train",
        help="train the DHG model on a dataset and export model.ts",
        description="Trains an LSTM (a preset of the paper's Table 1) to predict the expert's next force (or with "
        "--horizon K the force K records ahead) from windows of 20 records (the nine features at 10 Hz), with "
        "the paper's defaults: Adam, learning rate 0.004, batch 50, RMSE loss, min-max scaling fitted on the "
        "training data, a chronological split (the last 13.5 % of windows for test). Writes RUN/model.ts "
        "(TorchScript: raw windows in, forces in N out), metrics.json, loss.png, forces.png (reference vs "
        "predicted) and checkpoint.pt (resume with --resume). Runs under torchrun for multi-GPU/multi-node "
        "(DistributedDataParallel).",
        epilog=_EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    add_training(p)
    p.add_argument("--out", required=True, metavar="RUN", help="run folder to write")
    p.add_argument("--preset", default="fusion-2x256", choices=sorted(PRESETS), help="model preset")
    p.add_argument("--resume", action="store_true", help="continue from RUN/checkpoint.pt")
    p.set_defaults(func=cmd_train)

    p = sub.add_parser(
        "evaluate",
        help="RMSE of an exported model on a dataset",
        description="Runs an exported model.ts over every window of a dataset's episodes and prints the RMSE of the "
        "predicted force (N, overall and per axis) as JSON.",
        epilog=_EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("--model", required=True, metavar="MODEL.ts", help="exported model")
    p.add_argument("--data", required=True, metavar="DIR", help="dataset folder")
    p.add_argument("--skill", choices=["expert", "novice", "all"], default="expert", help="episodes to score")
    p.set_defaults(func=cmd_evaluate)

    p = sub.add_parser(
        "ablate",
        help="train the paper's four configurations on one split; write Table 1",
        description="Trains fusion-1x128, fusion-2x256, force-only-2x256 and all-2x256 on the same chronological "
        "split (with --seeds N, N seeds each) and writes OUT/table.md (the paper's Table 1 layout, test RMSE as mean "
        "± SD over seeds) and OUT/results.json. Finished runs (OUT/<preset>/seed-<s>/metrics.json) are reused.",
        epilog=_EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    add_training(p)
    p.add_argument("--out", required=True, metavar="DIR", help="folder for the runs and the table")
    p.add_argument("--seeds", type=int, default=1, help="seeds per preset, from --seed on (mean ± SD reported)")
    p.set_defaults(func=cmd_ablate)

    p = sub.add_parser(
        "ct-import",
        help="prepare a real CT (DICOM or NIfTI) as a volume file",
        description="Reads a DICOM series (folder or file) or a NIfTI file, converts to HU, resamples "
        "to isotropic voxels in the LPS frame, optionally crops, segments the bone layers and writes a "
        "prepared volume (.npz) that --ct accepts everywhere.",
        epilog=_EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("src", metavar="SRC", help="DICOM folder or file, or .nii/.nii.gz")
    p.add_argument("--out", required=True, metavar="FILE.npz", help="where to write the prepared volume")
    p.add_argument("--voxel-mm", type=float, default=0.5, metavar="MM", help="isotropic voxel size (default 0.5)")
    p.add_argument("--crop-mm", metavar="X0,Y0,Z0,X1,Y1,Z1", help="keep only this world box (mm, LPS)")
    p.set_defaults(func=cmd_ct_import)

    p = sub.add_parser(
        "inspect",
        help="a dataset at a glance: its episodes' skill metrics, and a plot of one",
        description="Validates a dataset folder (from 'dhg synth' or 'dhg record') and prints one line per "
        "episode: subject, skill, attempt, whether it is the subject's best (*), records, duration, 1 kHz "
        "ticks kept, and the skill metrics (completed, distance to B, maximum deviation, plunge, peak "
        "temperature, time above 47 °C, force jerk). With --plot it writes a PNG of one episode over time: "
        "the device force (1 kHz with the guidance share when the raw stream is kept), the tip temperature "
        "and the depth along A→B, with the layer at the tip shaded.\n\n"
        "  dhg inspect data/alice --plot alice.png            # the last attempt\n"
        "  dhg inspect data/demos --plot e3.png --episode 3",
        epilog=_EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("data", metavar="DIR", help="dataset folder")
    p.add_argument("--plot", metavar="FILE.png", help="write a PNG of one episode over time")
    p.add_argument("--episode", type=int, metavar="ID", help="the episode to plot (default: the last)")
    p.add_argument("--json", action="store_true", help="print the episodes as JSON (SI units) instead of a table")
    p.set_defaults(func=cmd_inspect)

    p = sub.add_parser(
        "phantom",
        help="write the built-in phantom femur as a volume file",
        description="Builds the procedural proximal-femur CT (deterministic for a seed) with its "
        "default hip-pinning path and writes it as a prepared volume (.npz).",
        epilog=_EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("--out", required=True, metavar="FILE.npz", help="where to write it")
    p.add_argument("--seed", type=int, default=0, help="texture and noise seed (default 0)")
    p.add_argument("--voxel-mm", type=float, default=0.5, metavar="MM", help="voxel size (default 0.5)")
    p.set_defaults(func=cmd_phantom)

    p = sub.add_parser(
        "lab-config",
        help="the secure lab mode: TLS, passwords and access control for every station, instructor and model worker",
        description="Reads a lab file (TOML) naming the server's TLS endpoint and certificates and every "
        "identity of the lab (stations, instructors, model workers), and writes one Zenoh configuration per "
        "member: the server's (TLS listener, the password dictionary, an access-control list that denies by "
        "default) and one client configuration for each identity. A station may publish only its own poses, "
        "query only its own control, metrics and X-rays and hear only its own outputs; an instructor reads every "
        "session; only model workers (and the server's own services) answer the model's queries; only the "
        "server publishes forces. The lab file's format and the how-to are in docs/deployment.md; deploy/ has "
        "an example.\n\n"
        "  dhg lab-config --lab deploy/lab.toml --out deploy/out --make-certs\n"
        "  dhg-serve --zenoh-config deploy/out/server.json5 --listen tls/0.0.0.0:7447 --lab deploy/lab.toml\n"
        "  dhg trainee --connect tls/dhg-server.lab:7447 --session station-1 --zenoh-config deploy/out/station-1.json5",
        epilog=_EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("--lab", required=True, metavar="FILE.toml", help="the lab file")
    p.add_argument("--out", required=True, metavar="DIR", help="folder for server.json5, users.txt and <name>.json5")
    p.add_argument(
        "--make-certs",
        action="store_true",
        help="create a lab CA and the server's certificate with openssl where the lab file's paths do not exist",
    )
    p.set_defaults(func=cmd_lab_config)

    p = sub.add_parser(
        "study",
        help="does guidance make virtual novices drill better, and learn? paired arms, offline, with statistics",
        description="Each novice seed (one hand: style, tremor, reaction, noise) follows a protocol per arm, offline "
        "through the 1 kHz core that dhg-serve runs (faster than real time), with the model in this process queried "
        "at every 10 Hz record: a guidance-free pre-test (the same for every arm), --train attempts in the arm's "
        "guidance, and a guidance-free post-test. The novice learns across attempts from the errors it experiences "
        "(error-based learning with forgetting, Emken et al. 2007). Arms: 'none' (the baseline, first), the guidance "
        "modes paper, corridor, brake, shaped at gain 1 ('shaped@0.5' sets a gain), and shaped-fading (the gain "
        "follows the core's assist-as-needed schedule, with guidance-free probes). The same hands in every arm, so "
        "arms are compared by paired differences against 'none', per metric the mean difference and its 95 % "
        "interval: in the first training attempt (guidance's immediate effect) and in the post-test (what training "
        "left); and post-test - pre-test within each arm. Operators (--operator): 'impedance', an arm that answers "
        "every force through the mass, damping and stiffness measured at a haptic handle (van Beek et al. 2015) with "
        "a 150-250 ms reaction, told nothing of the cue; 'instructed', the dhg synth novice who was told what the cue "
        "means. Writes DIR/results.md (tables), DIR/results.json (every attempt) and DIR/study.png. With --live, the "
        "attempts are drilled in real time through a running dhg-serve instead (its model, its guidance; one session "
        "per novice and arm, --workers at once): the check that the server guides as the offline core does.\n\n"
        "  dhg study --out out/study --novices 20                      # seeds 1000..1019, every arm\n"
        "  dhg study --out out/s --seeds 3,4 --arms none,brake,shaped@0.5 --train 1 --operator instructed\n"
        "  dhg study --out out/live --seeds 3 --arms none,shaped --train 1 --duration 60 --live tcp/127.0.0.1:7447",
        epilog=_EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("--out", required=True, metavar="DIR", help="folder for results.md, results.json, study.png")
    p.add_argument("--novices", type=int, default=20, metavar="N", help="novices, seeds 1000..1000+N-1 (default 20)")
    p.add_argument("--seeds", metavar="S,S,...", help="novice seeds instead of --novices")
    p.add_argument(
        "--arms",
        default="none,paper,corridor,brake,shaped,shaped-fading",
        help="arms, comma-separated, 'none' first (default: all)",
    )
    p.add_argument(
        "--operator",
        choices=("impedance", "instructed"),
        default="impedance",
        help="operator model (default impedance)",
    )
    p.add_argument("--train", type=int, default=6, metavar="N", help="guided training attempts per arm (default 6)")
    p.add_argument(
        "--probe-every",
        type=int,
        default=3,
        metavar="N",
        help="fading arms: every Nth training attempt is a guidance-free probe (default 3; 0: none)",
    )
    p.add_argument(
        "--drill-mm",
        type=float,
        metavar="MM",
        help="drill diameter for every attempt (default 2.5 mm); 4.5 mm heats the bone enough to test 47 °C",
    )
    p.add_argument(
        "--guidance-param",
        action="append",
        default=[],
        metavar="NAME=VALUE",
        help="change one of the core's guidance laws for every attempt (SI units; repeatable), e.g. "
        "corridor_deadband_m=0.25e-3 or brake_hold_n=1.8; the names are DrillingSession.guidance_params'",
    )
    p.add_argument("--model", metavar="FILE.ts", help="TorchScript model (default: the bundled one)")
    p.add_argument("--duration", type=float, default=150.0, metavar="S", help="most seconds per attempt (default 150)")
    p.add_argument(
        "--workers",
        type=int,
        metavar="N",
        help="processes offline (default 2); sessions at once with --live (default: one per arm)",
    )
    p.add_argument(
        "--live",
        metavar="ENDPOINT",
        help="drill through the dhg-serve at this Zenoh endpoint, in real time (its --model guides; --model unused)",
    )
    p.add_argument("--zenoh-config", metavar="FILE", help="with --live: a Zenoh JSON5 config (TLS, credentials, ...)")
    p.set_defaults(func=cmd_study)

    from dhg.cli.serve import add_commands

    add_commands(sub, "")
    return parser


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
    from dhg.study.runner import Protocol, parse_arms, run_study

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
        guidance=tuple(guidance),
        burr_radius_m=None if args.drill_mm is None else args.drill_mm / 2 * 1e-3,
    )
    prog, update = _progress(f"{len(seeds)} novices x {len(arms)} arms x {args.train + 2} attempts")
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


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of ``dhg``."""
    args = build_parser().parse_args(argv)
    return run_command(args.func, args)


def serve_main(argv: Sequence[str] | None = None) -> int:
    """Entry point of ``dhg-serve`` (see :mod:`dhg.cli.serve`)."""
    from dhg.cli.serve import serve_main as run

    return run(argv)


if __name__ == "__main__":
    sys.exit(main())
