"""Guidance studies: do virtual novices drill better with guidance, and do they learn? (``dhg study``)

Each novice (a seed: one hand, :func:`dhg.operators.styles.sample_style`, as one operator model of
:mod:`dhg.operators.models`) follows a protocol per arm, offline through the core (the same 1 kHz
session code ``dhg-serve`` runs, faster than real time) with the model in-process, queried at
every 10 Hz record:

1. a guidance-free **pre-test** (one attempt; the same for every arm, so it is run once);
2. ``train`` **training** attempts in the arm's guidance; the ``shaped-fading`` arm's gain follows
   the core's assist-as-needed schedule (:meth:`dhg.DrillingSession.set_fading`), its probes
   guidance-free;
3. a guidance-free **post-test**.

One attempt's plunge varies by about 2 mm (SD) with the hand's noise alone, as much as all a novice
learns, so a test can be *measured* more precisely than one attempt allows: with
``Protocol.test_replicates`` K, each test is drilled K times from the same learned state, each with
its own hand noise, and reported as their mean; the learner still learns only from the first (the
protocol's one test attempt), so K changes the measurement, not what the novice goes through. A
simulation can do this; a study of people cannot.

An arm is a guidance mode at a gain, or none. The trainee learns across the attempts
(:class:`dhg.operators.models.Learner`, after Emken et al. 2007) from the errors it experiences, so
guidance that hides the errors can also hide what there is to learn. Because every arm sees the
same hands with the same noise, arms are compared with paired differences against the unguided
arm, per metric the mean difference and its 95 % interval (Student's t over the novices): in the
first training attempt (guidance's immediate effect, from the same learned state in every arm)
and in the post-test (what the training left); and within each arm, post-test − pre-test.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Generator, Sequence
from concurrent.futures import ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from pathlib import Path
from typing import Any
from typing import Protocol as Protocol_

import numpy as np

from dhg.core.errors import DhgError, InvalidInputError
from dhg.core.protocol import WINDOW_RECORDS
from dhg.core.session import GuidanceMode
from dhg.operators.models import OPERATORS, Operator
from dhg.study.design import ARMS, METRICS, PHASES, Arm, Protocol, parse_arms
from dhg.study.result import Attempt, StudyResult

__all__ = ["ARMS", "METRICS", "PHASES", "Arm", "Protocol", "StudyResult", "parse_arms", "run_study"]

Window = np.ndarray
"""One (20, 9) window of records; a job sends it to get the predicted force (N)."""


class _Station(Protocol_):
    """Where a job's attempts are drilled: an in-process session, or a session on a server."""

    def guide(self, mode: GuidanceMode | None, gain: float) -> None: ...

    def set_fading(self, params: dict[str, Any] | None) -> None: ...

    def end_attempt(self) -> dict[str, Any] | None:
        """Ends the last attempt (the fading schedule counts it) and returns the schedule."""
        ...

    def attempt(
        self, style: Any, rng: np.random.Generator, cue: Any, guided: bool, rules: Any
    ) -> Generator[Window, np.ndarray, dict[str, float]]: ...


class _LocalStation:
    """A :class:`dhg.DrillingSession` in this process; its model queries are yielded to the
    caller, which answers many stations' at once (:func:`_lockstep`)."""

    def __init__(
        self,
        phantom: Any,
        profiles: Any,
        guidance: tuple[tuple[str, float], ...] = (),
        burr_radius_m: float | None = None,
    ) -> None:
        from dhg.core.session import DrillingSession, SessionConfig

        config = SessionConfig() if burr_radius_m is None else SessionConfig(burr_radius_m=burr_radius_m)
        self.session = DrillingSession(phantom.volume, phantom.path, config)
        if profiles is not None:  # the corridor follows the experts' spread, as dhg-serve --model does
            self.session.set_corridor_profile(profiles.bin_m, profiles.corridor_n_per_m)
        if guidance:
            self.session.set_guidance_params(**dict(guidance))

    def guide(self, mode: GuidanceMode | None, gain: float) -> None:
        self.session.set_guidance(mode or "paper", gain if mode else 0.0)

    def set_fading(self, params: dict[str, Any] | None) -> None:
        if params is None:
            self.session.set_fading(enabled=False)
        else:
            self.session.set_fading(params)

    def end_attempt(self) -> dict[str, Any] | None:
        self.session.reset()  # drill_episode's own reset then counts none
        return self.session.fading

    def attempt(
        self, style: Any, rng: np.random.Generator, cue: Any, guided: bool, rules: Any
    ) -> Generator[Window, np.ndarray, dict[str, float]]:
        from dhg.operators.episodes import drill_episode

        ep = yield from drill_episode(self.session, style, rng, rules=rules, guided=guided, cue_meaning=cue)
        return {k: float(v) for k, v in ep.metrics.items()} | {k: float(v) for k, v in ep.extra.items()}


