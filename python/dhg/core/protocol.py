"""Wire payloads of the real-time server, read from the one definition in the Rust core.

The layouts (field, type, byte offset, count, unit) come from ``dhg._bone_sim.protocol_layouts()``;
this module turns them into :mod:`struct` formats, so Python and Rust cannot disagree. The document
for client writers in other languages is ``docs/protocol.md``.

All payloads are little-endian and start with ``kind: u8, version: u8, flags: u16``. Positions are
world (LPS) coordinates in m, forces in N, times in s (``_ns`` fields: ns of the client's clock).
"""

from __future__ import annotations

import struct
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from dhg import _bone_sim
from dhg.core.errors import InvalidInputError

__all__ = [
    "FLAGS",
    "LAYOUTS",
    "MAX_PAYLOAD_BYTES",
    "MAX_QUERY_WINDOWS",
    "MAX_TICK_ROWS",
    "SERVER_LEAVES",
    "SESSION_LEAVES",
    "VERSION",
    "WINDOW_RECORDS",
    "Layout",
    "TICK_ROW",
    "decode",
    "decode_predict",
    "decode_ticks",
    "encode",
    "encode_pose",
    "encode_prediction",
    "keys",
    "server_key",
    "session_key",
    "session_of",
    "shared_predict_key",
    "worker_key",
    "worker_predict_key",
]

VERSION: int = _bone_sim.PROTOCOL_VERSION
WINDOW_RECORDS: int = _bone_sim.WINDOW_RECORDS
MAX_PAYLOAD_BYTES: int = _bone_sim.MAX_PAYLOAD_BYTES
MAX_QUERY_WINDOWS: int = _bone_sim.MAX_QUERY_WINDOWS
"""The most windows one model query holds (``predict`` messages back to back, ``entry`` 0, 1, …)."""

FLAGS: dict[str, int] = dict(_bone_sim.FLAGS)
"""Flag bits of the force and state headers (bit 0 of a pose: drill on), as the core defines them
(``protocol/``, ``flags``)."""

_CODES = {"u8": "B", "u16": "H", "u32": "I", "u64": "Q", "f32": "f", "f64": "d"}


@dataclass(frozen=True)
class Layout:
    """One payload layout: kind byte, fixed size (bytes) and its fields."""

    name: str
    kind: int
    size: int
    fields: tuple[tuple[str, str, int, int, str], ...]
    """(name, type, offset (bytes), count, unit) in order."""

    @property
    def struct(self) -> struct.Struct:
        """The :class:`struct.Struct` of the fixed part (no padding: fields are contiguous)."""
        return struct.Struct("<" + "".join(f"{n}{_CODES[t]}" if n > 1 else _CODES[t] for _, t, _, n, _ in self.fields))


LAYOUTS: dict[str, Layout] = {
    name: Layout(name, d["kind"], d["size"], tuple(tuple(f) for f in d["fields"]))
    for name, d in _bone_sim.protocol_layouts().items()
}
_STRUCTS = {name: layout.struct for name, layout in LAYOUTS.items()}
_DTYPES = {"u8": "<u1", "u16": "<u2", "u32": "<u4", "u64": "<u8", "f32": "<f4", "f64": "<f8"}
_ROW = LAYOUTS["tick_row"]
TICK_ROW: np.dtype = np.dtype(
    {
        "names": [name for name, *_ in _ROW.fields],
        "formats": [_DTYPES[ty] if n == 1 else (_DTYPES[ty], (n,)) for _, ty, _, n, _ in _ROW.fields],
        "offsets": [offset for _, _, offset, _, _ in _ROW.fields],
        "itemsize": _ROW.size,
    }
)
"""The numpy dtype of one row of a ``ticks`` batch (layout ``tick_row``)."""
MAX_TICK_ROWS: int = _bone_sim.MAX_TICK_ROWS


def check_session_id(session_id: str) -> str:
    """Returns ``session_id`` if it is a valid session id (the engine's rule: 1–64 of
    ``A-Z a-z 0-9 _ . -``, the first a letter or digit, so never ``.``, ``..`` or a hidden
    name), else raises :class:`dhg.core.errors.InvalidInputError` saying why."""
    from dhg.core.errors import InvalidInputError

    if not isinstance(session_id, str):
        raise InvalidInputError(f"session id {session_id!r}: must be a string")
    return _bone_sim.check_session_id(session_id)


