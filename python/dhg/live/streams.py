"""A live session's streams as the recorder hears them (``dhg record``).

A session reaches the recorder as two Zenoh streams, each in order but not in step with the other:
the 1 kHz ticks (in the server's ``ticks`` batches, each tick with the pose it used and the force
it rendered) and the 10 Hz states (the records). Resetting the session's bone restarts both
clocks, which starts a new episode (attempt). :class:`EpisodeSplitter` puts both streams into
the same episodes (the ticks as its ``force`` stream). :class:`RawParts` keeps
the 1 kHz rows in parts of 10 s, so each write of a long recording rewrites at most one small
part (a minute-long part cost 38 ms per flush, a 10 s one 18 ms: ``docs/benchmarks.md``).

Ticks here are the session's step numbers from 0 at its start or reset, as in ``raw.parquet``:
the step with tick ``k`` ends at session time ``(k + 1)`` ms, so its force message says
``tick = k + 1`` and the record it completes says ``time_s = (k + 1) * 1e-3``.
"""

from __future__ import annotations

import array
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np
import numpy.typing as npt

from dhg.core.features import RECORD_COLUMNS, TICK_S
from dhg.data.dataset import RAW_FILE, RAW_PART_FILE, RawPart, raw_parquet_bytes, raw_schema

__all__ = [
    "RAW_COLUMNS",
    "STATE_COLUMNS",
    "STATE_INDEX",
    "EpisodeSplitter",
    "RawParts",
    "RecordingEpisode",
    "StateRows",
    "force_jerk",
]

RAW_COLUMNS = len(raw_schema().names) - 1
"""Columns of a raw row as the recorder holds it: the schema's less ``episode_id``."""

SKIP_SLACK_TICKS = 20
"""How far (ticks, 1 ms each) a message may lie past the other stream's last tick in an episode
that stream has left and still belong to it: forces dropped at an episode's end leave a gap. A
state further past belongs to a later episode (one shorter than this without a record of its own
would take the state; that needs 20 dropped forces in a row at a reset)."""

Stream = Literal["force", "state"]

STATE_COLUMNS: tuple[str, ...] = (
    *RECORD_COLUMNS,
    "plunge_depth_m",
    "peak_temperature_c",
    "time_above_47_s",
    "guidance_gain",
)
"""What the recorder keeps of a state message, in this order: its record (:data:`RECORD_COLUMNS`:
time, the nine features, drill on) and the values the attempt's metrics take from it."""

STATE_INDEX: dict[str, int] = {name: i for i, name in enumerate(STATE_COLUMNS)}
"""A column of a :class:`StateRows` array, by name."""


class StateRows:
    """An attempt's states as the recorder keeps them: :data:`STATE_COLUMNS`, 15 float64 a state
    (120 bytes; the decoded message, a dict, took about 1 KB), appended as they arrive."""

    __slots__ = ("_buf",)

    def __init__(self) -> None:
        self._buf = array.array("d")

    def append(self, m: dict[str, Any], drill_on: bool) -> None:
        """Appends a decoded ``state`` message."""
        self._buf.extend(
            (m["time_s"], *m["features"], float(drill_on), m["plunge_depth_m"], m["peak_temperature_c"],
             m["time_above_47_s"], m["guidance_gain"])
        )  # fmt: skip

    def __len__(self) -> int:
        return len(self._buf) // len(STATE_COLUMNS)

    def array(self) -> npt.NDArray[np.float64]:
        """A copy, (N, 15): the record (:data:`RECORD_COLUMNS`) is its first 11 columns."""
        return np.array(self._buf, dtype=np.float64).reshape(-1, len(STATE_COLUMNS))


@dataclass
class RecordingEpisode:
    """One episode (attempt) of the recorded session as both streams fill it."""

    last: dict[str, int] = field(default_factory=dict)
    """Newest tick each stream put in it."""
    records: StateRows = field(default_factory=StateRows)
    """Its states, in order."""
    rows: list[npt.NDArray[np.float64]] = field(default_factory=list)
    """Ticks not yet written, in blocks of raw rows (:data:`RAW_COLUMNS` columns each: tick, the
    pose, force, guidance)."""
    episode_id: int | None = None
    """Its id in the dataset, given with its first record (None: no record yet)."""
    jerk_sum: float = 0.0
    jerk_count: int = 0
    last_row: npt.NDArray[np.float64] | None = None
    path: Any = None
    """The planned path (:class:`dhg.core.path.PlannedPath`) its metrics are measured against:
    the session's as the recorder asked after the attempt began (None: not asked yet); a
    ``set_path`` between attempts gives the next attempt the new one."""
    written: Any = None
    """What the last write made of it: ((state count, path, 1 kHz force count), its states, records
    and metrics). A later write reuses it while those three are the same, so an attempt that has
    ended is computed once."""