class _LiveStation:
    """A session on a running ``dhg-serve`` (``--live``): drilled in real time through the
    network, guided by the server's own model service."""

    def __init__(
        self, connect: str, session_id: str, zenoh_config_file: str | None, burr_radius_m: float | None = None
    ) -> None:
        from dhg.live.client import TraineeClient

        self.client = TraineeClient(connect, session_id, zenoh_config_file=zenoh_config_file)
        self.info = self.client.create(burr_radius_m=burr_radius_m)

    def guide(self, mode: GuidanceMode | None, gain: float) -> None:
        if mode is None:
            self.client.set_guidance(gain=0.0)
        else:
            self.client.set_guidance(gain=gain, mode=mode)

    def set_fading(self, params: dict[str, Any] | None) -> None:
        self.client.set_fading(params, enabled=params is not None)

    def end_attempt(self) -> dict[str, Any] | None:
        self.info = self.client.control("reset")
        return self.info.get("fading")

    def attempt(
        self, style: Any, rng: np.random.Generator, cue: Any, guided: bool, rules: Any
    ) -> Generator[Window, np.ndarray, dict[str, float]]:
        import time

        from dhg.core.path import PlannedPath
        from dhg.core.surgeon import SurgeonController
        from dhg.live.trainee import drive_surgeon, live_metrics, planned_depth_from_info, states_since_reset

        self.end_attempt()
        self.client.states.clear()
        path = PlannedPath(np.array(self.info["entry_m"]), np.array(self.info["target_m"]))
        surgeon = SurgeonController(
            path, style, rng, rules, breakthrough_depth_m=planned_depth_from_info(self.info), cue_meaning=cue
        )
        drive_surgeon(self.client, surgeon, rules.max_duration_s)
        time.sleep(0.25)  # the last state messages
        m = live_metrics(self.client, surgeon, states_since_reset(list(self.client.states)))
        return {k: float(v) for k, v in m.items()}
        yield  # a generator that never queries: the server's model guides it

    def close(self) -> None:
        try:
            self.client.control("close")
        except Exception:  # the server frees it after its idle timeout anyway
            pass
        self.client.close()


def _job(
    station: _Station,
    seed: int,
    arm: Arm | None,
    operator: Operator,
    protocol: Protocol,
    learned: dict[str, float] | None,
    on_attempt: Callable[[], None],
) -> Generator[Window, np.ndarray, tuple[int, str, list[Attempt]]]:
    """One novice's attempts at ``station``: the pre-test alone (``arm`` None), or an arm's
    training and post-test after the pre-test whose learned state (``learned``) it starts from.
    Yields the model's queries of guided attempts (answered by ``send``)."""
    from dhg.core.path import TaskRules
    from dhg.operators.models import Learner, cue_meaning, operator_style
    from dhg.operators.styles import sample_style

    base = operator_style(
        sample_style("novice", np.random.default_rng([seed, 1])), operator, np.random.default_rng([seed, 2])
    )
    learner = Learner(**(learned or {}))
    rules = TaskRules(max_duration_s=protocol.duration_s)

    def attempt(
        index: int, phase: str, mode: GuidanceMode | None, gain: float
    ) -> Generator[Window, np.ndarray, Attempt]:
        probe = False
        if phase == "train" and arm is not None and arm.fading:
            fading = station.end_attempt()  # ends the last attempt in the schedule
            assert fading is not None
            gain, probe = fading["gain"], fading["probe"]
        else:
            station.guide(mode, gain)
        guided = mode is not None
        cue = cue_meaning(operator, mode if guided else None)
        style = learner.style(base)
        # A test is drilled test_replicates times from the same learned state, each with its own
        # hand noise (replicate 0 is the protocol's attempt); the training attempts once.
        replicates = protocol.test_replicates if phase in ("pre", "post") else 1
        runs = []
        for r in range(replicates):
            rng = np.random.default_rng([seed, 1, 1, index] + ([r] if r else []))
            runs.append((yield from station.attempt(style, rng, cue, guided, rules)))
            on_attempt()
        m = runs[0]
        learner.update(m["plunge_depth_m"], m["max_deviation_m"])  # what was learned: replicate 0's errors
        head = {"phase": phase, "index": index, "gain": float(gain) if guided else 0.0, "probe": probe}
        if replicates == 1:
            return head | m
        mean = {k: float(np.mean([run[k] for run in runs])) for k in m}
        return head | mean | {"replicates": runs}

    if arm is None:
        pre = yield from attempt(0, "pre", None, 0.0)
        pre["learned"] = dataclasses.asdict(learner)
        return seed, "pre", [pre]
    out = []
    if arm.mode is not None:
        station.guide(arm.mode, arm.gain)
        if arm.fading:
            station.set_fading(
                {"start_gain": arm.gain, "max_gain": max(arm.gain, 1.0), "probe_every": protocol.probe_every}
            )
    for k in range(protocol.train):
        out.append((yield from attempt(1 + k, "train", arm.mode, arm.gain)))
    station.set_fading(None)
    out.append((yield from attempt(1 + protocol.train, "post", None, 0.0)))
    return seed, arm.name, out


