"""Type stubs for the native core ``dhg._bone_sim`` (written by hand; checked by mypy.stubtest)."""

from collections.abc import Sequence
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
    "FULL_MATERIAL",
    "XRAY_VIEWS",
    "MIN_PATH_LENGTH_M",
    "DEFAULT_RESERVED_BRICKS",
    "PLAN_STEP_M",
    "MAX_GAIN",
    "MAX_BURR_RADIUS_M",
    "MIN_BURR_RADIUS_M",
    "MAX_POSITION_M",
    "MAX_SPINDLE_RPM",
    "GUIDANCE_MODES",
    "PROTOCOL_VERSION",
    "WINDOW_RECORDS",
    "MAX_PAYLOAD_BYTES",
    "MAX_QUERY_WINDOWS",
    "MAX_TICK_ROWS",
    "Server",
    "SurgeonController",
    "surgeon_constants",
    "axis_quaternion",
    "protocol_layouts",
    "key_layout",
    "threshold_layers",
    "check_session_id",
    "check_zenoh_runtime",
    "defaults",
    "control_ops",
    "skill_metrics",
    "reply_schemas",
    "ERROR_KINDS",
    "FLAGS",
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
FULL_MATERIAL: Final[int]
XRAY_VIEWS: Final[list[str]]
MIN_PATH_LENGTH_M: Final[float]
DEFAULT_RESERVED_BRICKS: Final[int]
PLAN_STEP_M: Final[float]
MAX_GAIN: Final[float]
MAX_BURR_RADIUS_M: Final[float]
MIN_BURR_RADIUS_M: Final[float]
MAX_SPINDLE_RPM: Final[float]
GUIDANCE_MODES: Final[list[_GuidanceMode]]
MAX_POSITION_M: Final[float]
PROTOCOL_VERSION: Final[int]
WINDOW_RECORDS: Final[int]
MAX_PAYLOAD_BYTES: Final[int]
MAX_QUERY_WINDOWS: Final[int]
MAX_TICK_ROWS: Final[int]
ERROR_KINDS: Final[list[str]]
FLAGS: Final[list[tuple[str, int]]]
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
    ) -> dict[str, Any]: ...
    def remove_along(
        self,
        centers_m: npt.NDArray[np.float64],
        radius_m: float,
        spindle_rpm: float,
        dt_s: float,
        contact: float = 1.0,
    ) -> dict[str, Any]: ...
    def material_at(
        self, points_m: npt.NDArray[np.float64], interp: _Interp = "nearest"
    ) -> npt.NDArray[np.float64]: ...
    def layer_at(self, points_m: npt.NDArray[np.float64]) -> npt.NDArray[np.uint8]: ...
    def material_grid(self) -> npt.NDArray[np.float32]: ...
    def xray(self) -> tuple[_Image, _Image, _Image]: ...
    def bricks(self) -> tuple[npt.NDArray[np.uint32], npt.NDArray[np.uint16]]: ...
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
        config: dict[str, Any] | None = None,
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
    def set_fading(self, params: dict[str, Any] | None = None) -> None: ...
    def fading(self) -> dict[str, Any] | None: ...
    def guidance_params(self) -> dict[str, Any]: ...
    def set_guidance_params(self, params: dict[str, Any]) -> None: ...
    def set_prediction(self, predicted_n: tuple[float, float, float] | list[float]) -> npt.NDArray[np.float64]: ...
    def drive(self, surgeon: SurgeonController, guided: bool = False) -> npt.NDArray[np.float64] | None: ...
    @property
    def planned_breakthrough_depth_m(self) -> float | None: ...
    def reset(self, rest_device: bool = False) -> None: ...
    def xray(self) -> tuple[_Image, _Image, _Image]: ...
    @property
    def memory_bytes(self) -> int: ...
    def config(self) -> dict[str, Any]: ...

_Field = tuple[str, str, int, int, str]

@final
class SurgeonController:
    def __new__(
        cls,
        entry_m: Sequence[float],
        target_m: Sequence[float],
        style: dict[str, Any],
        seed: int,
        max_duration_s: float,
        breakthrough_depth_m: float | None = None,
        cue_meaning: str = "match",
        keep_raw: bool = False,
    ) -> SurgeonController: ...
    def step(
        self, feedback: Sequence[float], force_n: Sequence[float], cue_n: Sequence[float] = ...
    ) -> list[float] | None: ...
    @property
    def done(self) -> bool: ...
    @property
    def phase(self) -> str: ...
    @property
    def ticks(self) -> int: ...
    @property
    def max_ticks(self) -> int: ...
    @property
    def drilling_s(self) -> float: ...
    @property
    def push_n(self) -> float: ...
    @property
    def lean_n(self) -> float: ...
    @property
    def max_plunge_m(self) -> float: ...
    @property
    def buzz_felt_s(self) -> float: ...
    def raw(self) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.float64]] | None: ...

def surgeon_constants() -> dict[str, float]: ...
def axis_quaternion(d: Sequence[float]) -> list[float]: ...
def protocol_layouts() -> dict[str, dict[str, Any]]: ...
def check_session_id(session_id: str) -> str: ...
def check_zenoh_runtime() -> None: ...
def defaults() -> dict[str, dict[str, Any]]: ...
def control_ops() -> list[tuple[str, list[str]]]: ...
def key_layout() -> dict[str, Any]: ...
def threshold_layers(hu: npt.NDArray[np.float32], mapping: dict[str, float] | None = None) -> npt.NDArray[np.uint8]: ...
def reply_schemas() -> dict[str, dict[str, Any]]: ...
def skill_metrics(
    records: npt.NDArray[np.float64],
    entry_m: Sequence[float],
    target_m: Sequence[float],
    final_tip_m: Sequence[float],
    drilling_s: float,
    plunge_depth_m: float,
    peak_temperature_c: float,
    time_above_47_s: float,
    rules: dict[str, float] | None = None,
    forces_n: npt.NDArray[np.float64] | None = None,
) -> dict[str, float | bool]: ...

@final
class Server:
    def __new__(
        cls,
        volume: Volume,
        entry_m: tuple[float, float, float] | list[float],
        target_m: tuple[float, float, float] | list[float],
        zenoh_json5: str,
        prefix: str = "dhg",
        settings: dict[str, Any] | None = None,
        session: dict[str, Any] | None = None,
    ) -> Server: ...
    def health(self, window_s: float = 10.0) -> dict[str, Any]: ...
    def sessions(self) -> list[str]: ...
    def metrics(self, session_id: str) -> dict[str, Any]: ...
    def control(self, session_id: str, request: dict[str, Any]) -> dict[str, Any]: ...
    def xray(self, session_id: str, timeout_s: float = 1.0) -> tuple[_Image, _Image, _Image]: ...
    def bricks(
        self, session_id: str, timeout_s: float = 1.0
    ) -> tuple[npt.NDArray[np.uint32], npt.NDArray[np.uint16]]: ...
    def stop(self) -> None: ...
    @property
    def running(self) -> bool: ...
    @property
    def new_session_guidance(self) -> dict[str, Any]: ...
