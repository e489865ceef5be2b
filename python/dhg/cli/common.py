"""What every command line of DHG shares (``dhg`` in :mod:`dhg.cli.main`, ``dhg-serve`` and the live
commands in :mod:`dhg.cli.serve`): exit codes, the error-to-exit-code mapping, loading the bone,
progress bars. Both import from here, never from each other's modules in both directions."""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable
from pathlib import Path

from dhg.core.errors import DhgError, TransportError

__all__ = [
    "EXIT_BAD_INPUT",
    "EXIT_INTERNAL",
    "EXIT_NETWORK",
    "EXIT_OK",
    "EXIT_USAGE",
    "load_volume",
    "progress",
    "run_command",
]

EXIT_OK = 0
EXIT_INTERNAL = 1
EXIT_USAGE = 2
EXIT_BAD_INPUT = 3
EXIT_NETWORK = 5  # 4 meant "not built yet" while features were stubs; it is not reused


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
