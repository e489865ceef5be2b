"""The ``dhg`` subcommands that talk to a running ``dhg-serve``: ``trainee`` (a virtual trainee),
``record`` (a live session into a dataset), ``view`` (the live pages in a browser) and
``live-demo`` (the whole product, ``make demo``)."""

from __future__ import annotations

import argparse
import json
import os
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from dhg.cli.common import (
    EXIT_INTERNAL,
    EXIT_OK,
    NETWORK_EPILOG,
    check_seconds,
    endpoint,
    finite_float,
    stop_on_signals,
)
from dhg.core.session import GUIDANCE_MODES, MAX_BURR_RADIUS_M, MIN_BURR_RADIUS_M
from dhg.core.surgeon import MAX_ATTEMPT_S

__all__ = ["VIEW_NICE", "add_commands"]

VIEW_NICE = 10
"""``dhg view``'s nice value (its whole process, every thread): a screen yields the cores to the
haptic client and the server it shares a machine with, and draws with what is left
(``docs/decisions/0027-the-screen-yields-to-the-hand.md``)."""


# -- dhg trainee ------------------------------------------------------------------------------
def add_commands(sub: Any, epilog: str) -> None:
    """Adds ``trainee``, ``record``, ``view`` and ``live-demo`` to the ``dhg`` subcommands."""
    for add in (_add_trainee, _add_record, _add_view, _add_live_demo):
        add(sub, epilog)


def _add_trainee(sub: Any, epilog: str) -> None:
    """``dhg trainee``."""
    from dhg.live.runner import DEFAULT_ENDPOINT

    fmt = argparse.RawDescriptionHelpFormatter
    p = sub.add_parser(
        "trainee",
        help="a virtual trainee that drills through a running dhg-serve",
        description="Connects to a running dhg-serve, creates a session and drills A→B as a virtual "
        "surgeon (the operator model of 'dhg synth') who feels the force the server renders, guidance "
        "included, and reads the guidance as an instruction. In the paper's mode it leans into a cue that "
        "pushes the drill back (the expert pressed harder) and eases off one that pulls it in; in the other "
        "modes (corridor, brake, shaped) it yields to the cue, easing off where it resists. An expert eases "
        "off shortly before "
        "the depth where the session's planned layers (from the server's CT) show the burr leaving the "
        "first cortex. Prints the skill metrics and the "
        "pose→force and pose→guidance latencies at the end.\n\n"
        "  dhg trainee --skill novice --guidance on  --seed 3\n"
        "  dhg trainee --skill novice --guidance off --seed 3   # the same hand, unguided\n"
        "  dhg trainee --attempts 6 --fading --probe-every 3    # faded training, every 3rd attempt unguided\n\n"
        "With --attempts N the trainee drills N attempts, the session reset between them (a recorder "
        "starts a new episode for each), and learns from the plunge and deviation it felt in each, as the "
        "novices of 'dhg study' do. With --fading the server's fading schedule sets each attempt's gain "
        "from the last attempt's errors (assistance as needed) and makes every --probe-every-th attempt "
        "guidance-free.",
        epilog=NETWORK_EPILOG + epilog,
        formatter_class=fmt,
    )
    p.add_argument(
        "--connect",
        type=endpoint,
        default=DEFAULT_ENDPOINT,
        metavar="ENDPOINT",
        help=f"server (default {DEFAULT_ENDPOINT})",
    )
    p.add_argument("--session", metavar="ID", help="session id (default: trainee-<random>)")
    p.add_argument("--skill", choices=("novice", "expert"), default="novice", help="operator model (default novice)")
    p.add_argument("--guidance", choices=("on", "off"), default="on", help="feel the guidance force (default on)")
    p.add_argument("--gain", type=finite_float, default=1.0, metavar="G", help="guidance gain when on (default 1)")
    p.add_argument(
        "--guidance-mode",
        choices=GUIDANCE_MODES,
        help="the session's guidance mode (default: the server's, shaped unless dhg-serve --guidance-mode)",
    )
    p.add_argument(
        "--duration", type=finite_float, default=20.0, metavar="S", help="longest run in seconds (default 20)"
    )
    p.add_argument(
        "--drill-mm",
        type=finite_float,
        metavar="D",
        help="drill (burr) diameter in mm, e.g. 3.2 for a large guide wire (default: the server's, 2.5 mm)",
    )
    p.add_argument("--seed", type=int, default=0, help="the surgeon's style and tremor (default 0)")
    p.add_argument("--attempts", type=int, default=1, metavar="N", help="attempts, the bone reset between (default 1)")
    p.add_argument(
        "--fading",
        action="store_true",
        help="let the server fade the gain over the attempts (starting from --gain; docs/protocol.md, set_fading)",
    )
    p.add_argument(
        "--probe-every",
        type=int,
        metavar="K",
        help="with --fading, every Kth attempt is guidance-free (default: the server's, 4; 0: none)",
    )
    p.add_argument("--prefix", default="dhg", help="key prefix of the server (default dhg)")
    p.add_argument("--json", metavar="FILE", help="also write metrics and latencies (of every attempt) as JSON")
    p.add_argument("--zenoh-config", metavar="FILE", help="a Zenoh JSON5 config (TLS, credentials, ...)")
    p.set_defaults(func=_cmd_trainee)