MODEL_BATCH = 16
"""The offline study answers model queries in batches of exactly this many windows (padded).
Batched forward passes differ from one another in the last float32 bits with the batch's size
(about 1e-6 N), and a drilling hand amplifies such differences: at one fixed size, a window's
answer does not depend on which others share its batch or where it sits in it (checked by
``tests/test_study.py``), so a novice's result does not depend on the group it was run in."""


def _lockstep(jobs: list[Generator[Window, np.ndarray, Any]], predict: Callable[[np.ndarray], np.ndarray]) -> list[Any]:
    """Runs the jobs side by side, answering all their pending model queries with batched
    forward passes of :data:`MODEL_BATCH` windows (16 cost about twice one, not 16 times);
    returns their results in order."""
    results: list[Any] = [None] * len(jobs)
    pending: dict[int, Window] = {}
    batch = np.zeros((MODEL_BATCH, WINDOW_RECORDS, 9))

    def advance(i: int, reply: np.ndarray | None) -> None:
        try:
            pending[i] = next(jobs[i]) if reply is None else jobs[i].send(reply)
        except StopIteration as done:
            results[i] = done.value
            pending.pop(i, None)

    for i in range(len(jobs)):
        advance(i, None)
    while pending:
        ids = list(pending)[:MODEL_BATCH]
        for k, i in enumerate(ids):
            batch[k] = pending[i]
        batch[len(ids) :] = batch[0]  # padding: its answers are not used
        predicted = predict(batch)
        for k, i in enumerate(ids):
            advance(i, predicted[k])
    return results


# -- offline: worker processes, each drilling a group of novices in lockstep ------------------------
_WORKER: dict[str, Any] = {}


def _init_worker(model_path: str, voxel_m: float, events: Any = None) -> None:
    import torch

    from dhg.bone.phantom import default_phantom
    from dhg.learning.torchscript import load_model

    torch.set_num_threads(1)
    _WORKER.pop("error", None)  # with one worker this is the caller's process: no error of an earlier study
    try:
        _WORKER.update(phantom=default_phantom(voxel_m=voxel_m), model=load_model(model_path), events=events)
    except DhgError as exc:  # raised again by each job, so the caller gets it, not a broken pool
        _WORKER["error"] = exc


def _group(work: tuple[list[int], list[Arm], Operator, Protocol]) -> list[tuple[int, str, list[Attempt]]]:
    """Every attempt of a group of novices: their pre-tests, then every arm's protocol, all side
    by side (:func:`_lockstep`). Returns (seed, arm name or "pre", attempts) per job."""
    seeds, arms, operator, protocol = work
    if "error" in _WORKER:
        raise _WORKER["error"]
    phantom, model, events = _WORKER["phantom"], _WORKER["model"], _WORKER["events"]
    on_attempt = (lambda: events.put(1)) if events is not None else _WORKER["on_attempt"]
    profiles = model.profiles
    predict = model.predict

    def station() -> _LocalStation:
        return _LocalStation(phantom, profiles, protocol.guidance, protocol.burr_radius_m)

    pre = _lockstep([_job(station(), s, None, operator, protocol, None, on_attempt) for s in seeds], predict)
    learned = {seed: atts[0]["learned"] for seed, _, atts in pre}
    jobs = [_job(station(), s, a, operator, protocol, learned[s], on_attempt) for s in seeds for a in arms]
    return pre + _lockstep(jobs, predict)


