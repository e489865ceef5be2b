"""Shared fixtures: phantoms are built once per test session (volumes are immutable); the end-to-end
modules each share one ``dhg-serve``."""

from __future__ import annotations

from collections.abc import Iterator

import pytest

import dhg
from dhg.live.process import ServerProcess
from support import serve


@pytest.fixture(scope="session")
def phantom() -> dhg.Phantom:
    """The default phantom at its default 0.5 mm voxels (~2 s to build)."""
    return dhg.default_phantom()


@pytest.fixture(scope="session")
def coarse_phantom() -> dhg.Phantom:
    """The phantom at 1 mm voxels, for tests that only need the anatomy roughly."""
    return dhg.femur(seed=0, voxel_m=1e-3)


@pytest.fixture(scope="module")
def server() -> Iterator[tuple[ServerProcess, str]]:
    """One ``dhg-serve --role all`` with a 1 s idle timeout per module that asks for it. Its clean
    stop is checked by the module's last test (``support.stops_cleanly``; not here: an assert in a
    teardown fails whichever test ran last); this only makes sure it is stopped."""
    proc, endpoint = serve("--idle-timeout", "1.0")
    yield proc, endpoint
    proc.stop()
