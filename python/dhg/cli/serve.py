"""``dhg-serve``: its options, grouped, and the server's run (the ``dhg`` subcommands that talk to a
running server are in :mod:`dhg.cli.live`).

Exit codes (shared with ``dhg``): 0 success; 1 internal error; 2 usage error; 3 bad input
(unreadable CT or model file, invalid values); 5 network trouble (the listen endpoint is in use, no
server answered).
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import signal
import subprocess
import sys
import time
from collections.abc import Sequence
from typing import Any

from dhg.cli.common import EXIT_OK, NETWORK_EPILOG, endpoint, finite_float, load_volume, stop_on_signals
from dhg.cli.common import run_command as _run
from dhg.core.session import GUIDANCE_MODES

__all__ = ["serve_main", "serve_parser"]


# -- dhg-serve --------------------------------------------------------------------------------
def serve_parser() -> argparse.ArgumentParser:
    """The ``dhg-serve`` argument parser."""
    from dhg.core.server import ServerSettings
    from dhg.live.runner import DEFAULT_ENDPOINT

    d = ServerSettings()
    p = argparse.ArgumentParser(
        prog="dhg-serve",
        description=(
            "The real-time haptic guidance server. Trainees' stylus poses come in over Zenoh; a 1 kHz "
            "engine drills each trainee's own copy of the bone and sends back the force to render; every "
            "100 ms the last 20 records go to the LSTM model, and the guidance it drives (by default "
            "'shaped': a corridor around the planned path, a brake at the breakthrough and a warning before "
            "it; see --guidance-mode) is mixed into the force.\n\n"
            "  dhg-serve                                   # phantom femur + bundled model on "
            f"{DEFAULT_ENDPOINT}\n"
            "  dhg-serve --listen tcp/0.0.0.0:7447 --ct scan.nii.gz --model runs/x/model.ts\n"
            "  dhg-serve --role sim --listen tcp/0.0.0.0:7447      # engine next to the haptic devices\n"
            "  dhg-serve --role model --connect tcp/ENGINE:7447    # model worker on a GPU machine\n\n"
            "Then drive it: 'dhg trainee --connect ENDPOINT', record it: 'dhg record ...'."
        ),
        epilog=NETWORK_EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    for add in (_network_args, _bone_args, _model_args, _session_args, _view_args):
        add(p, d)
    return p


def _view_args(p: argparse.ArgumentParser, d: Any) -> None:
    """``dhg-serve``'s options for the live view (the all-in-one case of ``dhg view``)."""
    g = p.add_argument_group("the live view", "a 'dhg view' beside the server, in its own process")
    g.add_argument(
        "--view",
        type=int,
        metavar="PORT",
        help="also serve the live pages: the instructor's on http://127.0.0.1:PORT, each session's on the "
        "ports after it (the viewer is its own process, a Zenoh client of this server)",
    )
    g.add_argument(
        "--view-zenoh-config",
        metavar="FILE",
        help="the viewer's Zenoh client config (with --lab: an instructor's file, required)",
    )


def _network_args(p: argparse.ArgumentParser, d: Any) -> None:
    """``dhg-serve``'s options for the network (``d``: the default :class:`ServerSettings`)."""
    from dhg.live.runner import DEFAULT_ENDPOINT, ROLES

    g = p.add_argument_group("the network", "this process's role and its Zenoh endpoints")
    g.add_argument("--role", choices=ROLES, default="all", help="what this process runs (default: all)")
    g.add_argument(
        "--listen",
        action="append",
        type=endpoint,
        default=[],
        metavar="ENDPOINT",
        help=f"endpoint to listen on, repeatable (default for all/sim: {DEFAULT_ENDPOINT})",
    )
    g.add_argument(
        "--connect",
        action="append",
        type=endpoint,
        default=[],
        metavar="ENDPOINT",
        help=f"endpoint to connect to, repeatable (default for --role model: {DEFAULT_ENDPOINT})",
    )
    g.add_argument("--zenoh-config", metavar="FILE", help="a Zenoh JSON5 config (scouting, TLS, ...)")
    g.add_argument("--prefix", default="dhg", help="first chunk of every key expression (default: dhg)")


