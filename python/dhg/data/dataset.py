"""Demonstration datasets: the paper's 10 Hz records in Parquet, with a JSON dataset card.

A dataset is a folder:

- ``records.parquet``: one row per 10 Hz record, in episode order; an episode's rows are
  contiguous and time-ordered. Columns are ``episode_id``, ``subject_id``, ``skill``, ``attempt``,
  ``time_s``, the nine features in :data:`dhg.core.features.FEATURE_NAMES` order, and ``drill_on``.
  Each column carries its unit in the Parquet field metadata.
- ``raw.parquet`` (optional): the 1 kHz stream, one row per tick: ``episode_id``, ``tick``, the
  pose columns (:data:`dhg.core.features.POSE_COLUMNS`), the device force and its guidance share, for
  replay. A recording that stopped without its final write keeps it in parts
  (``raw-00000.parquet``, ``raw-00001.parquet``, ...), which :func:`load_raw` joins.
- ``card.json``: format and version, units, feature order, sampling rate, frame, the volume and
  planned path used, the generator's version and seed, per-episode styles and skill metrics, and
  each file's row count and SHA-256.

Virtual surgeons (``dhg synth``) and recordings of real people (``dhg record``) share this format.
:func:`load_dataset` refuses anything that does not match it, and says why.
"""

from __future__ import annotations

import ctypes
import errno
import hashlib
import json
import os
import shutil
import sys
import tempfile
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from dhg.core.errors import DhgError
from dhg.core.features import FEATURE_NAMES, FEATURE_UNITS, POSE_COLUMNS, RECORD_PERIOD_S
from dhg.core.layers import Layer

__all__ = [
    "DATASET_FORMAT",
    "DATASET_VERSION",
    "DatasetError",
    "Dataset",
    "EpisodeData",
    "RawPart",
    "load_dataset",
    "load_raw",
    "raw_parquet_bytes",
    "raw_parquet_options",
    "raw_schema",
    "records_schema",
    "volume_card",
    "EpisodeInput",
    "write_dataset",
]

DATASET_FORMAT = "dhg-demonstrations"
DATASET_VERSION = 1
RECORDS_FILE = "records.parquet"
RAW_FILE = "raw.parquet"
RAW_PART_FILE = "raw-{:05d}.parquet"
FORCE_COLUMNS = ("force_x_n", "force_y_n", "force_z_n")
GUIDANCE_COLUMNS = ("guidance_x_n", "guidance_y_n", "guidance_z_n")
CARD_FILE = "card.json"


class DatasetError(DhgError, ValueError):
    """A dataset folder that is missing, corrupt, truncated, or not in the documented format."""


def _pa():
    import pyarrow as pa

    return pa


def records_schema():
    """The exact Arrow schema of ``records.parquet`` (units in the field metadata)."""
    pa = _pa()
    fields = [
        pa.field("episode_id", pa.int32(), nullable=False),
        pa.field("subject_id", pa.string(), nullable=False),
        pa.field("skill", pa.string(), nullable=False),
        pa.field("attempt", pa.int32(), nullable=False),
        pa.field("time_s", pa.float64(), nullable=False, metadata={"unit": "s"}),
    ]
    for name, unit in zip(FEATURE_NAMES, FEATURE_UNITS, strict=True):
        kind = pa.int8() if name == "layer" else pa.float64()
        fields.append(pa.field(name, kind, nullable=False, metadata={"unit": unit}))
    fields.append(pa.field("drill_on", pa.bool_(), nullable=False))
    return pa.schema(fields)


def raw_schema():
    """The exact Arrow schema of ``raw.parquet`` (and of each of its parts)."""
    pa = _pa()
    fields = [pa.field("episode_id", pa.int32(), nullable=False), pa.field("tick", pa.int32(), nullable=False)]
    units = {"x_m": "m", "y_m": "m", "z_m": "m", "spindle_rpm": "rpm"}
    for name in POSE_COLUMNS:
        fields.append(pa.field(name, pa.float64(), nullable=False, metadata={"unit": units.get(name, "1")}))
    for name in FORCE_COLUMNS + GUIDANCE_COLUMNS:
        fields.append(pa.field(name, pa.float64(), nullable=False, metadata={"unit": "N"}))
    return pa.schema(fields)


