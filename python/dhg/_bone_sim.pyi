"""Type stubs for the native core ``dhg._bone_sim`` (written by hand; checked by mypy.stubtest)."""

from typing import Any, Final, Literal, final

import numpy as np
import numpy.typing as npt

__all__ = [
    "Volume",
    "DrilledVolume",
    "DrillingSession",
    "FEATURE_NAMES",
    "FEATURE_UNITS",
    "RECORD_PERIOD_TICKS",
    "TICK_S",
    "POSE_COLUMNS",
    "RECORD_COLUMNS",
    "LAYER_NAMES",
    "HU_MIN",
    "HU_MAX",
    "BRICK_EDGE",
    "MAX_BURR_RADIUS_M",
    "MIN_BURR_RADIUS_M",
    "MAX_POSITION_M",
    "MAX_SPINDLE_RPM",
    "GUIDANCE_MODES",
    "PROTOCOL_VERSION",
    "WINDOW_RECORDS",
    "MAX_PAYLOAD_BYTES",
    "Server",
    "protocol_layouts",
    "check_session_id",
    "__version__",
]

LAYER_NAMES: Final[list[str]]
FEATURE_NAMES: Final[list[str]]
FEATURE_UNITS: Final[list[str]]
RECORD_PERIOD_TICKS: Final[int]
TICK_S: Final[float]
POSE_COLUMNS: Final[int]
RECORD_COLUMNS: Final[int]
HU_MIN: Final[int]
HU_MAX: Final[int]
BRICK_EDGE: Final[int]
MAX_BURR_RADIUS_M: Final[float]
MIN_BURR_RADIUS_M: Final[float]
MAX_SPINDLE_RPM: Final[float]
GUIDANCE_MODES: Final[list[str]]
MAX_POSITION_M: Final[float]
PROTOCOL_VERSION: Final[int]
WINDOW_RECORDS: Final[int]
MAX_PAYLOAD_BYTES: Final[int]
__version__: Final[str]

_Interp = Literal["nearest", "linear"]
_Image = npt.NDArray[np.float32]

@final
class Volume:
    def __new__(
        cls,
        hu: npt.NDArray[np.float32],
        spacing_m: tuple[float, float, float],
        origin_m: tuple[float, float, float],
        direction: npt.NDArray[np.float64],
        labels: npt.NDArray[np.uint8] | None = None,
        mapping: dict[str, float] | None = None,
    ) -> Volume: ...
    @property
    def shape(self) -> tuple[int, int, int]: ...
    @property
    def spacing_m(self) -> list[float]: ...
    @property
    def origin_m(self) -> list[float]: ...
    @property
    def direction(self) -> npt.NDArray[np.float64]: ...
    @property
    def mapping(self) -> dict[str, float]: ...
    @property
    def memory_bytes(self) -> int: ...
    def labels(self) -> npt.NDArray[np.uint8]: ...
    def hu(self) -> npt.NDArray[np.int16]: ...
    def layer_at(self, points_m: npt.NDArray[np.float64]) -> npt.NDArray[np.uint8]: ...
    def layer_runs(
        self,
        entry_m: tuple[float, float, float] | list[float],
        target_m: tuple[float, float, float] | list[float],
        step_m: float,
    ) -> list[tuple[int, float, float]]: ...
    def hu_at(self, points_m: npt.NDArray[np.float64], interp: _Interp = "linear") -> npt.NDArray[np.float64]: ...
    def density_at(self, points_m: npt.NDArray[np.float64], interp: _Interp = "linear") -> npt.NDArray[np.float64]: ...
    def world_to_index(self, points_m: npt.NDArray[np.float64]) -> npt.NDArray[np.float64]: ...
    def xray(self) -> tuple[_Image, _Image, _Image]: ...