def _add_record(sub: Any, epilog: str) -> None:
    """``dhg record``."""
    from dhg.live.runner import DEFAULT_ENDPOINT

    fmt = argparse.RawDescriptionHelpFormatter
    p = sub.add_parser(
        "record",
        help="record a live session into a demonstrations dataset",
        description="Subscribes to one session's 10 Hz state on a running dhg-serve and writes it in the "
        "dataset format of 'dhg synth' (records.parquet + card.json), rewriting the folder atomically "
        "every second: stopping it (Ctrl-C) or the server crashing keeps everything up to the last "
        "second. A reset of the session's bone starts a new attempt. With --raw it also keeps the 1 kHz "
        "stream (raw.parquet: every tick's pose, device force and guidance share), written in "
        "10-second parts that are joined when it stops cleanly. Train on it with "
        "'dhg train --data DIR' (label experts with --skill expert). With --all it records every "
        "session on the server, each into DIR/<session id> as it appears: one recorder for a class.\n\n"
        "  dhg record --session alice-01 --skill expert --raw --out data/alice\n"
        "  dhg record --all --skill novice --out data/class-3",
        epilog=NETWORK_EPILOG + epilog,
        formatter_class=fmt,
    )
    p.add_argument(
        "--connect",
        type=endpoint,
        default=DEFAULT_ENDPOINT,
        metavar="ENDPOINT",
        help=f"server (default {DEFAULT_ENDPOINT})",
    )
    which = p.add_mutually_exclusive_group(required=True)
    which.add_argument("--session", metavar="ID", help="the session to record")
    which.add_argument("--all", action="store_true", help="record every session, each into DIR/<session id>")
    p.add_argument("--out", required=True, metavar="DIR", help="dataset folder (replaced on every flush)")
    p.add_argument("--skill", default="unknown", help="label of the subject: expert, novice, ... (default unknown)")
    p.add_argument("--subject", metavar="NAME", help="subject id (default: the session id)")
    p.add_argument("--duration", type=finite_float, metavar="S", help="stop after S seconds (default: until Ctrl-C)")
    p.add_argument(
        "--flush-every", type=finite_float, default=1.0, metavar="S", help="seconds between writes (default 1)"
    )
    p.add_argument(
        "--status-every",
        type=finite_float,
        default=5.0,
        metavar="S",
        help="print what has been recorded every S seconds, or which sessions the server has while the one "
        "asked for sends nothing (default 5; 0: quiet)",
    )
    p.add_argument(
        "--raw", action="store_true", help="also keep the 1 kHz pose/force stream (raw.parquet, about 2 MB a minute)"
    )
    p.add_argument(
        "--overwrite",
        action="store_true",
        help="with --session, replace what --out holds (without it a folder that is not empty is refused; "
        "--all never replaces: a session whose folder holds a recording goes to <id>-2, <id>-3, ...)",
    )
    p.add_argument("--prefix", default="dhg", help="key prefix of the server (default dhg)")
    p.add_argument("--zenoh-config", metavar="FILE", help="a Zenoh JSON5 config (TLS, credentials, ...)")
    p.set_defaults(func=_cmd_record)