@dataclass
class RawPart:
    """One file of the 1 kHz stream for :func:`write_dataset`: new bytes to write, or (``data``
    None) a part the folder being replaced already holds, which is hard-linked, not rewritten."""

    name: str
    rows: int
    sha256: str
    data: bytes | None = None


@dataclass
class EpisodeData:
    """One episode as numpy arrays (SI units)."""

    episode_id: int
    subject_id: str
    skill: str
    attempt: int
    times_s: npt.NDArray[np.float64]
    """(T,) record times (s)."""
    features: npt.NDArray[np.float64]
    """(T, 9) features in :data:`dhg.core.features.FEATURE_NAMES` order."""
    drill_on: npt.NDArray[np.bool_]
    """(T,) whether the drill ran."""
    metrics: dict[str, Any] = field(default_factory=dict)
    """Skill metrics from the card."""
    best_of_subject: bool = False
    """Whether this is the subject's best attempt (as the paper selected)."""


@dataclass
class Dataset:
    """A loaded, validated dataset."""

    path: Path
    card: dict[str, Any]
    episodes: list[EpisodeData]

    @property
    def n_records(self) -> int:
        """Total records."""
        return sum(len(e.times_s) for e in self.episodes)

    def select(self, skill: str | None = None, best_only: bool = False) -> list[EpisodeData]:
        """Episodes of one skill (``"expert"``/``"novice"``), optionally each subject's best only."""
        return [
            e for e in self.episodes if (skill is None or e.skill == skill) and (e.best_of_subject or not best_only)
        ]