def _bone_args(p: argparse.ArgumentParser, d: Any) -> None:
    """``dhg-serve``'s options for the bone (``d``: the default :class:`ServerSettings`)."""
    g = p.add_argument_group("the bone", "what is drilled: the volume and the default planned path")
    g.add_argument(
        "--ct",
        metavar="PATH",
        help="bone to drill: a prepared volume (.npz), DICOM folder or NIfTI file; default: the phantom femur",
    )
    g.add_argument("--voxel-mm", type=finite_float, default=0.5, metavar="MM", help="voxel size (default 0.5)")
    g.add_argument(
        "--entry-mm", metavar="X,Y,Z", help="entry point A of the default path (mm, LPS; a CT's own path by default)"
    )
    g.add_argument("--target-mm", metavar="X,Y,Z", help="target point B of the default path (mm, LPS)")


def _model_args(p: argparse.ArgumentParser, d: Any) -> None:
    """``dhg-serve``'s options for the model (``d``: the default :class:`ServerSettings`)."""
    from dhg.live.services import MODEL_NICE

    g = p.add_argument_group("the model", "the LSTM that predicts the expert's force, and its workers")
    g.add_argument(
        "--model",
        metavar="FILE.ts",
        help="TorchScript model from 'dhg train'; default: the bundled one. With --role sim, only its expert "
        "profiles are read (the corridor's stiffness along the path): give the engine the workers' model",
    )
    g.add_argument(
        "--device", choices=("auto", "cpu", "cuda"), default="auto", help="where the model runs (default: auto)"
    )
    g.add_argument(
        "--executor",
        choices=("auto", "onnxruntime", "torchscript"),
        default="auto",
        help="what runs the forward passes: onnxruntime (CPU; the same model exported to ONNX at start and "
        "checked against TorchScript, about a third of the CPU a lone pass), torchscript, or auto: ONNX "
        "Runtime on CPU, TorchScript on CUDA (default: auto)",
    )
    g.add_argument(
        "--model-threads",
        type=int,
        metavar="N",
        help="CPU threads of a forward pass, TorchScript's or ONNX Runtime's (default: a quarter of the cores, at "
        "least 1, so the 1 kHz engine keeps a core)",
    )
    g.add_argument(
        "--model-nice",
        type=int,
        default=MODEL_NICE,
        metavar="N",
        help=f"Linux nice value of the model's worker thread, 0 (as the engine) to 19 (default {MODEL_NICE}: a "
        "forward pass gives way to the threads that carry poses and forces, where they share cores, yet keeps "
        "about a tenth of a core where other programs keep the cores busy; 19 starves it there)",
    )
    g.add_argument(
        "--model-timeout",
        type=finite_float,
        default=d.model_timeout_s,
        metavar="S",
        help=f"give up on one model query after S seconds (default {d.model_timeout_s:g})",
    )
    g.add_argument(
        "--worker-id",
        metavar="NAME",
        help="this model service's name in the engine's worker pool (default: the Zenoh user name of "
        "--zenoh-config, else the Zenoh session id); several workers share the queries and take over "
        "from one that stops",
    )


