"""The model service over a real Zenoh session: answers good windows, refuses bad ones, counts."""

from __future__ import annotations

import copy
import json
import sys
import threading

import numpy as np
import pytest

from dhg.core import protocol
from dhg.core.errors import InvalidInputError
from dhg.learning.model_file import read_model_meta
from dhg.learning.torchscript import load_model
from dhg.learning.weights import default_model_path
from dhg.live import services
from dhg.live.services import ModelService, corridor_mismatch
from dhg.live.zenoh_config import open_zenoh, zenoh_config_json5
from support import wait_until


@pytest.fixture(scope="module")
def model():
    return load_model(default_model_path())


def _predict(window: np.ndarray, seq: int, entry: int = 0) -> bytes:
    return protocol.encode(
        "predict", window_seq=seq, rows=window.shape[0], cols=window.shape[1], entry=entry, window=window.ravel()
    )


def _query(z, key: str, window: np.ndarray, seq: int, payload: bytes | None = None) -> tuple[bool, bytes]:
    payload = _predict(window, seq) if payload is None else payload
    replies = list(z.get(key, payload=payload, timeout=10.0))
    assert len(replies) == 1, f"{len(replies)} replies"
    r = replies[0]
    return (True, r.ok.payload.to_bytes()) if r.ok is not None else (False, r.err.payload.to_bytes())


@pytest.mark.parametrize("executor", ["torchscript", "onnxruntime"])
def test_a_window_the_model_overflows_on_is_refused_not_answered_with_nan(executor):
    """Issue 21, item 10: a window of 3e38 values (finite in float32) made the model answer NaN.
    Either executor refuses it (decision 0030)."""
    model = load_model(default_model_path(), executor=executor)
    huge = np.full((model.window, 9), 3e38, dtype=np.float32)
    with pytest.raises(InvalidInputError, match="not finite"):
        model.predict(huge)
    assert not np.all(np.isfinite(model.predict(huge, check_output=False))), "the model no longer overflows"
    z = open_zenoh(zenoh_config_json5(mode="peer"))
    service = ModelService(z, model, prefix="svc-test")
    try:
        key = protocol.keys("svc-test", "x")["predict"]
        ok, body = _query(z, key, np.zeros((model.window, 9), dtype=np.float32), 1)
        assert ok and protocol.decode("prediction", body[:32])["window_seq"] == 1
        ok, body = _query(z, key, huge, 2)
        assert not ok and "not finite" in json.loads(body)["error"]
        stats = service.stats()
        assert (stats["answered"], stats["refused"]) == (1, 1)
    finally:
        service.close()
        z.close()


def _predictions(body: bytes) -> list[dict]:
    """The predictions of a reply, back to back (32 bytes each and the model id)."""
    out = []
    while body:
        head = protocol.decode("prediction", body[:32])
        out.append(head)
        body = body[32 + head["model_id_len"] :]
    return out


def test_a_query_of_several_windows_is_answered_window_by_window_in_one_pass(model):
    """Decision 0032: the engine sends a burst of sessions' windows in one query. Each window's
    prediction names its entry and window_seq; it is the model's prediction for that window alone;
    a window the model overflows on goes unanswered while the others are answered; a query whose
    entries are out of order, or one too many windows, gets an error reply."""
    z = open_zenoh(zenoh_config_json5(mode="peer"))
    service = ModelService(z, model, prefix="svc-multi")
    rng = np.random.default_rng(3)
    windows = [rng.normal(0.0, 1.0, (model.window, 9)).astype(np.float32) for _ in range(3)]
    huge = np.full((model.window, 9), 3e38, dtype=np.float32)
    try:
        key = protocol.keys("svc-multi", "x")["predict"]
        payload = b"".join(_predict(w, 10 + i, entry=i) for i, w in enumerate(windows))
        ok, body = _query(z, key, windows[0], 0, payload)
        assert ok
        got = _predictions(body)
        assert [(g["entry"], g["window_seq"]) for g in got] == [(0, 10), (1, 11), (2, 12)]
        alone = model.predict(np.stack(windows))
        np.testing.assert_allclose([g["force_n"] for g in got], alone, rtol=1e-4, atol=1e-5)
        assert service.batches == 1  # one forward pass for the three windows

        mixed = _predict(windows[0], 20, entry=0) + _predict(huge, 21, entry=1) + _predict(windows[2], 22, entry=2)
        ok, body = _query(z, key, windows[0], 0, mixed)
        assert ok and [(g["entry"], g["window_seq"]) for g in _predictions(body)] == [(0, 20), (2, 22)]

        swapped = _predict(windows[0], 30, entry=1) + _predict(windows[1], 31, entry=0)
        ok, body = _query(z, key, windows[0], 0, swapped)
        assert not ok and "entry" in json.loads(body)["error"]
        too_many = b"".join(_predict(windows[0], i, entry=i) for i in range(protocol.MAX_QUERY_WINDOWS + 1))
        ok, body = _query(z, key, windows[0], 0, too_many)
        assert not ok and f"1 to {protocol.MAX_QUERY_WINDOWS} windows" in json.loads(body)["error"]
        assert service.stats()["answered"] == 3 + 2
    finally:
        service.close()
        z.close()


