"""The client's force check (:class:`dhg.live.client.ForceGuard`) and the Python decoders, under
arbitrary input (hypothesis): nothing non-finite or above the device's limits is ever handed on."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st

from dhg.core import protocol
from dhg.core.errors import InvalidInputError
from dhg.core.session import DeviceProfile
from dhg.live.client import ForceGuard, all_finite

PEAK = DeviceProfile().peak_force_n
RATE = DeviceProfile().max_force_rate_n_per_s

anything = st.floats(allow_nan=True, allow_infinity=True, width=32)  # the wire carries f32
vec = st.tuples(anything, anything, anything)
plausible = st.floats(-2.0, 2.0)


def _force(force_n=(0.0, 0.0, 0.0), guidance_n=(0.0, 0.0, 0.0), **over) -> dict:
    m = protocol.decode("force", protocol.encode("force", force_n=force_n, guidance_n=guidance_n))
    return m | over


@settings(max_examples=400, deadline=None)
@given(st.lists(st.tuples(vec, vec, anything, st.integers(0, 5_000_000)), min_size=1, max_size=40))
def test_nothing_non_finite_or_over_the_limits_reaches_the_device(messages):
    guard = ForceGuard()
    now, last, first_t, travelled, n = 0, None, None, 0.0, 0
    for force, guidance, depth, gap_ns in messages:
        now += gap_ns
        out = guard.check(_force(force, guidance, depth_m=depth), now)
        if out is None:
            continue
        assert all_finite(out)
        assert math.hypot(*out["force_n"]) <= PEAK + 1e-9 and math.hypot(*out["guidance_n"]) <= PEAK + 1e-9
        if last is None:
            first_t = now
        else:  # a token bucket: the force travels at most a burst plus the rate limit times the time
            travelled += math.dist(out["force_n"], last)
            n += 1
            assert travelled <= guard.burst_n + RATE * (now - first_t) * 1e-9 + 2e-6 * n
        last = out["force_n"]


def test_the_guard_refuses_counts_and_slews():
    guard = ForceGuard()
    assert guard.check(_force((0.1, 0.0, 0.0)), 0) is not None
    assert guard.check(_force((math.nan, 0.0, 0.0)), 1_000_000) is None
    assert guard.check(_force(tip_m=(0.0, math.inf, 0.0)), 2_000_000) is None
    assert guard.check(_force((1e6, 0.0, 0.0)), 3_000_000) is None
    assert guard.check(_force(guidance_n=(0.0, 3.4, 0.0)), 4_000_000) is None
    assert guard.check(_force(layer=200), 4_500_000) is None  # no layer has id 200
    # A 3 N jolt 1 ms after a message: slewed to what the bucket holds (at most 5 ms of 200 N/s).
    out = guard.check(_force((3.1, 0.0, 0.0)), 5_000_000)
    assert out is not None and out["force_n"][0] == pytest.approx(0.1 + guard.burst_n)
    assert guard.rejected == {"non_finite": 2, "bad_layer": 1, "over_limit": 2, "rate_limited": 1}
    # The server's own stream (at most 0.2 N per 1 ms tick) passes untouched, however it is batched.
    guard = ForceGuard()
    f = 0.0
    for k in range(200):
        f += 0.2 if k < 15 else -0.2 if k < 30 else 0.0
        out = guard.check(_force((f, 0.0, 0.0)), 1_000_000 * k)
        assert out is not None and out["force_n"][0] == pytest.approx(f, abs=1e-6)
    assert guard.rejected["rate_limited"] == 0


@settings(max_examples=300, deadline=None)
@given(st.binary(max_size=200), st.sampled_from(sorted(protocol.LAYOUTS)))
def test_decoders_refuse_garbage_with_a_clear_error(payload, name):
    try:
        m = protocol.decode(name, payload)
    except InvalidInputError as exc:
        assert name in str(exc)
    else:
        assert len(payload) >= protocol.LAYOUTS[name].size and set(m) == {f[0] for f in protocol.LAYOUTS[name].fields}


@settings(max_examples=200, deadline=None)
@given(
    st.integers(0, 64),
    st.integers(0, 64),
    st.binary(max_size=64),
    st.integers(0, protocol.MAX_QUERY_WINDOWS + 1),
    st.permutations(range(3)),
)
@example(rows=3, cols=60, tail=b"", n=1, order=[0, 1, 2])  # 180 floats: what the fixed 20 x 9 window holds
@example(rows=20, cols=9, tail=b"", n=protocol.MAX_QUERY_WINDOWS, order=[0, 1, 2])
@example(rows=20, cols=9, tail=b"", n=3, order=[1, 0, 2])
def test_the_predict_decoder_takes_only_whole_windows_of_the_engines_shape_in_entry_order(rows, cols, tail, n, order):
    """A model query is 1 to MAX_QUERY_WINDOWS ``predict`` messages of 20 x 9 back to back, entry
    0, 1, …; anything else is refused with a message, never misread."""
    entries = [order[i] if i < 3 else i for i in range(n)]
    payload = (
        b"".join(
            protocol.encode("predict", window_seq=100 + i, rows=rows, cols=cols, entry=e, window=np.full(180, float(i)))
            for i, e in enumerate(entries)
        )
        + tail
    )
    try:
        seqs, windows = protocol.decode_predict(payload)
    except InvalidInputError as exc:
        assert "predict" in str(exc)
        good = 1 <= n <= protocol.MAX_QUERY_WINDOWS and not tail and (rows, cols) == (20, 9)
        assert not (good and entries == list(range(n)))
    else:
        assert (rows, cols, tail) == (20, 9, b"") and entries == list(range(n))
        assert list(seqs) == [100 + i for i in range(n)] and windows.shape == (n, 20, 9)
        assert all(np.all(windows[i] == i) for i in range(n))


class _Sample:
    def __init__(self, payload: bytes) -> None:
        self.payload = self
        self._b = payload

    def to_bytes(self) -> bytes:
        return self._b


_feature = st.floats(allow_nan=True, allow_infinity=True, width=32)
_state = st.one_of(
    st.binary(max_size=120),  # garbage
    st.tuples(
        st.floats(-1.0, 30.0) | st.sampled_from([math.nan, math.inf, 1e30]), st.lists(_feature, min_size=9, max_size=9)
    ),
)


@settings(max_examples=60, deadline=None)
@given(st.lists(_state, min_size=1, max_size=60))
def test_the_recorder_writes_only_possible_states_and_never_stops(messages):
    """Whatever arrives on a session's state key, the recorder keeps running, writes only
    finite states with a session clock, and counts every other message."""
    import tempfile
    from pathlib import Path

    from dhg.core.layers import Layer
    from dhg.data.dataset import load_dataset
    from dhg.live.recorder import MAX_SESSION_TIME_S, SessionRecorder, valid_message

    with tempfile.TemporaryDirectory() as tmp:
        rec = SessionRecorder((), "prop-1", Path(tmp) / "ds", zenoh_session=object())
        possible = 0
        for m in messages:
            if isinstance(m, bytes):
                payload = m
                try:  # garbage may happen to be a state
                    possible += valid_message("state", protocol.decode("state", m))
                except InvalidInputError:
                    pass
            else:
                t, feats = m
                payload = protocol.encode("state", time_s=t, features=feats)
                layer_ok = float(np.float32(feats[6])) in {float(v) for v in Layer}  # the layer feature
                possible += (
                    math.isfinite(t) and 0 <= t <= MAX_SESSION_TIME_S and all(map(math.isfinite, feats)) and layer_ok
                )
            rec._on_state(_Sample(payload))
        assert rec.decode_errors + rec.invalid_messages + possible == len(messages)
        wrote = rec.flush(final=True)
        assert wrote == (possible > 0)
        if wrote:
            for ep in load_dataset(Path(tmp) / "ds").episodes:
                assert all(map(math.isfinite, ep.features.ravel())) and ep.times_s.min() >= 0


def test_an_error_reply_becomes_the_class_of_its_kind_and_an_unknown_kind_says_so():
    from dhg.core.errors import ERROR_KINDS, EngineError
    from dhg.live.client import _refusal

    for kind, cls in ERROR_KINDS.items():
        exc = _refusal("k", json.dumps({"error": "what was wrong", "kind": kind}))
        assert type(exc) is cls and "what was wrong" in str(exc)
    newer = _refusal("k", json.dumps({"error": "x", "kind": "quota"}))
    assert type(newer) is EngineError and "'quota', unknown to this client" in str(newer)
    assert type(_refusal("k", "not json")) is EngineError