_KEYS: dict[str, Any] = _bone_sim.key_layout()
SESSION_LEAVES: tuple[str, ...] = tuple(_KEYS["session_leaves"])
"""The leaves under a session's key (``pose``, ``force``, …, ``bone``), as the core defines them
(``protocol/keys.rs``)."""
SERVER_LEAVES: tuple[str, ...] = tuple(_KEYS["server_leaves"])
"""The server's own queryables under ``<prefix>/server/`` (``health``, ``about``, ``volume``)."""


def _fill(template: str, prefix: str, key_id: str = "", leaf: str = "") -> str:
    return template.replace("{prefix}", prefix).replace("{id}", key_id).replace("{leaf}", leaf)


def session_key(prefix: str, session_id: str, leaf: str | None = None) -> str:
    """``<prefix>/session/<id>[/<leaf>]`` (``session_id`` may be ``*``, ``leaf`` may go deeper:
    ``xray/top``)."""
    root = _fill(_KEYS["templates"]["session"], prefix, session_id)
    return root if leaf is None else f"{root}/{leaf}"


def session_of(prefix: str, key: str) -> str | None:
    """The session id of a key under ``<prefix>/session/<id>/…``, or None for any other key."""
    head = session_key(prefix, "")
    if not key.startswith(head):
        return None
    sid, sep, _ = key[len(head) :].partition("/")
    return sid if sep and sid else None


def server_key(prefix: str, leaf: str) -> str:
    """``<prefix>/server/<leaf>`` (one of :data:`SERVER_LEAVES`)."""
    return _fill(_KEYS["templates"]["server"], prefix, leaf=leaf)


def shared_predict_key(prefix: str) -> str:
    """``<prefix>/model/predict``: the key every model service answers."""
    return _fill(_KEYS["templates"]["shared_predict"], prefix)


def worker_key(prefix: str, worker_id: str) -> str:
    """``<prefix>/model/workers/<id>``: a pool worker's liveliness token (``worker_id`` may be ``*``)."""
    return _fill(_KEYS["templates"]["worker"], prefix, worker_id)


def worker_predict_key(prefix: str, worker_id: str) -> str:
    """``<prefix>/model/workers/<id>/predict``: the key a pool worker answers."""
    return _fill(_KEYS["templates"]["worker_predict"], prefix, worker_id)


def keys(prefix: str, session_id: str) -> dict[str, str]:
    """The key expressions of one session under ``prefix`` (``session_id`` may be ``*``): one per
    session leaf, the server's (``health``, ``about``, ``volume``) and the shared model key
    (``predict``); see ``docs/protocol.md``."""
    return (
        {leaf: session_key(prefix, session_id, leaf) for leaf in SESSION_LEAVES}
        | {leaf: server_key(prefix, leaf) for leaf in SERVER_LEAVES}
        | {"predict": shared_predict_key(prefix)}
    )


def encode(name: str, flags: int = 0, **values: Any) -> bytes:
    """Packs a fixed-size payload of layout ``name``; fields not given are zero."""
    layout = LAYOUTS[name]
    args: list[Any] = []
    for field, ty, _, count, _ in layout.fields:
        if field == "kind":
            v: Any = layout.kind
        elif field == "version":
            v = VERSION
        elif field == "flags":
            v = flags
        else:
            v = values.pop(field, 0 if count == 1 else [0] * count)
        if count > 1:
            seq = list(np.asarray(v, dtype=float if ty.startswith("f") else int).ravel())
            if len(seq) != count:
                raise InvalidInputError(f"{name}.{field} needs {count} values, got {len(seq)}")
            args.extend(seq)
        else:
            args.append(v)
    if values:
        raise InvalidInputError(f"{name} has no fields {sorted(values)}")
    return _STRUCTS[name].pack(*args)


def decode(name: str, payload: bytes) -> dict[str, Any]:
    """Unpacks a payload of layout ``name`` into a dict (vectors as tuples, ``flags`` as an int).

    Raises :class:`InvalidInputError` on a wrong size, kind or version.
    """
    layout = LAYOUTS[name]
    if len(payload) < layout.size:
        raise InvalidInputError(f"{name} payload has {len(payload)} bytes, expected {layout.size}")
    if payload[0] != layout.kind or payload[1] != VERSION:
        raise InvalidInputError(
            f"{name} payload has kind {payload[0]} version {payload[1]}, expected {layout.kind} v{VERSION}"
        )
    flat = _STRUCTS[name].unpack_from(payload)
    out: dict[str, Any] = {}
    i = 0
    for field, _, _, count, _ in layout.fields:
        out[field] = flat[i] if count == 1 else tuple(flat[i : i + count])
        i += count
    return out