class _Query:
    """A query as the service's callback gets it, answered in memory."""

    def __init__(self, payload: bytes) -> None:
        self.payload = self
        self._payload = payload
        self.key_expr = "dhg/model/predict"
        self.replies: list[bytes] = []
        self.errors: list[str] = []
        self.dropped = False

    def to_bytes(self) -> bytes:
        return self._payload

    def reply(self, key, body: bytes) -> None:
        self.replies.append(body)

    def reply_err(self, body: str) -> None:
        self.errors.append(json.loads(body)["error"])

    def drop(self) -> None:
        self.dropped = True


def test_a_batch_of_queries_is_answered_query_by_query_in_passes_of_max_batch_windows(model):
    """Two queries of three and two windows in one batch, with passes of at most two windows: each
    query's reply holds its own windows' predictions (the model's for each window alone), a window
    with a NaN goes unanswered, and every query is dropped."""
    z = open_zenoh(zenoh_config_json5(mode="peer"))
    service = ModelService(z, model, prefix="svc-direct", max_batch=2)
    rng = np.random.default_rng(5)
    w = [rng.normal(0.0, 1.0, (model.window, 9)).astype(np.float32) for _ in range(5)]
    w[3][4, 2] = np.nan
    try:
        q1 = _Query(b"".join(_predict(w[i], 100 + i, entry=i) for i in range(3)))
        q2 = _Query(_predict(w[3], 7, entry=0) + _predict(w[4], 8, entry=1))
        batches = service.batches
        service._answer([q1, q2])
        assert service.batches - batches == 3  # five windows, two a pass
        assert q1.dropped and q2.dropped and not q1.errors and not q2.errors
        got1, got2 = _predictions(q1.replies[0]), _predictions(q2.replies[0])
        assert [(g["entry"], g["window_seq"]) for g in got1] == [(0, 100), (1, 101), (2, 102)]
        assert [(g["entry"], g["window_seq"]) for g in got2] == [(1, 8)]
        expected = model.predict(np.stack([w[0], w[1], w[2], w[4]]))
        np.testing.assert_allclose([g["force_n"] for g in got1 + got2], expected, rtol=1e-4, atol=1e-5)
        assert service.stats()["answered"] == 4
        with pytest.raises(InvalidInputError, match="max_batch"):
            ModelService(z, model, prefix="svc-direct0", max_batch=0)
    finally:
        service.close()
        z.close()


def test_onnx_runtimes_pool_threads_run_at_the_services_nice_value():
    """With more than one thread ONNX Runtime does part of each pass on a pool it starts when the
    model is loaded; the service lowers those threads with its own (decision 0026)."""
    import os

    import torch

    threads = torch.get_num_threads()
    torch.set_num_threads(2)
    try:
        model = load_model(default_model_path(), executor="onnxruntime")
    finally:
        torch.set_num_threads(threads)
    pool = model.runner.pool_threads
    assert model.runner.threads == 2 and len(pool) >= 1
    z = open_zenoh(zenoh_config_json5(mode="peer"))
    service = ModelService(z, model, prefix="svc-pool", nice=19)
    try:
        wait_until(lambda: all(os.getpriority(os.PRIO_PROCESS, t) == 19 for t in pool), 10.0, "the pool at nice 19")
        key = protocol.keys("svc-pool", "x")["predict"]
        ok, _ = _query(z, key, np.zeros((model.window, 9), dtype=np.float32), 1)
        assert ok
        assert os.getpriority(os.PRIO_PROCESS, threading.get_native_id()) == 0  # the caller's unchanged
    finally:
        service.close()
        z.close()


