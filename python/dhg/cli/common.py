"""What every command line of DHG shares (``dhg`` in :mod:`dhg.cli.main`, ``dhg-serve`` in
:mod:`dhg.cli.serve`, the live commands in :mod:`dhg.cli.live`): exit codes, the error-to-exit-code
mapping, loading the bone, progress bars, stopping on a signal. They import from here, never from
each other in both directions."""

from __future__ import annotations

import argparse
import math
import re
import signal
import sys
import threading
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from dhg.core.errors import DhgError, TransportError

__all__ = [
    "NETWORK_EPILOG",
    "check_seconds",
    "endpoint",
    "finite_float",
    "EXIT_BAD_INPUT",
    "EXIT_INTERNAL",
    "EXIT_NETWORK",
    "EXIT_OK",
    "EXIT_USAGE",
    "load_volume",
    "stop_on_signals",
    "progress",
    "run_command",
]

EXIT_OK = 0
EXIT_INTERNAL = 1
EXIT_USAGE = 2
EXIT_BAD_INPUT = 3
EXIT_NETWORK = 5  # 4 meant "not built yet" while features were stubs; it is not reused


def finite_float(text: str) -> float:
    """argparse's ``type`` for every number option: a float, refusing NaN and infinity (``float``
    takes both), so a bad value is a usage error (exit 2) naming its option."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number") from None
    if not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"{text!r} is not a finite number")
    return value


LONGEST_WAIT_S = 7 * 24 * 3600.0
"""The longest ``--duration`` a live command takes (a week; without it they run until Ctrl-C)."""


def check_seconds(option: str, value: float | None, most_s: float = LONGEST_WAIT_S, zero_ok: bool = False) -> None:
    """Refuses (``ValueError``, exit 3) a time option that is not > 0 (``zero_ok``: >= 0) and at
    most ``most_s``; ``None`` (not given) passes."""
    if value is None:
        return
    low_ok = value >= 0 if zero_ok else value > 0
    if not (low_ok and value <= most_s):  # also refuses NaN
        low = ">= 0" if zero_ok else "> 0"
        raise ValueError(f"{option} must be {low} and at most {most_s:g} s, got {value}")


_ENDPOINT = re.compile(r"[a-z][a-z0-9-]*/\S+")


def endpoint(text: str) -> str:
    """argparse's ``type`` for a Zenoh endpoint (``PROTOCOL/ADDRESS``, e.g. ``tcp/127.0.0.1:7447``):
    a malformed one is a usage error (exit 2), not network trouble."""
    if not _ENDPOINT.fullmatch(text):
        raise argparse.ArgumentTypeError(
            f"{text!r} is not a Zenoh endpoint: PROTOCOL/ADDRESS, e.g. tcp/127.0.0.1:7447 or tls/lab-server:7447"
        )
    return text


def load_volume(ct: str | None, voxel_mm: float):  # -> tuple[Volume, PlannedPath | None]
    """The phantom (default), a prepared volume file (.npz), or a CT to import."""
    from dhg.bone import phantom
    from dhg.core.path import PlannedPath
    from dhg.core.volume import Volume

    if ct is None:
        p = phantom.default_phantom(0, voxel_mm * 1e-3)
        return p.volume, p.path
    path = Path(ct)
    if path.suffix == ".npz":
        vol = Volume.load(path)
    else:
        from dhg.bone import ct as ct_mod

        vol = ct_mod.prepare(path, voxel_m=voxel_mm * 1e-3)
    planned = vol.meta.get("planned_path")
    return vol, (PlannedPath.from_dict(planned) if planned else None)


def progress(description: str):
    """A rich progress bar as a context manager with an ``update(done, total)`` callback."""
    from rich.progress import BarColumn, Progress, TaskProgressColumn, TextColumn, TimeRemainingColumn

    prog = Progress(
        TextColumn("{task.description}"),
        BarColumn(),
        TaskProgressColumn(),
        TimeRemainingColumn(),
        transient=False,
        disable=not sys.stderr.isatty(),
    )
    task = prog.add_task(description, total=None)

    def update(done: int, total: int) -> None:
        prog.update(task, completed=done, total=total)

    return prog, update


def run_command(func: Callable[[argparse.Namespace], int], args: argparse.Namespace) -> int:
    """Runs a command; maps a network failure to exit 5, bad input to 3, Ctrl-C to 130."""
    try:
        return int(func(args))
    except TransportError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return EXIT_NETWORK
    except (DhgError, ValueError, TypeError, OSError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return EXIT_BAD_INPUT
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130


NETWORK_EPILOG = """\
exit codes: 0 success, 1 internal error, 2 usage error, 3 bad input (CT, model file, values),
5 network trouble (endpoint in use, no server answering), 130 interrupted (Ctrl-C).
endpoints look like tcp/127.0.0.1:7447 (loopback) or tcp/0.0.0.0:7447 (every interface).
key expressions and payloads: docs/protocol.md. Units: SI (m, N, s, °C).
"""
"""The epilog of every command that talks over Zenoh."""


@contextmanager
def stop_on_signals() -> Iterator[threading.Event]:
    """An event set by SIGINT (Ctrl-C) or SIGTERM, instead of an exception at a random place."""
    stop = threading.Event()
    previous = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM)}

    def handler(signum: int, _frame: Any) -> None:
        stop.set()

    for s in previous:
        signal.signal(s, handler)
    try:
        yield stop
    finally:
        for s, h in previous.items():
            signal.signal(s, h)
