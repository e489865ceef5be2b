"""What a session recorder keeps between flushes, without a server: its states held compactly,
and an attempt's skill metrics computed again only when the attempt changed."""

from __future__ import annotations

import numpy as np
import pytest

from dhg.core import protocol
from dhg.core.features import RECORD_INDEX, RECORD_PERIOD_S
from dhg.core.path import PlannedPath, TaskRules
from dhg.core.skill import skill_metrics
from dhg.data.dataset import load_dataset
from dhg.live import session_recorder
from dhg.live.recorder import SessionRecorder
from dhg.live.trainee import state_records
from support import AnsweringSession, attempt_states, state_sample


def _recorder(out, attempts: list[list[bytes]]) -> SessionRecorder:
    rec = SessionRecorder("tcp/127.0.0.1:9", "s", out, zenoh_session=AnsweringSession("s"))
    for attempt in attempts:
        for payload in attempt:  # each attempt restarts the session's clock: a new episode
            rec.on_sample("state", state_sample(payload))
    return rec


def test_an_ended_attempt_is_measured_once_and_the_dataset_is_a_fresh_recorders(tmp_path, monkeypatch):
    """A flush used to compute every attempt's skill metrics again from its states, so a long
    recording's flushes grew with it; now only an attempt that changed is. What is written is
    what a recorder that never flushed before writes, and the records are the states' records."""
    attempts = [attempt_states(40, seed=s) for s in range(3)]
    calls: list[int] = []
    measured = session_recorder.skill_metrics
    monkeypatch.setattr(
        session_recorder,
        "skill_metrics",
        lambda records, *a, **k: calls.append(len(records)) or measured(records, *a, **k),
    )
    rec = _recorder(tmp_path / "long", attempts)
    assert rec.flush()
    assert calls == [40, 40, 40]
    # One more state of the last attempt: only that attempt is measured again.
    more = attempt_states(41, seed=2)[-1]
    rec.on_sample("state", state_sample(more))
    calls.clear()
    assert rec.flush()
    assert calls == [41], "the ended attempts were measured again"
    assert not rec.flush(), "nothing new: no write"

    fresh = _recorder(tmp_path / "fresh", [*attempts[:2], [*attempts[2], more]])
    assert fresh.flush()
    got, want = load_dataset(tmp_path / "long"), load_dataset(tmp_path / "fresh")
    assert len(got.episodes) == 3
    decoded = [[protocol.decode("state", p) for p in a] for a in (*attempts[:2], [*attempts[2], more])]
    path = PlannedPath(np.zeros(3), np.array([0.0, 0.0, 0.06]))  # AnsweringSession's
    for a, b, states in zip(got.episodes, want.episodes, decoded, strict=True):
        assert a.metrics == b.metrics
        # What the recorder computed from the decoded messages before it kept them compactly.
        records = state_records(states)
        np.testing.assert_array_equal(np.column_stack([a.times_s, a.features, a.drill_on]), records)
        expected = skill_metrics(
            records,
            path,
            TaskRules(),
            final_tip_m=records[-1, RECORD_INDEX["tip_x_m"] : RECORD_INDEX["tip_x_m"] + 3],
            drilling_s=float(np.count_nonzero(records[:, RECORD_INDEX["drill_on"]] > 0.5)) * RECORD_PERIOD_S,
            plunge_depth_m=max(s["plunge_depth_m"] for s in states),
            peak_temperature_c=states[-1]["peak_temperature_c"],
            time_above_47_s=states[-1]["time_above_47_s"],
        )
        expected["guidance_gain"] = states[-1]["guidance_gain"]
        assert a.metrics == pytest.approx(expected, rel=1e-12)
    rec.close()
    fresh.close()


def test_a_recorder_holds_a_state_in_far_less_than_its_decoded_message(tmp_path):
    """A state used to be kept as its decoded message (a dict of about 1 KB); now as 15 float64
    (twice that once a flush keeps its attempt's states: not measured here)."""
    import tracemalloc

    attempt = attempt_states(2000)
    rec = SessionRecorder("tcp/127.0.0.1:9", "s", tmp_path / "ds", zenoh_session=AnsweringSession("s"))
    rec.on_sample("state", state_sample(attempt[0]))
    tracemalloc.start()
    try:
        base = tracemalloc.get_traced_memory()[0]
        for payload in attempt[1:]:
            rec.on_sample("state", state_sample(payload))
        per_state = (tracemalloc.get_traced_memory()[0] - base) / (len(attempt) - 1)
    finally:
        tracemalloc.stop()
    assert rec.records == len(attempt)
    assert per_state < 200, f"{per_state:.0f} bytes a state"
    rec.close()