class _BlockingModel:
    """A model whose forward passes (after the service's warm-up) wait until the test releases them."""

    window = 20
    meta = {"preset": "blocking"}
    path = None

    def __init__(self) -> None:
        import threading

        self.calls = 0
        self.started = threading.Event()
        self.release = threading.Event()

    def predict(self, windows, check_output: bool = True):
        self.calls += 1
        if self.calls > 3:  # after the service's warm-up calls
            self.started.set()
            assert self.release.wait(timeout=30), "the test never released the forward pass"
        return np.zeros((len(np.atleast_3d(windows)), 3))


def test_queries_whose_asker_gave_up_are_refused_as_stale_not_computed():
    """Issue 21, item 10: the service computed queries the engine had long given up on. The
    service's clock is the test's, so the queries age by exactly what the test says."""
    import threading

    model = _BlockingModel()
    now = [0.0]
    z = open_zenoh(zenoh_config_json5(mode="peer"))
    service = ModelService(z, model, prefix="svc-stale", max_age_s=0.1, clock=lambda: now[0])
    key = protocol.keys("svc-stale", "x")["predict"]
    results: list[tuple[bool, bytes]] = []
    try:
        window = np.zeros((20, 9), dtype=np.float32)
        first = threading.Thread(target=lambda: results.append(_query(z, key, window, 1)))
        first.start()
        assert model.started.wait(timeout=10), "the first query never reached the model"
        later = [threading.Thread(target=lambda s=s: results.append(_query(z, key, window, s))) for s in (2, 3)]
        for t in later:
            t.start()
        # Both wait behind the first forward pass.
        wait_until(lambda: service._queue.qsize() >= 2, 10.0, "the later queries reaching the service")
        now[0] = 1.0  # a second passes on the service's clock: the two queued queries are stale
        model.release.set()
        for t in [first, *later]:
            t.join(timeout=20)
        stats = service.stats()
        # The first is answered; the two queued behind it are older than 0.1 s by then.
        assert stats["answered"] == 1 and stats["stale"] == 2 and stats["refused"] == 2, stats
        assert sum(ok for ok, _ in results) == 1
        assert all("stale" in json.loads(body)["error"] for ok, body in results if not ok)
    finally:
        model.release.set()
        service.close()
        z.close()


class _ScriptedModel:
    """A model whose forward passes are scripted by the test: each call is recorded, and it raises
    while ``failing`` is set."""

    meta = {"preset": "scripted"}
    path = None

    def __init__(self, window: int = 20) -> None:
        import threading

        self.window = window
        self.batches: list[int] = []
        self.failing = False
        self.gate = threading.Event()
        self.gate.set()
        self.entered = threading.Event()

    def predict(self, windows, check_output: bool = True):
        import os
        import threading

        n = len(np.atleast_3d(windows))
        self.batches.append(n)
        self.nice = os.getpriority(os.PRIO_PROCESS, threading.get_native_id())
        self.entered.set()
        assert self.gate.wait(timeout=30), "the test never opened the gate"
        if self.failing:
            raise RuntimeError("CUDA out of memory (scripted)")
        return np.tile([0.1, 0.2, 0.3], (n, 1))


def test_a_model_whose_window_is_not_the_engines_is_refused_at_start_up():
    z = open_zenoh(zenoh_config_json5(mode="peer"))
    try:
        with pytest.raises(InvalidInputError, match="windows of 10 records, but the engine sends 20"):
            ModelService(z, _ScriptedModel(window=10), prefix="svc-window")
    finally:
        z.close()


def test_queries_that_wait_behind_a_forward_pass_are_answered_in_one_batch_and_a_full_queue_refuses():
    import threading

    model = _ScriptedModel()
    z = open_zenoh(zenoh_config_json5(mode="peer"))
    service = ModelService(z, model, prefix="svc-batch", max_queue=3)
    key = protocol.keys("svc-batch", "x")["predict"]
    window = np.zeros((20, 9), dtype=np.float32)
    results: dict[int, tuple[bool, bytes]] = {}
    try:
        warm = len(model.batches)
        model.entered.clear()
        model.gate.clear()
        first = threading.Thread(target=lambda: results.__setitem__(1, _query(z, key, window, 1)))
        first.start()
        assert model.entered.wait(timeout=10), "the first query never reached the model"
        later = [
            threading.Thread(target=lambda s=s: results.__setitem__(s, _query(z, key, window, s))) for s in (2, 3, 4)
        ]
        for t in later:
            t.start()
        # All three wait behind the first pass: the queue is full.
        wait_until(lambda: service._queue.qsize() >= 3, 10.0, "the later queries reaching the service")
        ok, body = _query(z, key, window, 5)  # one more: refused at once, not queued
        assert not ok and "busy" in json.loads(body)["error"]
        model.gate.set()
        for t in [first, *later]:
            t.join(timeout=20)
        assert model.batches[warm:] == [1, 3], "the three waiting queries were not one forward pass"
        for seq in (1, 2, 3, 4):
            ok, body = results[seq]
            assert ok and protocol.decode("prediction", body[:32])["window_seq"] == seq
        stats = service.stats()
        assert (stats["answered"], stats["busy"], stats["refused"], stats["batches"]) == (4, 1, 1, 2), stats
    finally:
        model.gate.set()
        service.close()
        z.close()


