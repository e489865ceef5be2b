"""The version of this build of DHG: the crate's (``crates/bone_sim/Cargo.toml``, its one
definition), as the native module reports it. Datasets, model files and the server's ``about``
stamp it."""

from __future__ import annotations

from dhg import _bone_sim

__all__ = ["__version__"]

__version__: str = _bone_sim.__version__
"""This build's version (a semantic version string, e.g. ``0.1.0``)."""
