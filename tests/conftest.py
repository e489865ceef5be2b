"""Shared fixtures: phantoms are built once per test session (volumes are immutable)."""

from __future__ import annotations

import pytest

import dhg


@pytest.fixture(scope="session")
def phantom() -> dhg.Phantom:
    """The default phantom at its default 0.5 mm voxels (~2 s to build)."""
    return dhg.default_phantom()


@pytest.fixture(scope="session")
def coarse_phantom() -> dhg.Phantom:
    """The phantom at 1 mm voxels, for tests that only need the anatomy roughly."""
    return dhg.femur(seed=0, voxel_m=1e-3)