class EpisodeSplitter:
    """Puts messages of the two streams into shared episodes by tick.

    Each stream walks the same list of episodes. A tick at or below the stream's previous tick in
    its episode is a reset. The stream then joins the next episode, which the other stream
    opened when it saw the same reset first, or opens it. An episode that the other stream left
    behind and whose ticks end more than :data:`SKIP_SLACK_TICKS` before this tick is one this
    stream never saw (an attempt shorter than one record has no state), and is passed over.
    """

    def __init__(self) -> None:
        self.episodes: list[RecordingEpisode] = []
        self._at: dict[str, int] = {"force": -1, "state": -1}

    def at(self, stream: Stream) -> int:
        """Index of the episode ``stream`` is in (-1 before its first message)."""
        return self._at[stream]

    def place(self, stream: Stream, tick: int) -> RecordingEpisode:
        """The episode of a ``stream`` message at ``tick``."""
        other: Stream = "state" if stream == "force" else "force"
        i = self._at[stream]
        if i >= 0 and tick > self.episodes[i].last[stream]:
            ep = self.episodes[i]
            ep.last[stream] = tick
            return ep
        j = i + 1
        while j < len(self.episodes):
            cand = self.episodes[j]
            left_behind = self._at[other] > j
            if not (left_behind and tick > cand.last.get(other, -1) + SKIP_SLACK_TICKS):
                break
            j += 1
        if j == len(self.episodes):
            self.episodes.append(RecordingEpisode())
        self._at[stream] = j
        ep = self.episodes[j]
        ep.last[stream] = tick
        return ep


def force_jerk(ep: RecordingEpisode, rows: npt.NDArray[np.float64]) -> None:
    """Adds new rows of ``ep`` (tick first, device force in columns 10–12) to its RMS rate of
    change of the device force (N/s), counting only consecutive ticks: a tick the transport
    lost leaves a gap, not a jump."""
    if ep.last_row is not None:
        rows = np.vstack([ep.last_row[None, :], rows])
    if len(rows) > 1:
        consecutive = np.diff(rows[:, 0]) == 1
        d = np.diff(rows[:, 10:13], axis=0)[consecutive] / TICK_S
        ep.jerk_sum += float(np.sum(d * d))
        ep.jerk_count += int(np.count_nonzero(consecutive))
    ep.last_row = rows[-1].copy()


class RawParts:
    """The 1 kHz rows of a recording, written as parts. The open part is rewritten on each
    write until it holds ``part_rows`` rows; then it is closed, and later writes hard-link it
    unchanged (:class:`dhg.data.dataset.RawPart`). :meth:`joined` makes the single ``raw.parquet``
    of a recording that ends cleanly."""

    def __init__(self, part_rows: int = 10_000) -> None:  # why 10,000: docs/decisions/0013-raw-part-size.md
        self.part_rows = part_rows
        self._closed: list[RawPart] = []
        self._open: list[npt.NDArray[np.float64]] = []
        self._open_rows = 0
        self.rows = 0

    def add(self, episode_id: int, rows: npt.NDArray[np.float64]) -> None:
        """Appends rows (:data:`RAW_COLUMNS` columns) of episode ``episode_id``."""
        if len(rows):
            self._open.append(np.column_stack([np.full(len(rows), float(episode_id)), rows]))
            self._open_rows += len(rows)
            self.rows += len(rows)

    def _table(self, arrays: list[npt.NDArray[np.float64]]) -> Any:
        import pyarrow as pa

        a = np.concatenate(arrays) if arrays else np.empty((0, RAW_COLUMNS + 1))
        schema = raw_schema()
        cols = [
            pa.array(a[:, i].astype(np.int32) if f.name in ("episode_id", "tick") else a[:, i], type=f.type)
            for i, f in enumerate(schema)
        ]
        return pa.Table.from_arrays(cols, schema=schema)

    def parts(self) -> list[RawPart]:
        """The parts for the next write: the closed ones (to link) and the open one (new bytes)."""
        if not self._open:
            return list(self._closed)
        return [*self._closed, _part(RAW_PART_FILE.format(len(self._closed)), self._table(self._open))]

    def written(self, parts: list[RawPart]) -> None:
        """Call after ``parts`` were written: closes the open part once it is full."""
        if self._open_rows >= self.part_rows and len(parts) > len(self._closed):
            p = parts[len(self._closed)]
            self._closed.append(RawPart(p.name, p.rows, p.sha256))
            self._open, self._open_rows = [], 0

    def joined(self, folder: Path) -> list[RawPart]:
        """Every row so far as one ``raw.parquet`` (the closed parts are read back from
        ``folder``, the dataset written last)."""
        import pyarrow as pa
        import pyarrow.parquet as pq

        if self.rows == 0:
            return []
        tables = [pq.read_table(folder / p.name) for p in self._closed]
        if self._open:
            tables.append(self._table(self._open))
        return [_part(RAW_FILE, pa.concat_tables(tables).cast(raw_schema()))]


def _part(name: str, table: Any) -> RawPart:
    import hashlib

    data = raw_parquet_bytes(table)
    return RawPart(name, table.num_rows, hashlib.sha256(data).hexdigest(), data)