def _add_view(sub: Any, epilog: str) -> None:
    """``dhg view``."""
    from dhg.live.runner import DEFAULT_ENDPOINT

    p = sub.add_parser(
        "view",
        help="the live pages in a browser: a trainee's bone, drill and X-rays, or the instructor's class",
        description="Serves the live view of a running dhg-serve on a local web page. With --session, one "
        "trainee's page: the bone's layers in 3D (cortex see-through, cancellous bone, the lesion) "
        "re-meshed where the drill cuts, the planned path A->B, the drill at the tip's pose (30 Hz), "
        "force and guidance arrows, the numbers the hand feels (force, guidance share, thrust, "
        "temperature against 47 C, depth, lateral deviation, layer, a plunge warning, guidance mode and "
        "gain), a 20 s timeline, X-rays from the top, front and side on demand, and after each attempt "
        "(a reset) its skill metrics and plot. Without --session, the instructor's page on --port: every "
        "session on the server with its live state and metrics, each with a link to its own page (on the "
        "ports after --port). The viewer is one more Zenoh client: it never runs in the server's "
        "process. Open the printed URL in a browser; Ctrl-C stops it.\n\n"
        "  dhg view --session alice-01            # http://127.0.0.1:8080\n"
        "  dhg view --port 9000                   # the instructor's page, sessions on 9001, 9002, ...\n"
        "  dhg view --connect tls/lab-server:7447 --zenoh-config instructor.json5",
        epilog=NETWORK_EPILOG + epilog,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument(
        "--connect",
        type=endpoint,
        default=DEFAULT_ENDPOINT,
        metavar="ENDPOINT",
        help=f"server (default {DEFAULT_ENDPOINT})",
    )
    p.add_argument("--session", metavar="ID", help="one trainee's page (default: the instructor's page)")
    p.add_argument("--port", type=int, default=8080, help="the page's port (default 8080; 0: any free port)")
    p.add_argument("--host", default="127.0.0.1", help="address to serve on (default 127.0.0.1: this machine)")
    p.add_argument(
        "--frame-hz", type=finite_float, default=30.0, metavar="HZ", help="drill updates a second (default 30)"
    )
    p.add_argument("--duration", type=finite_float, metavar="S", help="stop after S seconds (default: until Ctrl-C)")
    p.add_argument("--prefix", default="dhg", help="key prefix of the server (default dhg)")
    p.add_argument("--zenoh-config", metavar="FILE", help="a Zenoh JSON5 config (the lab's instructor or station file)")
    p.add_argument(
        "--nice",
        type=int,
        default=VIEW_NICE,
        metavar="N",
        help=f"this process's nice value, 0 to 19 (default {VIEW_NICE}: on a machine it shares with a haptic "
        "station or the server, the screen gives way to them and draws with the CPU left over)",
    )
    p.set_defaults(func=_cmd_view)


def _cmd_view(args: argparse.Namespace) -> int:
    from dhg.view import Viewer

    check_seconds("--duration", args.duration)
    if not 0 <= args.nice <= 19:
        raise ValueError(f"--nice must be 0 (as the server) to 19 (yield to everything), got {args.nice}")
    _yield_cores(args.nice)
    with (
        stop_on_signals() as stop,
        Viewer(
            args.connect,
            port=args.port,
            session_id=args.session,
            host=args.host,
            prefix=args.prefix,
            zenoh_config_file=args.zenoh_config,
            frame_hz=args.frame_hz,
        ) as viewer,
    ):
        what = f"session {args.session}" if args.session else "the instructor's page (every session)"
        print(f"dhg view: {what} at {viewer.url} (Ctrl-C to stop)", flush=True)
        t0 = time.monotonic()
        stop.wait(args.duration)
        elapsed = time.monotonic() - t0
        # A page draws only while a browser watches it (decision 0029): its rate is per watched second.
        lines = [
            f"  {sid}: watched {p.watched_s:.0f} s, {p.frames} drill updates"
            f" ({p.frames / p.watched_s if p.watched_s else 0.0:.1f}/s watched), {p.bone_updates} bone queries, "
            f"{p.remeshed_chunks} chunks re-meshed"
            for sid, p in viewer.pages.items()
        ]
    print(f"dhg view stopped after {elapsed:.0f} s ({len(lines)} trainee page(s) served)", flush=True)
    for line in lines:
        print(line, flush=True)
    return EXIT_OK


def _yield_cores(nice: int) -> None:
    """Raises every thread of this process to at least ``nice``, before the viewer starts its own
    (Zenoh's, the web server's: they inherit it). Linux nice values are per thread, and some exist
    already (numpy's BLAS pool starts at import). Never lowered: that needs privilege."""
    if not os.path.isdir("/proc/self/task"):  # not Linux: the process's one nice value
        if hasattr(os, "nice"):
            os.nice(max(0, nice - os.nice(0)))
        return
    for tid in map(int, os.listdir("/proc/self/task")):
        try:
            if os.getpriority(os.PRIO_PROCESS, tid) < nice:
                os.setpriority(os.PRIO_PROCESS, tid, nice)
        except OSError:  # the thread ended meanwhile
            continue


def _add_live_demo(sub: Any, epilog: str) -> None:
    """``dhg live-demo``."""
    fmt = argparse.RawDescriptionHelpFormatter
    p = sub.add_parser(
        "live-demo",
        help="the whole product: dhg-serve plus a guided and an unguided virtual novice (make demo)",
        description="Starts dhg-serve (phantom femur, bundled model) on a free loopback port, runs a virtual "
        "novice with guidance and the same novice (same seed) without, each for up to --duration seconds, "
        "prints both runs' skill metrics and the guidance and latency figures side by side, writes the "
        "guided session's X-ray views (top/front/side.png) and live.png (force, guidance and temperature "
        "over time) into --out, and stops the server.",
        epilog=NETWORK_EPILOG + epilog,
        formatter_class=fmt,
    )
    p.add_argument("--out", default="out/demo", metavar="DIR", help="folder for the PNGs (default out/demo)")
    p.add_argument("--duration", type=finite_float, default=20.0, metavar="S", help="seconds per run (default 20)")
    p.add_argument("--seed", type=int, default=7, help="the novice's hand (default 7)")
    p.add_argument("--zenoh-config", metavar="FILE", help="a Zenoh JSON5 config for the server and both trainees")
    p.set_defaults(func=_cmd_live_demo)


def _check_trainee_args(args: argparse.Namespace) -> None:
    """Refuses ``dhg trainee`` flags that cannot go together, before connecting."""
    check_seconds("--duration", args.duration, MAX_ATTEMPT_S)
    if args.attempts < 1:
        raise ValueError(f"--attempts must be at least 1, got {args.attempts}")
    if args.probe_every is not None and (not args.fading or args.probe_every < 0):
        raise ValueError("--probe-every needs --fading and is 0 (no probes) or a positive count")
    if args.fading and args.guidance == "off":
        raise ValueError("--fading fades the guidance: it needs --guidance on")
    lo_mm, hi_mm = 2e3 * MIN_BURR_RADIUS_M, 2e3 * MAX_BURR_RADIUS_M
    if args.drill_mm is not None and not lo_mm <= args.drill_mm <= hi_mm:
        raise ValueError(f"--drill-mm must be a diameter in [{lo_mm:g}, {hi_mm:g}] mm, got {args.drill_mm}")


def _report_trainee(args: argparse.Namespace, runs: list[Any]) -> None:
    """Prints the last attempt's drill, skill metrics and latencies; writes ``--json``."""
    run = runs[-1]
    if args.attempts > 1:
        print(f"last attempt ({args.attempts}):")
    print(f"  drill diameter         {run.burr_radius_m * 2e3:g} mm")
    planned = run.planned_breakthrough_depth_m
    print(
        f"  planned breakthrough   {'none (no cortex on the path)' if planned is None else f'{planned * 1e3:.3f} mm'}"
    )
    report = {
        "session": run.session_id,
        "burr_radius_m": run.burr_radius_m,
        "planned_breakthrough_depth_m": run.planned_breakthrough_depth_m,
        "guidance_mode": run.guidance_mode,
        "metrics": run.metrics,
        "latency": run.latency,
        "poses": run.poses_sent,
        "attempts": [
            {
                "attempt": r.attempt,
                "guidance_gain": r.guidance_gain,
                "probe": r.probe,
                "fading": r.fading,
                "metrics": r.metrics,
                "poses": r.poses_sent,
            }
            for r in runs
        ],
    }
    for k, v in run.metrics.items():
        print(f"  {k:22s} {v}")
    lat = run.latency
    print(
        f"  pose→force    p50 {lat['pose_to_force_p50_s'] * 1e3:.2f} ms  p99 {lat['pose_to_force_p99_s'] * 1e3:.2f} ms "
        f"({lat['forces']} forces for {run.poses_sent} poses)"
    )
    print(
        f"  pose→guidance p50 {lat['pose_to_guidance_p50_s'] * 1e3:.2f} ms  "
        f"p99 {lat['pose_to_guidance_p99_s'] * 1e3:.2f} ms ({lat['guidance']} messages)"
    )
    if args.json:
        with open(args.json, "w") as fh:
            json.dump(report, fh, indent=1)


def _cmd_trainee(args: argparse.Namespace) -> int:
    from dhg.live.client import TraineeClient
    from dhg.live.trainee import TraineeRun, run_course

    _check_trainee_args(args)
    burr_radius_m = None if args.drill_mm is None else args.drill_mm / 2 * 1e-3
    gain = args.gain if args.guidance == "on" else 0.0
    with TraineeClient(args.connect, args.session, prefix=args.prefix, zenoh_config_file=args.zenoh_config) as client:
        client.health(1.0)  # fails fast, with a clear message, when no server answers
        fading = None
        if args.fading:
            fading = {} if args.probe_every is None else {"probe_every": args.probe_every}

        def finished(run: TraineeRun) -> None:
            if args.attempts > 1:
                m = run.metrics
                print(
                    f"  attempt {run.attempt + 1}: gain {run.guidance_gain:.2f}{' (probe)' if run.probe else ''}, "
                    f"plunge {m['plunge_depth_m'] * 1e3:.2f} mm, max deviation {m['max_deviation_m'] * 1e3:.2f} mm, "
                    f"reached B {'yes' if m['reached_target'] else 'no'}",
                    flush=True,
                )

        runs = run_course(
            client,
            args.attempts,
            args.skill,
            gain,
            args.duration,
            args.seed,
            fading=fading,
            burr_radius_m=burr_radius_m,
            guidance_mode=args.guidance_mode,
            on_start=lambda mode: print(
                f"session {client.session_id}: {args.skill}, guidance {args.guidance} ({mode}, gain {gain:g}"
                f"{', fading' if args.fading else ''}), seed {args.seed}",
                flush=True,
            ),
            on_attempt=finished,
        )
    _report_trainee(args, runs)
    return EXIT_OK


def _cmd_record(args: argparse.Namespace) -> int:
    from dhg.live.recorder import SessionRecorder

    check_seconds("--flush-every", args.flush_every, 3600.0)
    check_seconds("--status-every", args.status_every, 3600.0, zero_ok=True)
    check_seconds("--duration", args.duration)
    if args.all:
        if args.subject:
            raise ValueError("--subject names one subject; with --all each session's id is its subject")
        return _record_all(args)
    rec = SessionRecorder(
        args.connect,
        args.session,
        args.out,
        args.prefix,
        args.subject,
        args.skill,
        args.flush_every,
        zenoh_config_file=args.zenoh_config,
        raw=args.raw,
        overwrite=args.overwrite,
    )
    print(f"recording session {args.session} into {args.out} (Ctrl-C to stop)", flush=True)

    def status(t: float) -> None:
        if rec.records == 0:
            ids = rec.server_sessions()
            where = "no server answers" if ids is None else f"sessions on the server now: {', '.join(ids) or 'none'}"
            print(f"  {t:5.0f} s: nothing from session {args.session} yet ({where})", flush=True)
        else:
            ticks = f", {rec.raw_rows} ticks written" if args.raw else ""
            failed = f"; {rec.flush_errors} failed flushes (last: {rec.last_flush_error})" if rec.flush_errors else ""
            print(f"  {t:5.0f} s: {rec.records} records in {rec.attempts} attempt(s){ticks}{failed}", flush=True)

    _run_recorder(rec, args, status)
    print(f"recorded {rec.records} records in {rec.flushes} flushes to {args.out}{_left_out(rec)}")
    if args.raw:
        print(
            f"  1 kHz stream: {rec.raw_rows} ticks; {rec.lost_tick_batches} batches of 100 lost in transport "
            f"(not recoverable), {rec.raw_rows_without_records} in attempts too short for a record"
        )
    return EXIT_OK


def _left_out(rec: Any) -> str:
    """What a recorder (one session or ``--all``) left out, as "; ..." clauses; "" when nothing."""

    def n(name: str) -> int:
        return int(getattr(rec, name, 0))

    parts = [
        f"{n('invalid_messages')} impossible messages left out" if n("invalid_messages") else "",
        f"{n('refused_ids')} ids the server does not have ({n('unconfirmed_messages')} messages)"
        if n("refused_ids")
        else "",
        f"{n('flush_errors')} failed flushes (last: {rec.last_flush_error})" if n("flush_errors") else "",
        f"{n('lost_states')} states lost in transport (not recoverable)" if n("lost_states") else "",
        f"{n('lost_tick_batches')} batches of ticks lost in transport (not recoverable)"
        if n("lost_tick_batches")
        else "",
    ]
    return "".join(f"; {p}" for p in parts if p)


def _record_all(args: argparse.Namespace) -> int:
    from dhg.live.recorder import AllSessionsRecorder

    def found(session_id: str, folder: Path) -> None:
        print(f"  recording session {session_id} into {folder}", flush=True)

    rec = AllSessionsRecorder(
        args.connect,
        args.out,
        args.prefix,
        args.skill,
        args.flush_every,
        zenoh_config_file=args.zenoh_config,
        raw=args.raw,
        on_new_session=found,
    )
    print(f"recording every session into {args.out}/<session id> (Ctrl-C to stop)", flush=True)

    def status(t: float) -> None:
        print(f"  {t:5.0f} s: {len(rec.sessions)} sessions, {rec.records} records{_left_out(rec)}", flush=True)

    _run_recorder(rec, args, status)
    print(f"recorded {rec.records} records of {len(rec.sessions)} sessions to {args.out}{_left_out(rec)}")
    return EXIT_OK


def _run_recorder(rec: Any, args: argparse.Namespace, status: Callable[[float], None]) -> None:
    """Runs a recorder until Ctrl-C, SIGTERM or ``--duration``; it flushes a last time and closes."""
    try:
        with stop_on_signals() as stop:
            rec.run(stop, args.duration, status, args.status_every)
    finally:
        rec.close()


def _cmd_live_demo(args: argparse.Namespace) -> int:
    from dhg.cli.demo import run_live_demo

    check_seconds("--duration", args.duration, MAX_ATTEMPT_S)
    code = run_live_demo(args.out, args.duration, args.seed, zenoh_config_file=args.zenoh_config)
    return EXIT_OK if code == 0 else EXIT_INTERNAL