def _session_args(p: argparse.ArgumentParser, d: Any) -> None:
    """``dhg-serve``'s options for sessions and guidance (``d``: the default :class:`ServerSettings`)."""

    g = p.add_argument_group(
        "sessions and guidance", "trainee slots, timeouts, the guidance new sessions get, the tick thread's wait"
    )
    g.add_argument(
        "--max-sessions",
        type=int,
        default=d.max_sessions,
        metavar="N",
        help=f"trainee slots (default {d.max_sessions})",
    )
    g.add_argument(
        "--lab",
        metavar="FILE.toml",
        help="the lab file of dhg lab-config: each station may hold at most [server] sessions_per_station "
        "sessions (default 2), named after it",
    )
    g.add_argument(
        "--idle-timeout",
        type=finite_float,
        default=d.idle_timeout_s,
        metavar="S",
        help=f"free a session after this many seconds without poses (default {d.idle_timeout_s:g})",
    )
    g.add_argument(
        "--guidance-mode",
        choices=GUIDANCE_MODES,
        default=d.guidance_mode,
        help="guidance of new sessions (default shaped). 'paper': the paper's cue, predicted expert force "
        "minus the trainee's; 'corridor': a lateral pull back to the planned line beyond a 0.5 mm "
        "deadband, nothing along the drill; 'brake': a hold along the drill the moment the cortex gives, "
        "decaying over 0.4 s, plus the model's cue only where it resists; 'shaped': corridor + brake + a "
        "soft resistance ramp over the last mm before the planned breakthrough. Each trainee can change "
        "theirs with the set_guidance control request",
    )
    g.add_argument(
        "--guidance-gain",
        type=finite_float,
        default=d.guidance_gain,
        metavar="G",
        help="guidance gain of new sessions, 0..4; 0 = computed and published but not felt (default 1)",
    )
    g.add_argument(
        "--wait",
        choices=("sleep", "spin"),
        default=d.wait,
        help="how the 1 kHz tick thread and the force publisher wait between events. 'sleep' (default) "
        "leaves idle cores idle; each force then pays the host's wake-up latency (tens of µs on bare "
        "metal with real-time scheduling, up to milliseconds on a virtual machine). 'spin' busy-waits "
        "instead while a session is open, keeping two cores at 100 %%: use it on a machine with cores to "
        "spare that cannot give the tick thread SCHED_FIFO, never on a 2-core machine",
    )
    g.add_argument(
        "--tick-on",
        choices=("pose", "thread"),
        default=d.tick_on,
        help="where a pose ticks its session. 'pose' (default): a pose that finds its session due ticks it "
        "on the Zenoh thread that received it and the force leaves from there, no thread hand-off; the "
        "tick thread ticks the rest (a late or early pose, a silent client). 'thread': every pose is handed "
        "to the tick thread and every force to the publisher thread (the design before; for comparison: "
        "pose → force p50 about 1.35 times as long, 14-17 %% more server CPU on a 2-core VM)",
    )
    g.add_argument(
        "--status-every", type=finite_float, default=5.0, metavar="S", help="status line period (default 5 s)"
    )


def _point_mm(text: str, option: str) -> Any:
    import numpy as np

    try:
        vals = [float(v) * 1e-3 for v in text.split(",")]
    except ValueError:
        vals = []
    if len(vals) != 3:
        raise ValueError(f"{option} takes three numbers in mm: X,Y,Z, got {text!r}")
    return np.array(vals)


def _serve_options(args: argparse.Namespace) -> Any:
    """The runner's options from the flags: the role, the network, and the engine's settings
    (with a ``--lab`` file, its stations own their sessions)."""
    from dhg.core.server import ServerSettings
    from dhg.live import runner

    owners: tuple[str, ...] = ()
    per_owner = 0
    if args.lab:
        from dhg.live.lab import load_lab

        lab = load_lab(args.lab)
        owners, per_owner = tuple(s.name for s in lab.of("station")), lab.sessions_per_station
    settings = ServerSettings(
        max_sessions=args.max_sessions,
        idle_timeout_s=args.idle_timeout,
        model_timeout_s=args.model_timeout,
        guidance_mode=args.guidance_mode,
        guidance_gain=args.guidance_gain,
        wait=args.wait,
        tick_on=args.tick_on,
        session_owners=owners,
        max_sessions_per_owner=per_owner,
    )
    return runner.ServeOptions(
        role=args.role,
        listen=args.listen,
        connect=args.connect,
        zenoh_config=args.zenoh_config,
        prefix=args.prefix,
        settings=settings,
        model_device=args.device,
        worker_id=args.worker_id,
        model_nice=args.model_nice,
    )


