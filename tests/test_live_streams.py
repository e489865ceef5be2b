"""The recorder's stream handling: episodes shared by the force and state streams, forces paired
with their poses, and the 1 kHz stream's parts as the dataset loader reads them."""

from __future__ import annotations

import json

import numpy as np
import pytest

from dhg.data.dataset import DatasetError, EpisodeInput, load_dataset, load_raw, write_dataset
from dhg.live.streams import RAW_COLUMNS, EpisodeSplitter, RawParts, RecordingEpisode, force_jerk
from support import column_encodings, rewrite_dataset_file


def _ids(split: EpisodeSplitter, stream: str, ticks: list[int]) -> list[int]:
    return [split.episodes.index(split.place(stream, t)) for t in ticks]  # type: ignore[arg-type]


def test_both_streams_land_in_the_same_episodes_whichever_sees_a_reset_first():
    s = EpisodeSplitter()
    assert _ids(s, "force", [0, 1, 2, 99, 100, 199]) == [0] * 6
    assert _ids(s, "state", [99, 199]) == [0, 0]
    # The states see the reset first (forces are late): the state opens episode 1 ...
    assert _ids(s, "state", [99]) == [1]
    # ... and the forces join it when they reach the same reset.
    assert _ids(s, "force", [200, 0, 1, 99]) == [0, 1, 1, 1]
    # Now the forces see the next reset first; a state of the old episode that comes late stays there.
    assert _ids(s, "force", [0, 5]) == [2, 2]
    assert _ids(s, "state", [199, 99]) == [1, 2]
    assert len(s.episodes) == 3


def test_an_attempt_too_short_for_a_record_is_passed_over_by_the_states():
    s = EpisodeSplitter()
    _ids(s, "force", list(range(300)))
    _ids(s, "state", [99, 199, 299])
    assert _ids(s, "force", [0, 30]) == [1, 1]  # reset, then reset again after 31 ms: no state
    assert _ids(s, "force", [0, 120]) == [2, 2]
    assert _ids(s, "state", [99]) == [2]  # not the short episode 1
    assert len(s.episodes[1].records) == 0 and s.at("state") == 2


def test_a_late_state_of_an_episode_stays_with_it_even_past_a_few_dropped_forces():
    s = EpisodeSplitter()
    _ids(s, "force", list(range(185)))  # forces 185..199 dropped in transport
    _ids(s, "state", [99])
    assert _ids(s, "force", [0]) == [1]
    assert _ids(s, "state", [199]) == [0]  # 15 ticks past the last force: still episode 0


def _rows(ticks: np.ndarray, force: np.ndarray) -> np.ndarray:
    rows = np.zeros((len(ticks), RAW_COLUMNS))
    rows[:, 0] = ticks
    rows[:, 1:4] = ticks[:, None] * 1e-6  # the burr moves 1 um per tick
    rows[:, 4] = 1.0  # identity quaternion
    rows[:, 10:13] = force
    return rows


def test_force_jerk_counts_only_consecutive_ticks():
    ep = RecordingEpisode()
    ticks = np.array([0, 1, 2, 10, 11])
    force = np.zeros((5, 3))
    force[:, 2] = [0.0, 0.001, 0.002, 1.0, 1.001]  # 1 N/s, and a jump across the gap
    force_jerk(ep, _rows(ticks[:3], force[:3]))
    force_jerk(ep, _rows(ticks[3:], force[3:]))  # in two flushes: the first's last row carries over
    assert ep.jerk_count == 3
    assert np.sqrt(ep.jerk_sum / ep.jerk_count) == pytest.approx(1.0)


def _records(n: int) -> np.ndarray:
    r = np.zeros((n, 11))
    r[:, 0] = 0.1 * np.arange(1, n + 1)
    r[:, 8] = 20.0  # temperature (°C)
    return r


def _write(out, parts, episodes=2):
    eps = [EpisodeInput("p0", "expert", a, _records(3)) for a in range(episodes)]
    write_dataset(out, eps, {"generator": {"name": "test"}}, overwrite=True, raw_parts=parts)