def test_after_a_batch_of_n_the_worker_gathers_the_next_burst_of_n_and_a_lone_query_waits_for_nothing(monkeypatch):
    """The engine's sessions record on one 100 ms grid, so their queries come in bursts (decision
    0028): once a pass answered N, the next N queries to arrive share one pass even when they come
    one by one. A lone query, after a lone query, is computed at once."""
    import threading

    model = _ScriptedModel()
    z = open_zenoh(zenoh_config_json5(mode="peer"))
    # A long burst window, and a long memory of the last burst (a busy host may take a while
    # between the test's steps): the test would stall visibly (past its deadlines) if a lone query
    # waited for a burst.
    monkeypatch.setattr(services, "BURST_MEMORY_S", 60.0)
    service = ModelService(z, model, prefix="svc-burst", burst_wait_s=60.0)
    key = protocol.keys("svc-burst", "x")["predict"]
    window = np.zeros((20, 9), dtype=np.float32)

    def ask(seq: int) -> threading.Thread:
        t = threading.Thread(target=lambda: _query(z, key, window, seq))
        t.start()
        return t

    try:
        warm = len(model.batches)
        ask(1).join(timeout=20)  # after the warm-up's lone passes: computed at once
        assert model.batches[warm:] == [1]
        # Three queries behind a held pass: one batch of three.
        model.entered.clear()
        model.gate.clear()
        held = ask(2)
        assert model.entered.wait(timeout=20), "the query never reached the model"
        queued = [ask(s) for s in (3, 4, 5)]
        wait_until(lambda: service._queue.qsize() >= 3, 10.0, "the three queries reaching the service")
        model.gate.set()
        for t in (held, *queued):
            t.join(timeout=20)
        assert model.batches[warm:] == [1, 1, 3]
        # The next three, one at a time: the worker holds the first until the other two are in.
        arrived = service._queue.unfinished_tasks  # counts every put; get leaves it as it is
        burst = [ask(6)]
        wait_until(
            lambda: service._queue.unfinished_tasks == arrived + 1 and service._queue.qsize() == 0,
            10.0,
            "the worker taking the burst's first query",
        )
        burst += [ask(7), ask(8)]
        for t in burst:
            t.join(timeout=20)
        assert not any(t.is_alive() for t in burst), "a query of the burst was not answered"
        assert model.batches[warm:] == [1, 1, 3, 3], "the burst was not one forward pass"
        assert service.stats()["answered"] == 8
    finally:
        model.gate.set()
        service.close()
        z.close()


def test_a_model_that_raises_gets_error_replies_and_the_service_answers_again_after():
    model = _ScriptedModel()
    z = open_zenoh(zenoh_config_json5(mode="peer"))
    service = ModelService(z, model, prefix="svc-raise")
    key = protocol.keys("svc-raise", "x")["predict"]
    window = np.zeros((20, 9), dtype=np.float32)
    try:
        model.failing = True
        ok, body = _query(z, key, window, 1)
        assert not ok and "model failed: CUDA out of memory" in json.loads(body)["error"]
        model.failing = False
        ok, body = _query(z, key, window, 2)
        assert ok and protocol.decode("prediction", body[:32])["window_seq"] == 2
        assert service.stats()["answered"] == 1 and service.stats()["refused"] == 1
    finally:
        service.close()
        z.close()


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="per-thread nice values are Linux's")
def test_the_forward_passes_run_at_the_nice_value_asked_for_and_a_bad_one_is_refused():
    import os

    base = os.getpriority(os.PRIO_PROCESS, 0)
    z = open_zenoh(zenoh_config_json5(mode="peer"))
    window = np.zeros((20, 9), dtype=np.float32)
    try:
        for nice, expected in ((19, 19), (0, base)):
            model = _ScriptedModel()
            service = ModelService(z, model, prefix=f"svc-nice{nice}", nice=nice)
            try:
                ok, _ = _query(z, protocol.keys(f"svc-nice{nice}", "x")["predict"], window, 1)
                assert ok and model.nice == expected, (nice, model.nice)
            finally:
                service.close()
        # The process's own threads keep their priority: only the worker's was lowered.
        assert os.getpriority(os.PRIO_PROCESS, 0) == base
        for bad in (-1, 20):
            with pytest.raises(InvalidInputError, match="nice must be 0 .* to 19"):
                ModelService(z, _ScriptedModel(), prefix="svc-nice-bad", nice=bad)
    finally:
        z.close()


