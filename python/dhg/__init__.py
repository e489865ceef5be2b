"""DHG — Deep Haptic Guidance: a real-time haptic guidance server for training bone drilling.

Units are SI everywhere (m, kg, s, N; °C for temperature). Frames and array layouts:
``docs/frames.md``.
"""

from __future__ import annotations

from dhg.bone.phantom import Phantom, default_phantom, femur
from dhg.core.errors import (
    CTImportError,
    DhgError,
    EngineError,
    InvalidInputError,
    ShapeError,
    TransportError,
    VolumeFileError,
)
from dhg.core.layers import Layer
from dhg.core.path import PlannedPath
from dhg.core.server import Server, ServerSettings, start_engine
from dhg.core.session import (
    CuttingLaw,
    DeviceProfile,
    DrillingSession,
    SessionConfig,
    SessionState,
    StepResult,
    ThermalParams,
)
from dhg.core.version import __version__
from dhg.core.volume import DrilledVolume, HuMapping, RemovalReport, Volume, XRayViews

__all__ = [
    "CTImportError",
    "CuttingLaw",
    "DeviceProfile",
    "DrillingSession",
    "SessionConfig",
    "SessionState",
    "StepResult",
    "ThermalParams",
    "DhgError",
    "DrilledVolume",
    "EngineError",
    "HuMapping",
    "InvalidInputError",
    "Layer",
    "Phantom",
    "PlannedPath",
    "RemovalReport",
    "Server",
    "ServerSettings",
    "ShapeError",
    "TransportError",
    "Volume",
    "VolumeFileError",
    "XRayViews",
    "__version__",
    "default_phantom",
    "femur",
    "start_engine",
]