def test_raw_parts_are_linked_once_closed_and_joined_at_the_end(tmp_path):
    out = tmp_path / "rec"
    parts = RawParts(part_rows=5)
    parts.add(0, _rows(np.arange(3), np.ones((3, 3))))
    p1 = parts.parts()
    _write(out, p1)
    parts.written(p1)
    assert [p.name for p in p1] == ["raw-00000.parquet"] and load_raw(out).num_rows == 3
    parts.add(0, _rows(np.arange(3, 6), np.ones((3, 3))))
    p2 = parts.parts()
    _write(out, p2)
    parts.written(p2)  # 6 rows >= 5: part 0 is closed
    inode = (out / "raw-00000.parquet").stat().st_ino
    parts.add(1, _rows(np.arange(4), 2 * np.ones((4, 3))))
    p3 = parts.parts()
    assert [p.name for p in p3] == ["raw-00000.parquet", "raw-00001.parquet"] and p3[0].data is None
    _write(out, p3)
    parts.written(p3)
    assert (out / "raw-00000.parquet").stat().st_ino == inode, "a closed part is linked, not rewritten"
    t = load_raw(out)
    assert t.column("episode_id").to_pylist() == [0] * 6 + [1] * 4
    assert t.column("tick").to_pylist() == [*range(6), *range(4)]
    joined = parts.joined(out)
    _write(out, joined)
    card = json.loads((out / "card.json").read_text())
    assert sorted(card["files"]) == ["raw.parquet", "records.parquet"]
    t2 = load_raw(out)
    assert t2.equals(t)
    for name, (compressions, encodings) in column_encodings(out / "raw.parquet").items():  # decision 0037
        expected = "DELTA_BINARY_PACKED" if name in ("episode_id", "tick") else "BYTE_STREAM_SPLIT"
        assert compressions == {"ZSTD"} and expected in encodings and "RLE_DICTIONARY" not in encodings, name
    np.testing.assert_array_equal(t2.column("force_z_n").to_numpy(), [1.0] * 6 + [2.0] * 4)


def _parts_dataset(tmp_path):
    out = tmp_path / "rec"
    parts = RawParts(part_rows=2)
    for k in range(3):
        parts.add(0, _rows(np.arange(2 * k, 2 * k + 2), np.zeros((2, 3))))
        p = parts.parts()
        _write(out, p, episodes=1)
        parts.written(p)
    return out


def test_load_raw_refuses_a_missing_or_changed_part(tmp_path):
    out = _parts_dataset(tmp_path)
    assert load_raw(out).num_rows == 6
    (out / "raw-00001.parquet").write_bytes((out / "raw-00001.parquet").read_bytes()[:-8])
    with pytest.raises(DatasetError, match="raw-00001.parquet: SHA-256 differs"):
        load_raw(out)
    (out / "raw-00001.parquet").unlink()
    with pytest.raises(DatasetError, match="raw-00001.parquet: missing"):
        load_raw(out)


def test_load_raw_refuses_a_gap_in_the_parts_and_rows_of_unknown_episodes(tmp_path):
    out = _parts_dataset(tmp_path)
    card = json.loads((out / "card.json").read_text())
    card["files"]["raw-00004.parquet"] = card["files"].pop("raw-00002.parquet")
    (out / "card.json").write_text(json.dumps(card))
    with pytest.raises(DatasetError, match="not numbered 0, 1"):
        load_raw(out)
    other = tmp_path / "other"
    parts = RawParts()
    parts.add(3, _rows(np.arange(2), np.zeros((2, 3))))
    _write(other, parts.parts(), episodes=1)
    with pytest.raises(DatasetError, match=r"episodes \[3\] that the records do not have"):
        load_raw(other)


def test_load_raw_refuses_ticks_that_go_back_within_an_episode(tmp_path):
    out = tmp_path / "rec"
    parts = RawParts()
    parts.add(0, _rows(np.array([0, 1, 1]), np.zeros((3, 3))))
    _write(out, parts.parts(), episodes=1)
    assert len(load_dataset(out).episodes) == 1
    with pytest.raises(DatasetError, match="ticks do not increase"):
        load_raw(out)


def test_load_raw_names_the_columns_that_differ(tmp_path):
    import pyarrow as pa
    import pyarrow.parquet as pq

    out = _parts_dataset(tmp_path)
    part = out / "raw-00000.parquet"
    t = pq.read_table(part)
    rewrite_dataset_file(out, part.name, t.set_column(1, "tick", pa.array(t.column("tick").to_numpy().astype("int64"))))
    with pytest.raises(DatasetError, match="column types differ from the format: tick is int64"):
        load_raw(out)


class _Sample:
    """What the recorder reads of a Zenoh sample."""

    def __init__(self, payload: bytes) -> None:
        self.payload = self
        self._bytes = payload

    def to_bytes(self) -> bytes:
        return self._bytes


class _NoServer:
    def get(self, *args, **kwargs):
        raise ConnectionError("no server in this test")