def _sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for chunk in iter(lambda: fh.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


@dataclass
class EpisodeInput:
    """What the writer needs of an episode (the virtual surgeons' and the recorder's common form)."""

    subject_id: str
    skill: str
    attempt: int
    records: npt.NDArray[np.float64]
    """(M, 11): time, nine features, drill_on."""
    metrics: dict[str, Any] = field(default_factory=dict)
    style: dict[str, Any] = field(default_factory=dict)
    best_of_subject: bool = False
    raw_poses: npt.NDArray[np.float64] | None = None
    raw_forces_n: npt.NDArray[np.float64] | None = None


def write_dataset(
    out_dir: str | os.PathLike[str],
    episodes: Sequence[EpisodeInput],
    card_extra: dict[str, Any],
    overwrite: bool = False,
    raw_parts: Sequence[RawPart] = (),
) -> Path:
    """Writes a dataset folder atomically: everything goes to a temporary folder beside it, is
    flushed to disk, and only then replaces ``out_dir`` in one atomic swap, so ``out_dir`` holds
    the whole old dataset or the whole new one at every moment. ``card_extra`` adds the volume,
    path and generator sections of the card. The 1 kHz stream comes from the episodes'
    ``raw_poses`` (one ``raw.parquet``) or, for a recording, from ``raw_parts``."""
    import pyarrow.parquet as pq

    out = Path(out_dir)
    if out.exists() and any(out.iterdir()) and not overwrite:
        raise DatasetError(f"{out} exists and is not empty (pass overwrite to replace it)")
    if any(ep.raw_poses is not None for ep in episodes) and raw_parts:
        raise DatasetError("give the 1 kHz stream as the episodes' raw_poses or as raw_parts, not both")
    table = _records_table(episodes)  # checks every episode before anything is written
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.", dir=out.parent))
    umask = os.umask(0)
    os.umask(umask)
    os.chmod(tmp, 0o777 & ~umask)  # mkdtemp makes it private; the dataset should not be
    try:
        # pyarrow's defaults: the file's SHA-256 names a model's training data (dhg train), so the
        # same records must keep giving the same bytes with the pinned pyarrow (docs/model.md).
        pq.write_table(table, tmp / RECORDS_FILE)
        files = {RECORDS_FILE: {"rows": table.num_rows, "sha256": _sha256(tmp / RECORDS_FILE)}}
        for part in raw_parts:
            _place_part(part, out, tmp)
            files[part.name] = {"rows": part.rows, "sha256": part.sha256}
        if any(ep.raw_poses is not None for ep in episodes):
            raw_table = _raw_table(episodes)
            pq.write_table(raw_table, tmp / RAW_FILE, **raw_parquet_options(raw_table.schema))
            files[RAW_FILE] = {"rows": raw_table.num_rows, "sha256": _sha256(tmp / RAW_FILE)}
        card = {
            "format": DATASET_FORMAT,
            "version": DATASET_VERSION,
            "sampling_rate_hz": round(1.0 / RECORD_PERIOD_S, 9),
            "features": [{"name": n, "unit": u} for n, u in zip(FEATURE_NAMES, FEATURE_UNITS, strict=True)],
            "layers": {str(int(layer)): layer.name.lower() for layer in Layer},
            "frame": "world frame LPS, metres; see docs/frames.md",
            **card_extra,
            "episodes": [_card_episode(eid, ep) for eid, ep in enumerate(episodes)],
            "files": files,
        }
        (tmp / CARD_FILE).write_text(json.dumps(card, indent=1))
        _fsync_tree(tmp)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    _install(tmp, out)
    return out


def _card_episode(eid: int, ep: EpisodeInput) -> dict[str, Any]:
    """An episode's entry in the dataset card."""
    return {
        "episode_id": eid,
        "subject_id": ep.subject_id,
        "skill": ep.skill,
        "attempt": int(ep.attempt),
        "records": len(ep.records),
        "best_of_subject": bool(ep.best_of_subject),
        "metrics": ep.metrics,
        "style": ep.style,
    }


def _records_table(episodes: Sequence[EpisodeInput]) -> Any:
    """The episodes' 10 Hz records as one Arrow table of :func:`records_schema`, built from numpy
    columns (no Python list per value); refuses records of the wrong shape or not finite."""
    pa = _pa()
    blocks = []
    for eid, ep in enumerate(episodes):
        r = np.asarray(ep.records, dtype=np.float64)
        if r.ndim != 2 or r.shape[1] != 11:
            raise DatasetError(f"episode {eid}: records must be (M, 11), got {r.shape}")
        if not np.all(np.isfinite(r)):
            raise DatasetError(f"episode {eid}: records contain NaN or infinite values")
        blocks.append(r)
    r = np.concatenate(blocks) if blocks else np.zeros((0, 11))
    counts = [len(b) for b in blocks]
    episode_of_row = np.repeat(np.arange(len(blocks), dtype=np.int32), counts)

    def per_episode(values: list[Any], kind: Any) -> Any:
        # One value per episode, taken for each of its records.
        return pa.array(values, kind).take(pa.array(episode_of_row))

    schema = records_schema()
    cols = [
        pa.array(episode_of_row, pa.int32()),
        per_episode([ep.subject_id for ep in episodes], pa.string()),
        per_episode([ep.skill for ep in episodes], pa.string()),
        pa.array(np.repeat(np.array([int(ep.attempt) for ep in episodes], dtype=np.int32), counts), pa.int32()),
        pa.array(r[:, 0]),
    ]
    for i, name in enumerate(FEATURE_NAMES):
        col = r[:, 1 + i]
        cols.append(pa.array(col.astype(np.int8)) if name == "layer" else pa.array(col))
    cols.append(pa.array(r[:, 10] > 0.5))
    return pa.Table.from_arrays(cols, schema=schema)


def _raw_table(episodes: Sequence[EpisodeInput]) -> Any:
    """The episodes' 1 kHz streams (``raw_poses``, ``raw_forces_n``) as one Arrow table of
    :func:`raw_schema`, from numpy columns; a virtual surgeon drills without guidance (zeros)."""
    pa = _pa()
    kept = [
        (eid, np.asarray(ep.raw_poses), np.asarray(ep.raw_forces_n))
        for eid, ep in enumerate(episodes)
        if ep.raw_poses is not None and ep.raw_forces_n is not None
    ]
    poses = np.concatenate([np.zeros((0, len(POSE_COLUMNS)))] + [p for _, p, _ in kept])
    forces = np.concatenate([np.zeros((0, len(FORCE_COLUMNS)))] + [f for _, _, f in kept])
    counts = [len(p) for _, p, _ in kept]
    cols = [
        pa.array(np.repeat(np.array([eid for eid, _, _ in kept], dtype=np.int32), counts), pa.int32()),
        pa.array(np.concatenate([np.zeros(0, np.int32)] + [np.arange(n, dtype=np.int32) for n in counts])),
    ]
    cols += [pa.array(poses[:, i]) for i in range(len(POSE_COLUMNS))]
    cols += [pa.array(forces[:, i]) for i in range(len(FORCE_COLUMNS))]
    cols += [pa.array(np.zeros(len(poses))) for _ in GUIDANCE_COLUMNS]
    return pa.Table.from_arrays(cols, schema=raw_schema())


def _place_part(part: RawPart, out: Path, tmp: Path) -> None:
    """Puts one raw part into the folder being built: its new bytes, or a hard link to the same
    (unchanged) part in the folder it replaces, so a long recording never rewrites old parts."""
    dest = tmp / part.name
    if part.data is not None:
        dest.write_bytes(part.data)
        return
    src = out / part.name
    if not src.is_file():
        raise DatasetError(f"{src}: the raw part to keep is missing")
    try:
        os.link(src, dest)
    except OSError:  # a file system without hard links: copy it
        shutil.copyfile(src, dest)


def volume_card(volume: Any) -> dict[str, Any]:
    """A dataset card's ``volume`` (a :class:`dhg.core.volume.Volume`): where it came from (its
    ``meta``: phantom seed and voxel size, or the CT file), its shape (z, y, x) and spacing (m)."""
    return {k: v for k, v in volume.meta.items() if k != "planned_path"} | {
        "shape_zyx": list(volume.shape),
        "spacing_m": list(volume.spacing_m),
    }


def raw_parquet_options(schema: Any) -> dict[str, Any]:
    """How the 1 kHz stream's Parquet files are written (``pyarrow.parquet.write_table`` keywords):
    zstd, each float column ``BYTE_STREAM_SPLIT`` (the bytes of its values regrouped by position,
    so that the repeating sign, exponent and high mantissa bytes of a smooth signal compress) and
    each integer column ``DELTA_BINARY_PACKED`` (consecutive ticks cost a few bits). Both are
    lossless standard Parquet encodings (pyarrow reads them; another reader needs the two); other
    columns are plain. Against pyarrow's defaults (snappy, dictionaries) the stream takes 43 % of
    the bytes and is written 4× faster (decision 0037). ``records.parquet`` keeps the defaults
    (its SHA-256 names a model's training data)."""
    pa = _pa()
    encoding = {}
    for f in schema:
        if pa.types.is_floating(f.type):
            encoding[f.name] = "BYTE_STREAM_SPLIT"
        elif pa.types.is_integer(f.type):
            encoding[f.name] = "DELTA_BINARY_PACKED"
    return {"compression": "zstd", "use_dictionary": False, "column_encoding": encoding}


def raw_parquet_bytes(table: Any) -> bytes:
    """A table of the 1 kHz stream as the bytes of a Parquet file (:func:`raw_parquet_options`)."""
    import pyarrow.parquet as pq

    sink = _pa().BufferOutputStream()
    pq.write_table(table, sink, **raw_parquet_options(table.schema))
    return bytes(sink.getvalue().to_pybytes())


def _fsync_tree(folder: Path) -> None:
    """Flushes a folder's files and the folder itself to disk (a power cut keeps them)."""
    for f in folder.iterdir():
        with open(f, "rb") as fh:
            os.fsync(fh.fileno())
    _fsync_dir(folder)


def _fsync_dir(folder: Path) -> None:
    fd = os.open(folder, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def _exchange(a: Path, b: Path) -> bool:
    """Swaps two paths in one atomic step (Linux ``renameat2(RENAME_EXCHANGE)``). False where
    the platform or file system cannot; the paths are then untouched."""
    if not sys.platform.startswith("linux"):
        return False
    try:
        fn = ctypes.CDLL(None, use_errno=True).renameat2
    except (OSError, AttributeError):
        return False  # glibc < 2.28, or another libc
    fn.argtypes = [ctypes.c_int, ctypes.c_char_p, ctypes.c_int, ctypes.c_char_p, ctypes.c_uint]
    at_fdcwd, rename_exchange = -100, 2
    if fn(at_fdcwd, os.fsencode(a), at_fdcwd, os.fsencode(b), rename_exchange) == 0:
        return True
    err = ctypes.get_errno()
    if err in (errno.ENOSYS, errno.EINVAL, errno.EOPNOTSUPP, errno.EXDEV):
        return False
    raise OSError(err, os.strerror(err), str(b))


def _install(tmp: Path, out: Path) -> None:
    """Puts the complete folder ``tmp`` at ``out``. ``out`` always holds a whole dataset, old or
    new: an existing one is swapped out in one atomic step, then deleted. Where no atomic swap
    exists, ``out`` is missing for the moment between two renames, and a crash there leaves the
    new dataset complete in ``tmp`` (which :func:`load_dataset` then points to)."""
    if not out.exists():
        os.replace(tmp, out)
    elif _exchange(tmp, out):
        shutil.rmtree(tmp, ignore_errors=True)  # tmp now holds the old dataset
    else:
        old = tmp.with_name(tmp.name + ".old")
        os.replace(out, old)
        os.replace(tmp, out)
        shutil.rmtree(old, ignore_errors=True)
    _fsync_dir(out.parent)


def _fail(path: Path, what: str) -> DatasetError:
    return DatasetError(f"{path}: {what}")


def _read_listed(path: Path, expected: dict[str, Any], verify_hashes: bool) -> Any:
    """A Parquet file of the folder as an Arrow table, after checking it against its entry in the
    card's ``files``: the SHA-256 (unless ``verify_hashes`` is off), that it parses, and its rows."""
    pa = _pa()
    import pyarrow.parquet as pq

    if verify_hashes and expected.get("sha256") != _sha256(path):
        raise _fail(path, "SHA-256 differs from the card: the file is truncated, corrupt or was changed")
    try:
        table = pq.read_table(path)
    except (OSError, pa.ArrowException) as exc:
        raise _fail(path, f"unreadable Parquet ({exc})") from None
    if table.num_rows != expected.get("rows"):
        raise _fail(path, f"{table.num_rows} rows, the card says {expected.get('rows')}")
    return table


def _read_card(root: Path) -> dict[str, Any]:
    """The dataset card of the folder ``root``, after checking its format, version, features
    (names, order and units) and sampling rate."""
    card_path = root / CARD_FILE
    if not card_path.is_file():
        leftovers = sorted(p.name for p in root.parent.glob(f".{root.name}.*") if (p / CARD_FILE).is_file())
        hint = f" ({', '.join(leftovers)} beside it hold an interrupted rewrite)" if leftovers else ""
        raise _fail(root, f"no {CARD_FILE}: not a DHG dataset folder{hint}")
    try:
        card = json.loads(card_path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise _fail(card_path, f"unreadable dataset card ({exc})") from None
    if card.get("format") != DATASET_FORMAT:
        raise _fail(card_path, f"format {card.get('format')!r}, expected {DATASET_FORMAT!r}")
    if card.get("version") != DATASET_VERSION:
        raise _fail(card_path, f"version {card.get('version')} is not supported (this DHG reads {DATASET_VERSION})")
    names = [f.get("name") for f in card.get("features", [])]
    units = [f.get("unit") for f in card.get("features", [])]
    if names != list(FEATURE_NAMES):
        raise _fail(card_path, f"feature order {names} differs from {list(FEATURE_NAMES)}")
    if units != list(FEATURE_UNITS):
        raise _fail(card_path, f"feature units {units} differ from {list(FEATURE_UNITS)}")
    if abs(float(card.get("sampling_rate_hz", 0)) - 1.0 / RECORD_PERIOD_S) > 1e-6:
        raise _fail(card_path, f"sampling rate {card.get('sampling_rate_hz')} Hz, expected {1.0 / RECORD_PERIOD_S}")
    return card


def _check_records_schema(rec_path: Path, table: Any) -> None:
    """Refuses a records table whose columns, types or units differ from :func:`records_schema`."""
    want = records_schema()
    if table.schema.names != want.names:
        raise _fail(rec_path, f"columns {table.schema.names} differ from {want.names}")
    for f in want:
        got = table.schema.field(f.name)
        if got.type != f.type:
            raise _fail(rec_path, f"column {f.name!r} has type {got.type}, expected {f.type}")
        if f.metadata and (got.metadata or {}).get(b"unit") != f.metadata.get(b"unit"):
            raise _fail(
                rec_path,
                f"column {f.name!r} has unit {(got.metadata or {}).get(b'unit')}, expected {f.metadata[b'unit']}",
            )


def _episodes(rec_path: Path, cols: dict[str, list[Any]], card: dict[str, Any]) -> list[EpisodeData]:
    """The episodes of the records' columns ``cols``, each checked against its entry in the card:
    contiguous rows, increasing times, finite values and the row count the card gives."""
    ids = np.asarray(cols["episode_id"], dtype=np.int64)
    starts = np.flatnonzero(np.r_[True, ids[1:] != ids[:-1]]) if len(ids) else np.empty(0, int)
    if len(np.unique(ids)) != len(starts):
        raise _fail(rec_path, "episodes are interleaved: an episode's rows must be contiguous")
    times = np.asarray(cols["time_s"], dtype=np.float64)
    feats = np.column_stack([np.asarray(cols[n], dtype=np.float64) for n in FEATURE_NAMES])
    if not np.all(np.isfinite(feats)) or not np.all(np.isfinite(times)):
        raise _fail(rec_path, "NaN or infinite values in the records")
    drill = np.asarray(cols["drill_on"], dtype=bool)
    card_eps = {int(e["episode_id"]): e for e in card.get("episodes", [])}
    episodes = []
    bounds = [*starts.tolist(), len(ids)]
    for lo, hi in zip(bounds[:-1], bounds[1:], strict=True):
        eid = int(ids[lo])
        if np.any(np.diff(times[lo:hi]) <= 0):
            raise _fail(rec_path, f"episode {eid}: record times are not increasing")
        meta = card_eps.get(eid)
        if meta is None or int(meta.get("records", -1)) != hi - lo:
            raise _fail(rec_path, f"episode {eid}: {hi - lo} rows do not match the card")
        episodes.append(
            EpisodeData(
                episode_id=eid,
                subject_id=str(cols["subject_id"][lo]),
                skill=str(cols["skill"][lo]),
                attempt=int(cols["attempt"][lo]),
                times_s=times[lo:hi],
                features=feats[lo:hi],
                drill_on=drill[lo:hi],
                metrics=dict(meta.get("metrics", {})),
                best_of_subject=bool(meta.get("best_of_subject", False)),
            )
        )
    if len(episodes) != len(card_eps):
        raise _fail(rec_path, f"{len(episodes)} episodes in the records, {len(card_eps)} in the card")
    return episodes


def load_dataset(path: str | os.PathLike[str], verify_hashes: bool = True) -> Dataset:
    """Loads and validates a dataset folder.

    Raises:
        DatasetError: missing files, a card of another format/version, feature order or units that
            differ from :mod:`dhg.core.features`, a records table whose columns or types differ from
            :func:`records_schema`, rows that disagree with the card, interleaved or unordered
            episodes, or a file whose hash does not match the card (truncated or corrupt).
    """

    root = Path(path)
    card = _read_card(root)
    rec_path = root / RECORDS_FILE
    if not rec_path.is_file():
        raise _fail(root, f"no {RECORDS_FILE}")
    table = _read_listed(rec_path, card.get("files", {}).get(RECORDS_FILE, {}), verify_hashes)
    _check_records_schema(rec_path, table)
    return Dataset(root, card, _episodes(rec_path, table.to_pydict(), card))


def raw_files(card: dict[str, Any]) -> list[str]:
    """The names of a dataset's raw stream files in order: ``[raw.parquet]``, the parts
    ``raw-00000.parquet`` ... of a recording that stopped before joining them, or none."""
    import re

    return sorted(n for n in card.get("files", {}) if n == RAW_FILE or re.fullmatch(r"raw-\d{5}\.parquet", n))


def load_raw(path: str | os.PathLike[str] | Dataset, verify_hashes: bool = True) -> Any:
    """The 1 kHz stream of a dataset as one Arrow table (:func:`raw_schema`), or ``None`` when the
    dataset has none. Parts are read in order and joined. Files written before the guidance
    columns existed read with zero guidance.

    Raises:
        DatasetError: whatever :func:`load_dataset` refuses; a raw file that is missing, changed
            (SHA-256), unreadable, of another schema or row count than the card says; parts that
            are not numbered 0, 1, ... without a gap, or mixed with ``raw.parquet``; rows of an
            episode the records do not have; an episode's rows split up or its ticks not
            increasing; NaN or infinite values.
    """
    pa = _pa()

    ds = path if isinstance(path, Dataset) else load_dataset(path, verify_hashes)
    names = raw_files(ds.card)
    if not names:
        return None
    if RAW_FILE in names and len(names) > 1:
        raise _fail(ds.path, f"both {RAW_FILE} and raw parts are listed in the card")
    if RAW_FILE not in names and names != [RAW_PART_FILE.format(i) for i in range(len(names))]:
        raise _fail(ds.path, f"raw parts {names} are not numbered 0, 1, ... without a gap")
    want = raw_schema()
    tables = []
    for name in names:
        f = ds.path / name
        expected = ds.card["files"][name]
        if not f.is_file():
            raise _fail(f, "missing (the card lists it)")
        t = _read_listed(f, expected, verify_hashes)
        if t.schema.names == [n for n in want.names if n not in GUIDANCE_COLUMNS]:
            for name_g in GUIDANCE_COLUMNS:  # written before guidance was recorded
                t = t.append_column(want.field(name_g), pa.array(np.zeros(t.num_rows)))
        if t.schema.names != want.names:
            raise _fail(f, f"columns {t.schema.names} differ from {want.names}")
        wrong = [f"{n} is {t.schema.field(n).type}" for n in want.names if t.schema.field(n).type != want.field(n).type]
        if wrong:
            raise _fail(f, f"column types differ from the format: {', '.join(wrong)}")
        tables.append(t.cast(want))
    table = pa.concat_tables(tables)
    ids = table.column("episode_id").to_numpy()
    ticks = table.column("tick").to_numpy()
    known = {e.episode_id for e in ds.episodes}
    starts = np.flatnonzero(np.r_[True, ids[1:] != ids[:-1]]) if len(ids) else np.empty(0, int)
    if len(np.unique(ids)) != len(starts):
        raise _fail(ds.path, "raw stream: an episode's rows are split up (they must be contiguous)")
    unknown = set(np.unique(ids).tolist()) - known
    if unknown:
        raise _fail(ds.path, f"raw stream: rows of episodes {sorted(unknown)} that the records do not have")
    same = ids[1:] == ids[:-1]
    if np.any(np.diff(ticks)[same] <= 0):
        raise _fail(ds.path, "raw stream: ticks do not increase within an episode")
    values = np.column_stack([table.column(n).to_numpy() for n in want.names[2:]]) if len(ids) else np.empty((0, 1))
    if not np.all(np.isfinite(values)):
        raise _fail(ds.path, "raw stream: NaN or infinite values")
    return table