def encode_pose(
    seq: int,
    client_time_ns: int,
    position_m: npt.ArrayLike,
    orientation_wxyz: npt.ArrayLike,
    drill_on: bool,
    spindle_rpm: float,
) -> bytes:
    """A stylus pose: burr centre (m, world), orientation quaternion (w, x, y, z; +z of the tool
    frame is the drill axis), drill on/off, spindle speed (rpm), the client's sequence number and
    clock (ns), both echoed in the force."""
    return encode(
        "pose",
        flags=FLAGS["drill_on"] if drill_on else 0,
        seq=seq & 0xFFFFFFFF,
        client_time_ns=client_time_ns,
        position_m=position_m,
        orientation_wxyz=orientation_wxyz,
        spindle_rpm=spindle_rpm,
    )


def decode_predict(payload: bytes) -> tuple[npt.NDArray[np.uint32], npt.NDArray[np.float32]]:
    """A model query → (window_seq of each window (n,), the windows (n, rows, cols) float32, oldest
    record first). A query holds 1 to :data:`MAX_QUERY_WINDOWS` ``predict`` messages back to back,
    ``entry`` 0, 1, … in order; the reply answers window ``i`` with a ``prediction`` of ``entry`` i.

    Raises :class:`InvalidInputError` on a wrong kind, version, size or entry order.
    """
    size = LAYOUTS["predict"].size
    start, count = next((f[2], f[3]) for f in LAYOUTS["predict"].fields if f[0] == "window")
    cols = count // WINDOW_RECORDS
    n, extra = divmod(len(payload), size)
    if n == 0 or extra or n > MAX_QUERY_WINDOWS:
        raise InvalidInputError(
            f"predict payload has {len(payload)} bytes: 1 to {MAX_QUERY_WINDOWS} windows of {size} bytes"
        )
    seqs = np.empty(n, dtype=np.uint32)
    for i in range(n):
        head = decode("predict", payload[i * size : (i + 1) * size])
        if (head["rows"], head["cols"]) != (WINDOW_RECORDS, cols):
            raise InvalidInputError(
                f"predict window {i} is {head['rows']}x{head['cols']}, expected {WINDOW_RECORDS}x{cols}"
            )
        if head["entry"] != i:
            raise InvalidInputError(f"predict window {i} has entry {head['entry']}: entries run 0, 1, … in order")
        seqs[i] = head["window_seq"]
    records = np.frombuffer(payload, dtype="<f4").reshape(n, size // 4)
    windows = records[:, start // 4 :].reshape(n, WINDOW_RECORDS, cols)
    return seqs, windows


def decode_ticks(payload: bytes) -> npt.NDArray[np.void]:
    """A ``ticks`` batch → its rows (a structured array of :data:`TICK_ROW`, oldest first).

    Raises :class:`InvalidInputError` on a wrong kind, version or size, more than
    ``MAX_TICK_ROWS`` rows, or a NaN or infinite value.
    """
    fixed = LAYOUTS["ticks"].size
    if len(payload) > fixed + MAX_TICK_ROWS * _ROW.size:
        raise InvalidInputError(f"ticks payload has {len(payload)} bytes, over {MAX_TICK_ROWS} rows")
    head = decode("ticks", payload[:fixed])
    rows = head["rows"]
    if len(payload) != fixed + rows * _ROW.size:
        raise InvalidInputError(f"ticks payload has {len(payload)} bytes for {rows} rows of {_ROW.size}")
    out = np.frombuffer(payload, dtype=TICK_ROW, offset=fixed, count=rows)
    for name in ("position_m", "orientation_wxyz", "spindle_rpm", "force_n", "guidance_n"):
        if not np.isfinite(out[name]).all():
            raise InvalidInputError(f"ticks payload has a NaN or infinite {name}")
    return out


def encode_prediction(
    window_seq: int, force_n: npt.ArrayLike, inference_s: float, model_id: str, entry: int = 0
) -> bytes:
    """A model reply's answer to the query's window ``entry``: predicted expert force (N, world),
    inference time (s) and the model id. A reply holds one or more back to back."""
    ident = model_id.encode()[:1024]
    body = encode(
        "prediction",
        window_seq=window_seq,
        force_n=force_n,
        inference_s=inference_s,
        model_id_len=len(ident),
        entry=entry,
    )
    return body + ident
