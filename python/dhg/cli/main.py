"""The ``dhg`` command line (one command, subcommands) and ``dhg-serve``.

Exit codes: 0 success; 1 unexpected internal error (a bug: please report it); 2 usage error
(bad arguments); 3 bad input (unreadable CT or volume file, invalid values); 5 network trouble
(endpoint in use, no server answering). This module holds the parsers; what each offline command
does is in :mod:`dhg.cli.commands`.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from typing import Any

from dhg.cli.commands import (
    cmd_ablate,
    cmd_ct_import,
    cmd_demo,
    cmd_evaluate,
    cmd_inspect,
    cmd_lab_config,
    cmd_phantom,
    cmd_study,
    cmd_synth,
    cmd_train,
    cmd_xray,
)
from dhg.cli.common import finite_float, run_command
from dhg.learning.presets import PRESETS, TrainConfig

__all__ = ["build_parser", "main", "serve_main"]

_EPILOG = """\
exit codes: 0 success, 1 internal error, 2 usage error, 3 bad input, 5 network trouble,
130 interrupted (Ctrl-C).
units: SI throughout (m, s, kg); options ending in -mm take millimetres for convenience.
"""


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
    for add in (
        _add_xray,
        _add_demo,
        _add_synth,
        _add_train,
        _add_evaluate,
        _add_ablate,
        _add_ct_import,
        _add_inspect,
        _add_phantom,
        _add_lab_config,
        _add_study,
    ):
        add(sub)
    from dhg.cli.live import add_commands

    add_commands(sub, "")
    return parser


def _add_source(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--ct",
        metavar="PATH",
        help="a prepared volume (.npz from 'dhg ct-import' or 'dhg phantom'), "
        "a DICOM folder/file or a NIfTI file; default: the built-in phantom femur",
    )
    p.add_argument(
        "--voxel-mm",
        type=finite_float,
        default=0.5,
        metavar="MM",
        help="isotropic voxel size used to build the phantom or resample a CT (default 0.5)",
    )


def _add_xray(sub: Any) -> None:
    """``dhg xray``."""
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
    _add_source(p)
    p.add_argument("--no-path", action="store_true", help="do not draw the planned path")
    p.set_defaults(func=cmd_xray)


def _add_demo(sub: Any) -> None:
    """``dhg demo``."""
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
    _add_source(p)
    p.add_argument("--burr-mm", type=finite_float, default=2.5, metavar="MM", help="drill diameter (default 2.5)")
    p.add_argument("--feed-mm-s", type=finite_float, default=1.5, metavar="MM_S", help="feed rate (default 1.5 mm/s)")
    p.add_argument("--rpm", type=finite_float, default=1200.0, help="spindle speed (default 1200 rpm)")
    p.set_defaults(func=cmd_demo)


def _add_synth(sub: Any) -> None:
    """``dhg synth``."""
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
    _add_source(p)
    p.set_defaults(func=cmd_synth)


def _add_training(p: argparse.ArgumentParser) -> None:
    """The training flags of ``train`` and ``ablate``: one per :class:`TrainConfig` field a person
    sets, with the dataclass's default (``_train_config`` maps them back)."""
    d = TrainConfig()
    p.add_argument("--data", required=True, metavar="DIR", help="dataset folder (from 'dhg synth' or 'dhg record')")
    p.add_argument(
        "--epochs",
        type=int,
        default=d.max_epochs,
        help=f"most epochs (early stopping usually ends sooner; default {d.max_epochs})",
    )
    p.add_argument(
        "--patience",
        type=int,
        default=d.patience,
        help=f"epochs without a better validation RMSE before stopping (default {d.patience})",
    )
    p.add_argument(
        "--lr", type=finite_float, default=d.learning_rate, help=f"Adam learning rate (paper: {d.learning_rate})"
    )
    p.add_argument("--batch", type=int, default=d.batch_size, help=f"batch size (paper: {d.batch_size})")
    p.add_argument("--seed", type=int, default=d.seed, help=f"seed (default {d.seed})")
    p.add_argument(
        "--device", choices=["cpu", "cuda", "auto"], default=d.device, help=f"where to train (default {d.device})"
    )
    p.add_argument("--best-only", action="store_true", help="only each subject's best attempt, as the paper did")
    p.add_argument(
        "--horizon",
        type=int,
        default=d.horizon,
        metavar="K",
        help="predict the expert's force K records (K x 0.1 s) after the window's last: 1 is the paper's "
        f"next record; a larger K gives guidance that leads the expert's force (default {d.horizon})",
    )