def _model_file(args: argparse.Namespace) -> str:
    """``--model``, or the bundled model; a missing file is a :class:`ModelFileError`."""
    from dhg.learning.model_file import ModelFileError
    from dhg.learning.weights import default_model_path

    model_file = str(args.model or default_model_path())
    if not os.path.isfile(model_file):
        raise ModelFileError(f"{model_file}: no such model file (train one with 'dhg train', or omit --model)")
    return model_file


def _load_model(args: argparse.Namespace, options: Any, described: list[str]) -> tuple[Any, Any]:
    """The guidance model (``--model`` or the bundled one) and the options, with the corridor the
    model's expert profiles give when this process also runs the sessions; says what it loaded in
    ``described``."""
    import torch

    from dhg.learning.torchscript import load_model

    torch.set_num_threads(args.model_threads if args.model_threads is not None else max(1, (os.cpu_count() or 2) // 4))
    model_file = _model_file(args)
    model = load_model(model_file, device=args.device, executor=args.executor)
    described.append(f"model {model.meta.get('preset', '?')} from {model_file} on {model.device} ({model.executor})")
    if args.role == "all":
        options = _with_corridor(options, model.meta, described)
    return model, options


def _corridor_of_model_file(args: argparse.Namespace, options: Any, described: list[str]) -> Any:
    """The engine alone (``--role sim``): the options with the corridor the expert profiles of
    ``--model`` (or the bundled model) give, read from its metadata without torch, so that its
    sessions are guided as ``--role all``'s are. The workers should serve the same model; each
    checks that it does, and warns where not (:class:`dhg.live.services.CorridorCheck`)."""
    from dhg.learning.model_file import read_model_meta

    model_file = _model_file(args)
    options = _with_corridor(options, read_model_meta(model_file), described)
    described[-1] += f" (of {model_file}; the model workers serve their own)"
    return options


def _with_corridor(options: Any, meta: dict[str, Any], described: list[str]) -> Any:
    """The options with the corridor the expert profiles in a model's metadata give (unchanged
    for a model without them); says which in ``described``."""
    from dhg.learning.profiles import DemoProfiles

    if meta.get("profiles") is None:
        described.append("corridor fixed (the model has no expert profiles)")
        return options
    # The corridor follows the experts' spread along the path (dhg.learning.profiles).
    profiles = DemoProfiles.from_dict(meta["profiles"])
    profile = (profiles.bin_m, tuple(profiles.corridor_n_per_m))
    settings = dataclasses.replace(options.settings, corridor_profile=profile)
    described.append(f"corridor from {profiles.episodes} expert demonstrations")
    return dataclasses.replace(options, settings=settings)


def _load_bone(args: argparse.Namespace) -> tuple[Any, Any]:
    """The volume (``--ct`` or the phantom) and its planned path (``--entry-mm``/``--target-mm``
    override the volume's)."""
    volume, path = load_volume(args.ct, args.voxel_mm)
    if (args.entry_mm is None) != (args.target_mm is None):
        raise ValueError("give both --entry-mm and --target-mm, or neither")
    if args.entry_mm is not None:
        from dhg.core.path import PlannedPath

        path = PlannedPath(_point_mm(args.entry_mm, "--entry-mm"), _point_mm(args.target_mm, "--target-mm"))
    if path is None:
        raise ValueError(f"{args.ct}: this volume has no planned path; give --entry-mm and --target-mm")
    return volume, path


def _say(line: str) -> None:
    print(line, flush=True)


def _cmd_serve(args: argparse.Namespace) -> int:
    from dhg.core.server import check_zenoh_runtime
    from dhg.live import runner

    if not 0 < args.status_every <= 3600:
        raise ValueError(f"--status-every must be > 0 and at most 3600 s, got {args.status_every}")
    if args.model_threads is not None and args.model_threads < 1:
        raise ValueError(f"--model-threads must be at least 1, got {args.model_threads}")
    check_zenoh_runtime()  # before the model and the bone load: Zenoh would refuse it only after
    options = _serve_options(args)
    # Python hands the GIL over every 5 ms by default: a model reply could wait that long behind a
    # Zenoh callback. 0.5 ms keeps the guidance path's tail short at negligible cost.
    sys.setswitchinterval(5e-4)
    t0 = time.perf_counter()
    volume = path = model = None
    described: list[str] = []
    if args.role in ("all", "model"):
        model, options = _load_model(args, options, described)
    else:
        options = _corridor_of_model_file(args, options, described)
    if args.role in ("all", "sim"):
        volume, path = _load_bone(args)
        described.append(f"volume {volume}")
    with stop_on_signals() as stop:
        with runner.start(options, volume, path, model) as running:
            where = "listening on" if options.listen or args.role != "model" else "connected to"
            print(
                f"dhg-serve ready: role {args.role}, {where} {', '.join(running.endpoints)}, prefix {args.prefix}, "
                f"{'; '.join(described)} (started in {time.perf_counter() - t0:.1f} s)",
                flush=True,
            )
            if running.engine is not None:
                hint = runner.scheduling_hint(running.engine.health(), os.cpu_count() or 1)
                if hint:
                    print(f"note: {hint}", flush=True)
            viewer = _start_viewer(args, running.endpoints) if args.view is not None else None
            # A worker alone checks that the engine's corridor is its model's (--role sim takes
            # it from its own --model): it says so once an engine answers, and again when a
            # restarted engine's corridor differs.
            check = None
            if args.role == "model" and model is not None:
                from dhg.live.services import CorridorCheck

                check = CorridorCheck(running.zenoh, model.meta, args.prefix, report=_say)
            try:
                while not stop.wait(args.status_every):
                    print(time.strftime("%H:%M:%S ") + running.status_line(), flush=True)
            finally:
                if check is not None:
                    check.close()
                if viewer is not None:
                    _stop_viewer(viewer)
            sessions = running.engine.sessions() if running.engine is not None else []
            print(f"dhg-serve stopping: closing {len(sessions)} session(s)", flush=True)
    print("dhg-serve stopped", flush=True)
    return EXIT_OK


def _start_viewer(args: argparse.Namespace, endpoints: Sequence[str]) -> subprocess.Popen[bytes]:
    """``dhg view`` for this server, in its own process (it cannot slow the 1 kHz loop)."""
    if args.lab and not args.view_zenoh_config:
        raise ValueError("with --lab, --view needs --view-zenoh-config (an instructor's client file)")
    connect = [e.replace("0.0.0.0", "127.0.0.1").replace("[::]", "[::1]") for e in endpoints]
    cmd = [sys.executable, "-m", "dhg.cli.main", "view", "--port", str(args.view), "--prefix", args.prefix]
    cmd += ["--connect", connect[0]]
    config = args.view_zenoh_config or (None if args.lab else args.zenoh_config)
    if config:
        cmd += ["--zenoh-config", config]
    return subprocess.Popen(cmd)


def _stop_viewer(viewer: subprocess.Popen[bytes]) -> None:
    viewer.send_signal(signal.SIGTERM)
    try:
        viewer.wait(timeout=10)
    except subprocess.TimeoutExpired:
        viewer.kill()
        viewer.wait()


def serve_main(argv: Sequence[str] | None = None) -> int:
    """Entry point of ``dhg-serve``."""
    args = serve_parser().parse_args(argv)
    return _run(_cmd_serve, args)


if __name__ == "__main__":
    sys.exit(serve_main())