def _ticks(first_tick: int, n: int, pose_seq: int = 5, fz: float = 1.5) -> bytes:
    """A ``ticks`` batch as the server sends it (rows built from the layout, not from the decoder)."""
    from dhg.core import protocol

    rows = np.zeros(n, dtype=protocol.TICK_ROW)
    rows["tick"] = np.arange(first_tick, first_tick + n)
    rows["pose_seq"] = pose_seq
    rows["flags"] = protocol.FLAGS["drill_on"]
    rows["position_m"] = [0.01, 0.02, 0.03]
    rows["orientation_wxyz"] = [1.0, 0.0, 0.0, 0.0]
    rows["spindle_rpm"] = 1250.0
    rows["force_n"] = [0.0, 0.0, fz]
    head = protocol.encode("ticks", rows=n, first_tick=first_tick)
    return head + rows.tobytes()


def test_ticks_before_their_episodes_first_record_wait_for_it_and_a_reset_splits_a_batch(tmp_path):
    from dhg.core import protocol
    from dhg.live.recorder import SessionRecorder

    rec = SessionRecorder((), "s1", tmp_path / "rec", raw=True, zenoh_session=_NoServer())
    rec.on_sample("ticks", _Sample(_ticks(1, 100)))  # ticks 0..99, before the first record
    rec.flush()
    assert load_raw(tmp_path / "rec") is None  # no record yet: the rows wait for it
    state = protocol.encode("state", record_seq=1, time_s=0.1, features=[0.0] * 8 + [37.0])
    rec.on_sample("state", _Sample(state))
    assert rec.flush()
    raw = load_raw(tmp_path / "rec")
    assert raw.column("tick").to_pylist() == list(range(100)) and raw.column("x_m").to_pylist()[0] == 0.01
    assert raw.column("force_z_n").to_pylist() == [1.5] * 100 and raw.column("drill_on").to_pylist()[0] == 1.0
    # a reset in the middle of a batch: ticks 101..150, then 1..50 of the next attempt
    batch = _ticks(101, 50)
    second = _ticks(1, 50, fz=2.5)
    head = protocol.encode("ticks", rows=100, first_tick=101)
    rec.on_sample("ticks", _Sample(head + batch[24:] + second[24:]))
    rec.on_sample("state", _Sample(protocol.encode("state", record_seq=1, time_s=0.05, features=[0.0] * 8 + [37.0])))
    assert rec.flush(final=True)
    ds = load_dataset(tmp_path / "rec")
    raw = load_raw(tmp_path / "rec")
    ids, ticks = raw.column("episode_id").to_numpy(), raw.column("tick").to_numpy()
    assert len(ds.episodes) == 2 and list(ticks[ids == 1]) == list(range(50))
    assert set(raw.column("force_z_n").to_numpy()[ids == 1]) == {2.5}
    assert rec.decode_errors == 0 and ds.card["generator"]["raw"]["lost_batches"] == 0


def test_a_bad_ticks_batch_is_counted_and_left_out(tmp_path):
    from dhg.core import protocol
    from dhg.live.recorder import SessionRecorder

    rec = SessionRecorder((), "s1", tmp_path / "rec", raw=True, zenoh_session=_NoServer())
    good = _ticks(1, 10)
    nan = bytearray(good)
    nan[24 + 16 : 24 + 24] = np.float64(np.nan).tobytes()  # row 0's x
    for bad in (good[:-1], bytes(nan), good[:1] + b"\x09" + good[2:]):
        rec.on_sample("ticks", _Sample(bytes(bad)))
    with pytest.raises(ValueError, match="NaN or infinite position_m"):
        protocol.decode_ticks(bytes(nan))
    assert rec.decode_errors == 3 and not rec._split.episodes


def test_a_pages_timeline_holds_what_the_hand_felt_at_each_record():
    """The page's force plot: the device force on the hand and its guidance share as they were at
    each record (the newest view/force then), not the bone's feedback alone, nor the newest
    guidance message drawn flat across the 20 s."""
    from dhg.core import protocol
    from dhg.live.zenoh_config import open_zenoh, zenoh_config_json5
    from dhg.view.feed import SessionFeed
    from support import wait_until

    z = open_zenoh(zenoh_config_json5(mode="peer"))
    try:
        feed = SessionFeed(z, "feed-1", prefix="feedtest")
        keys = protocol.keys("feedtest", "feed-1")
        for k, (hand, share) in enumerate(((1.0, 0.0), (2.0, 0.5))):
            z.put(keys["view/force"], protocol.encode("force", force_n=(0.0, 0.0, hand), guidance_n=(0.0, share, 0.0)))
            wait_until(lambda k=k: feed.forces > k, 10.0, "the force")
            z.put(keys["state"], protocol.encode("state", record_seq=k + 1, time_s=0.1 * (k + 1)))
            wait_until(lambda k=k: feed.states > k, 10.0, "the state")
        got = [(s["hand_force_n"], s["guidance_share_n"]) for s in feed.timeline_states()]
        assert got == [(1.0, 0.0), (2.0, 0.5)], got
    finally:
        z.close()