def _add_train(sub: Any) -> None:
    """``dhg train``."""
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
    _add_training(p)
    p.add_argument("--out", required=True, metavar="RUN", help="run folder to write")
    p.add_argument("--preset", default="fusion-2x256", choices=sorted(PRESETS), help="model preset")
    p.add_argument("--resume", action="store_true", help="continue from RUN/checkpoint.pt")
    p.set_defaults(func=cmd_train)


def _add_evaluate(sub: Any) -> None:
    """``dhg evaluate``."""
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


def _add_ablate(sub: Any) -> None:
    """``dhg ablate``."""
    p = sub.add_parser(
        "ablate",
        help="train the paper's four configurations on one split; write Table 1",
        description="Trains fusion-1x128, fusion-2x256, force-only-2x256 and all-2x256 on the same chronological "
        "split (with --seeds N, N seeds each) and writes OUT/table.md (the paper's Table 1 layout, test RMSE as mean "
        "± SD over seeds) and OUT/results.json. Finished runs (OUT/<preset>/seed-<s>/metrics.json) are reused.",
        epilog=_EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    _add_training(p)
    p.add_argument("--out", required=True, metavar="DIR", help="folder for the runs and the table")
    p.add_argument("--seeds", type=int, default=1, help="seeds per preset, from --seed on (mean ± SD reported)")
    p.set_defaults(func=cmd_ablate)


def _add_ct_import(sub: Any) -> None:
    """``dhg ct-import``."""
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
    p.add_argument(
        "--voxel-mm", type=finite_float, default=0.5, metavar="MM", help="isotropic voxel size (default 0.5)"
    )
    p.add_argument("--crop-mm", metavar="X0,Y0,Z0,X1,Y1,Z1", help="keep only this world box (mm, LPS)")
    p.set_defaults(func=cmd_ct_import)


def _add_inspect(sub: Any) -> None:
    """``dhg inspect``."""
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


def _add_phantom(sub: Any) -> None:
    """``dhg phantom``."""
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
    p.add_argument("--voxel-mm", type=finite_float, default=0.5, metavar="MM", help="voxel size (default 0.5)")
    p.set_defaults(func=cmd_phantom)


def _add_lab_config(sub: Any) -> None:
    """``dhg lab-config``."""
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


def _add_study(sub: Any) -> None:
    """``dhg study``."""
    from dhg.study.design import Protocol

    d = Protocol()
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
        "  dhg study --out out/learn --arms none,shaped-fading --test-replicates 8   # learning, measured precisely\n"
        "  dhg study --out out/live --seeds 3 --arms none,shaped --train 1 --duration 60 --live tcp/127.0.0.1:7447",
        epilog=_EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    _study_who_args(p)
    _study_attempt_args(p, d)
    _study_run_args(p)
    p.set_defaults(func=cmd_study)


def _study_who_args(p: argparse.ArgumentParser) -> None:
    """``dhg study``: where the results go, which novices, which arms and which operator model."""
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


def _study_attempt_args(p: argparse.ArgumentParser, d: Any) -> None:
    """``dhg study``: each arm's protocol and its attempts (``d``: the :class:`Protocol` defaults)."""
    from dhg.core.surgeon import MAX_ATTEMPT_S

    p.add_argument(
        "--train", type=int, default=d.train, metavar="N", help=f"guided training attempts per arm (default {d.train})"
    )
    p.add_argument(
        "--probe-every",
        type=int,
        default=d.probe_every,
        metavar="N",
        help=f"fading arms: every Nth training attempt is a guidance-free probe (default {d.probe_every}; 0: none)",
    )
    p.add_argument(
        "--test-replicates",
        type=int,
        default=d.test_replicates,
        metavar="K",
        help="measure each pre- and post-test as the mean of K attempts from the same learned state, each with "
        "its own hand noise (the novice learns from the first only); one attempt's plunge varies by about 2 mm, "
        f"so K = 8 shows 1 mm of learning that K = 1 cannot (default {d.test_replicates})",
    )
    p.add_argument(
        "--drill-mm",
        type=finite_float,
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
    p.add_argument(
        "--duration",
        type=finite_float,
        default=d.duration_s,
        metavar="S",
        help=f"most seconds per attempt, up to {MAX_ATTEMPT_S:g} (default {d.duration_s:g})",
    )


def _study_run_args(p: argparse.ArgumentParser) -> None:
    """``dhg study``: offline processes, or a live server to drill through."""
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