def test_the_corridor_check_finds_an_engine_guided_by_other_profiles():
    meta = read_model_meta(default_model_path())
    profiles = meta["profiles"]
    about = {
        "guidance": {
            "params": {
                "corridor_profile_n_per_m": list(profiles["corridor_n_per_m"]),
                "corridor_profile_bin_m": profiles["bin_m"],
            }
        }
    }
    assert corridor_mismatch(about, meta) is None
    halved = copy.deepcopy(about)
    halved["guidance"]["params"]["corridor_profile_n_per_m"] = [0.5 * k for k in profiles["corridor_n_per_m"]]
    assert "other expert profiles" in (corridor_mismatch(halved, meta) or "")
    finer = copy.deepcopy(about)
    finer["guidance"]["params"]["corridor_profile_bin_m"] = profiles["bin_m"] / 2
    assert corridor_mismatch(finer, meta) is not None
    fixed = copy.deepcopy(about)
    fixed["guidance"]["params"]["corridor_profile_n_per_m"] = []
    assert "fixed stiffness" in (corridor_mismatch(fixed, meta) or "")
    bare = {k: v for k, v in meta.items() if k != "profiles"}
    assert corridor_mismatch(fixed, bare) is None, "neither has profiles"
    assert "no expert profiles" in (corridor_mismatch(about, bare) or "")


def test_the_corridor_check_reports_again_when_a_restarted_engine_guides_by_other_profiles():
    """An engine answering ``about`` (here a queryable whose answer the test swaps, as a restart
    with another ``--model`` would): the check reports agreement, says nothing while the answer
    stays the same or while no engine answers, and warns once the answer changes."""
    meta = read_model_meta(default_model_path())
    profiles = meta["profiles"]
    params = {
        "corridor_profile_n_per_m": list(profiles["corridor_n_per_m"]),
        "corridor_profile_bin_m": profiles["bin_m"],
    }
    answer: dict[str, dict | None] = {"about": {"guidance": {"params": params}}}
    asked = []

    def reply(query):
        asked.append(1)
        if answer["about"] is not None:  # None: no engine (restarting)
            query.reply(query.key_expr, json.dumps(answer["about"]).encode())

    z = open_zenoh(zenoh_config_json5(mode="peer"))
    engine = z.declare_queryable(protocol.server_key("svc-recheck", "about"), reply)
    reports: list[str] = []
    with pytest.raises(InvalidInputError, match="recheck_s must be > 0"):
        services.CorridorCheck(z, meta, "svc-recheck", report=reports.append, recheck_s=0.0)
    check = services.CorridorCheck(z, meta, "svc-recheck", report=reports.append, every_s=0.2, recheck_s=0.05)
    try:
        wait_until(lambda: len(asked) >= 1 and reports, timeout_s=30.0, what="the first report")
        assert reports == ["note: the engine's corridor follows this model's expert profiles"]
        answer["about"] = None
        n = len(asked)
        wait_until(lambda: len(asked) >= n + 3, timeout_s=30.0, what="asks while no engine answers")
        answer["about"] = {"guidance": {"params": params}}  # the same model again
        n = len(asked)
        wait_until(lambda: len(asked) >= n + 3, timeout_s=30.0, what="asks of the restarted engine")
        assert len(reports) == 1, reports
        halved = dict(params, corridor_profile_n_per_m=[0.5 * k for k in profiles["corridor_n_per_m"]])
        answer["about"] = {"guidance": {"params": halved}}
        wait_until(lambda: len(reports) >= 2, timeout_s=30.0, what="the warning")
        assert reports[1].startswith("warning:") and "other expert profiles" in reports[1], reports
        assert check.result == reports[1]
    finally:
        check.close()
        engine.undeclare()
        z.close()