def _run_offline(
    seeds: list[int],
    arms: list[Arm],
    model_path: str,
    protocol: Protocol,
    operator: Operator,
    workers: int,
    voxel_m: float,
    on_attempt: Callable[[], None],
) -> list[tuple[int, str, list[Attempt]]]:
    # A whole number of groups per worker (for balance at the end), each of at most 6 novices (the
    # arms of 5 novices fill about two model batches).
    n_groups = workers * max(1, -(-len(seeds) // (6 * workers)))
    size = -(-len(seeds) // n_groups)
    groups = [(seeds[i : i + size], arms, operator, protocol) for i in range(0, len(seeds), size)]
    from dhg.learning.model_file import read_model_meta

    read_model_meta(model_path)  # a missing or foreign model file: its error now, before any worker starts
    if workers == 1:
        _init_worker(model_path, voxel_m)
        _WORKER["on_attempt"] = on_attempt
        return [r for g in groups for r in _group(g)]
    import multiprocessing
    import queue

    ctx = multiprocessing.get_context("fork")
    events = ctx.Queue()
    out: list[tuple[int, str, list[Attempt]]] = []
    with ProcessPoolExecutor(
        workers, mp_context=ctx, initializer=_init_worker, initargs=(model_path, voxel_m, events)
    ) as pool:
        futures = [pool.submit(_group, g) for g in groups]
        while not all(f.done() for f in futures):
            try:
                events.get(timeout=0.2)
                on_attempt()
            except queue.Empty:
                pass
        try:
            for f in futures:
                out += f.result()  # re-raises a worker's error
        except BrokenProcessPool as exc:
            raise DhgError(f"a study worker process died ({exc}); its error is printed above") from None
    while True:  # attempts counted after the last check
        try:
            events.get_nowait()
            on_attempt()
        except queue.Empty:
            break
    return out


# -- live: sessions on a running server, drilled in real time, side by side -----------------------
def _run_live(
    seeds: list[int],
    arms: list[Arm],
    protocol: Protocol,
    operator: Operator,
    connect: str,
    zenoh_config_file: str | None,
    parallel: int,
    on_attempt: Callable[[], None],
) -> list[tuple[int, str, list[Attempt]]]:
    import threading
    import uuid
    from concurrent.futures import ThreadPoolExecutor

    tag = uuid.uuid4().hex[:6]
    lock = threading.Lock()

    def counted() -> None:
        with lock:
            on_attempt()

    def run(seed: int, arm: Arm | None, learned: dict[str, float] | None) -> tuple[int, str, list[Attempt]]:
        sid = f"study-{tag}-{seed}-{'pre' if arm is None else ''.join(c if c.isalnum() else '_' for c in arm.name)}"
        station = _LiveStation(connect, sid, zenoh_config_file, protocol.burr_radius_m)
        try:
            job = _job(station, seed, arm, operator, protocol, learned, counted)
            try:  # a live station never queries (the server's model guides it): one step runs the job
                next(job)
            except StopIteration as done:
                return done.value
            raise AssertionError("a live station's model is the server's")
        finally:
            station.close()

    with ThreadPoolExecutor(parallel) as pool:
        pre = list(pool.map(lambda s: run(s, None, None), seeds))
        learned = {seed: atts[0]["learned"] for seed, _, atts in pre}
        jobs = [(s, a) for s in seeds for a in arms]
        return pre + list(pool.map(lambda j: run(j[0], j[1], learned[j[0]]), jobs))


def run_study(
    seeds: Sequence[int],
    arms: Sequence[Arm],
    model_path: str | Path,
    protocol: Protocol | None = None,
    operator: Operator = "impedance",
    workers: int = 2,
    voxel_m: float = 0.5e-3,
    progress: Callable[[int, int], None] | None = None,
    live: str | None = None,
    zenoh_config_file: str | None = None,
) -> StudyResult:
    """Runs the protocol for every novice in every arm (see the module docs). Offline by
    default: ``workers`` processes, each drilling its novices side by side, the model in-process.
    With ``live`` (a Zenoh endpoint of a running ``dhg-serve``), the attempts are drilled in real
    time through that server, its own model guiding them, up to ``workers`` sessions at once;
    ``model_path`` and ``voxel_m`` are then the server's business and unused."""
    protocol = protocol or Protocol()
    protocol.validate()
    if live and protocol.guidance:
        raise InvalidInputError(
            "with live, the server's guidance laws apply: change them on dhg-serve, not in the protocol"
        )
    if not seeds:
        raise InvalidInputError("a study needs at least one novice seed")
    if operator not in OPERATORS:
        raise InvalidInputError(f"operator must be one of {', '.join(OPERATORS)}, got {operator!r}")
    if workers < 1:
        raise InvalidInputError(f"workers must be at least 1, got {workers}")
    seeds = [int(s) for s in seeds]
    if len(set(seeds)) != len(seeds):
        raise InvalidInputError("novice seeds repeat")
    arms = list(arms)
    k = protocol.test_replicates
    total = len(seeds) * (k + len(arms) * (protocol.train + k))
    done = 0

    def on_attempt() -> None:
        nonlocal done
        done += 1
        if progress:
            progress(done, total)

    if live is None:
        results = _run_offline(seeds, arms, str(model_path), protocol, operator, workers, voxel_m, on_attempt)
    else:
        results = _run_live(seeds, arms, protocol, operator, live, zenoh_config_file, workers, on_attempt)
    pre = {seed: atts[0] for seed, name, atts in results if name == "pre"}
    by: dict[str, dict[int, list[Attempt]]] = {a.name: {} for a in arms}
    for seed, name, atts in results:
        if name != "pre":
            by[name][seed] = [pre[seed], *atts]
    return StudyResult(arms, seeds, {a: [by[a][s] for s in seeds] for a in by}, operator, protocol)