@final
class DrilledVolume:
    def __new__(cls, volume: Volume, reserve_bricks: int = 512) -> DrilledVolume: ...
    @property
    def volume(self) -> Volume: ...
    def remove(
        self,
        center_m: tuple[float, float, float],
        radius_m: float,
        spindle_rpm: float,
        dt_s: float,
        contact: float = 1.0,
    ) -> dict[str, float]: ...
    def remove_along(
        self,
        centers_m: npt.NDArray[np.float64],
        radius_m: float,
        spindle_rpm: float,
        dt_s: float,
        contact: float = 1.0,
    ) -> dict[str, float]: ...
    def material_at(
        self, points_m: npt.NDArray[np.float64], interp: _Interp = "nearest"
    ) -> npt.NDArray[np.float64]: ...
    def layer_at(self, points_m: npt.NDArray[np.float64]) -> npt.NDArray[np.uint8]: ...
    def material_grid(self) -> npt.NDArray[np.float32]: ...
    def xray(self) -> tuple[_Image, _Image, _Image]: ...
    def reset(self) -> None: ...
    @property
    def removed_mass_kg(self) -> float: ...
    @property
    def removed_voxels(self) -> int: ...
    @property
    def drilled_bricks(self) -> int: ...
    @property
    def memory_bytes(self) -> int: ...

_GuidanceMode = Literal["paper", "corridor", "brake", "shaped"]

@final
class DrillingSession:
    def __new__(
        cls,
        volume: Volume,
        entry_m: tuple[float, float, float],
        target_m: tuple[float, float, float],
        config: dict[str, float] | None = None,
    ) -> DrillingSession: ...
    def tick(
        self, pose: tuple[float, ...] | None = None
    ) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.float64] | None]: ...
    def step(self, poses: npt.NDArray[np.float64]) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.float64]]: ...
    def state(self) -> dict[str, Any]: ...
    def feedback(self) -> tuple[float, float, float, float, float, float, int, bool, int, bool, float]: ...
    def set_path(self, entry_m: tuple[float, float, float], target_m: tuple[float, float, float]) -> None: ...
    def path(self) -> tuple[list[float], list[float]]: ...
    def guidance_share(self) -> tuple[float, float, float]: ...
    def set_guidance(self, mode: _GuidanceMode, gain: float) -> None: ...
    def guidance(self) -> tuple[str, float]: ...
    def set_corridor_profile(self, bin_m: float, stiffness_n_per_m: list[float]) -> None: ...
    def set_fading(self, params_json: str | None = None) -> None: ...
    def fading(self) -> str | None: ...
    def set_prediction(self, predicted_n: tuple[float, float, float] | list[float]) -> npt.NDArray[np.float64]: ...
    @property
    def planned_breakthrough_depth_m(self) -> float | None: ...
    def reset(self) -> None: ...
    def xray(self) -> tuple[_Image, _Image, _Image]: ...
    @property
    def memory_bytes(self) -> int: ...
    def config(self) -> dict[str, float]: ...

_Field = tuple[str, str, int, int, str]

def protocol_layouts() -> dict[str, dict[str, Any]]: ...
def check_session_id(session_id: str) -> str: ...

@final
class Server:
    def __new__(
        cls,
        volume: Volume,
        entry_m: tuple[float, float, float] | list[float],
        target_m: tuple[float, float, float] | list[float],
        zenoh_json5: str,
        prefix: str = "dhg",
        max_sessions: int = 16,
        server: dict[str, float] | None = None,
        session: dict[str, float] | None = None,
        wait: str = "sleep",
        guidance_mode: _GuidanceMode = "shaped",
        corridor_profile: tuple[float, list[float]] | None = None,
        session_owners: list[str] = ...,
        max_sessions_per_owner: int = 0,
    ) -> Server: ...
    def health(self, window_s: float = 10.0) -> dict[str, Any]: ...
    def sessions(self) -> list[str]: ...
    def metrics(self, session_id: str) -> dict[str, Any]: ...
    def control(self, session_id: str, request: dict[str, Any]) -> dict[str, Any]: ...
    def xray(self, session_id: str, timeout_s: float = 1.0) -> tuple[_Image, _Image, _Image]: ...
    def stop(self) -> None: ...
    @property
    def running(self) -> bool: ...
