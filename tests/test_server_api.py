"""The native server's Python surface, in-process: settings are checked, bad values are refused
with a clear error, and it stops cleanly (no Zenoh peers involved beyond loopback)."""

from __future__ import annotations

import ctypes
import itertools
import os
import platform
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from dhg import _bone_sim
from dhg.bone.planning import planned_breakthrough_depth_m
from dhg.core import protocol
from dhg.core.errors import EngineError, InvalidInputError
from dhg.core.layers import Layer
from dhg.core.server import ServerSettings, start_engine
from dhg.live.client import TraineeClient
from dhg.live.process import free_port
from dhg.live.runner import scheduling_hint
from dhg.live.trainee import planned_depth_from_info
from dhg.live.zenoh_config import open_zenoh, zenoh_config_json5
from support import Stylus, wait_until


@pytest.fixture()
def engine(coarse_phantom):
    conf = zenoh_config_json5([f"tcp/127.0.0.1:{free_port()}"], mode="router")
    srv = start_engine(coarse_phantom.volume, coarse_phantom.path, conf, ServerSettings(max_sessions=2))
    yield srv
    srv.stop()


def test_new_sessions_are_guided_as_the_server_settings_say_and_the_server_says_so(coarse_phantom):
    """``Server.new_session_guidance`` (the ``about`` reply's ``guidance``) is what the engine runs:
    the settings' mode, gain and limits and corridor profile over the core's other laws."""
    from dhg.core.session import GUIDANCE_DEFAULTS

    conf = zenoh_config_json5([f"tcp/127.0.0.1:{free_port()}"], mode="router")
    settings = ServerSettings(
        guidance_mode="corridor",
        guidance_gain=0.5,
        guidance_max_n=0.6,
        guidance_max_rate_n_per_s=4.0,
        guidance_timeout_s=0.3,
        corridor_profile=(2e-3, (100.0, 250.0)),
    )
    srv = start_engine(coarse_phantom.volume, coarse_phantom.path, conf, settings)
    try:
        g = srv.new_session_guidance
        p = g.pop("params")
        assert g == {"mode": "corridor", "gain": 0.5}
        assert (p.pop("max_n"), p.pop("max_rate_n_per_s"), p.pop("timeout_s")) == (0.6, 4.0, 0.3)
        assert (p.pop("corridor_profile_bin_m"), p.pop("corridor_profile_n_per_m")) == (2e-3, [100.0, 250.0])
        set_by_the_settings = {
            "max_n",
            "max_rate_n_per_s",
            "timeout_s",
            "corridor_profile_bin_m",
            "corridor_profile_n_per_m",
        }
        others = {k: v for k, v in GUIDANCE_DEFAULTS.items() if k not in set_by_the_settings}
        assert p == others, "the other laws: the core's"
        info = srv.control("set-1", {"op": "create"})
        assert (info["guidance_mode"], info["guidance_gain"]) == ("corridor", 0.5)
    finally:
        srv.stop()


def test_unknown_server_settings_are_refused_with_the_allowed_keys(coarse_phantom):
    conf = zenoh_config_json5([f"tcp/127.0.0.1:{free_port()}"], mode="router")
    p = coarse_phantom.path

    def start(settings):
        return _bone_sim.Server(coarse_phantom.volume._vol, list(p.entry_m), list(p.target_m), conf, settings=settings)

    with pytest.raises(InvalidInputError, match="unknown field `idle`.*idle_timeout_s"):
        start({"idle": 1.0})
    with pytest.raises(InvalidInputError, match="max_sessions"):
        start({"max_sessions": 0})
    with pytest.raises(InvalidInputError, match="unknown variant `poll`.*sleep.*spin"):
        start({"wait": "poll"})
    with pytest.raises(InvalidInputError, match="idle_timeout_s"):
        start({"idle_timeout_s": "soon"})
    # Zenoh's query timeout is a Duration: 1e20 s was a PanicException from inside the start.
    with pytest.raises(InvalidInputError, match="model_timeout_s .*at most"):
        start({"model_timeout_s": 1e20})


def test_a_spinning_engine_serves_a_zenoh_client_says_so_sleeps_when_idle_and_stops(coarse_phantom):
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    conf = zenoh_config_json5([endpoint], mode="router")
    srv = start_engine(coarse_phantom.volume, coarse_phantom.path, conf, ServerSettings(wait="spin"))
    try:
        # Without a session it sleeps: the tick thread parks (and counts its wake-ups, which a
        # spinning thread would not), and the process is seen, over some 0.2 s, to use less than
        # the 2 cores its two spinning threads would (a loaded machine only delays seeing it).
        wait_until(lambda: srv.health()["tick_thread_wakes"] >= 10, 30.0, "the idle tick thread parked and woke")

        def idle() -> bool:
            cpu0, wall0 = time.process_time(), time.monotonic()
            time.sleep(0.2)
            return (time.process_time() - cpu0) / (time.monotonic() - wall0) < 0.3

        wait_until(idle, 30.0, "an idle spinning engine to use under 0.3 cores")
        forces: list[dict] = []
        with TraineeClient(endpoint, "spin-1", on_force=forces.append) as c:
            a = np.array(c.create()["entry_m"])
            t0 = time.monotonic()
            for _ in range(300):  # 0.3 s at 1 kHz, hovering 5 mm off A with the drill off
                last = c.send_pose(a - [0.0, 0.0, 5e-3], (1.0, 0.0, 0.0, 0.0), False, 0.0)
                time.sleep(1e-3)
            # The session keeps ticking on the newest pose: its force echoes it sooner or later.
            wait_until(lambda: forces and forces[-1]["pose_seq"] == last, 10.0, "a force echoing the last pose")
            h = srv.health()
        seqs = [m["pose_seq"] for m in list(forces)]
        # Each force echoes a pose this client sent (0: none yet), never one older than the force
        # before.
        assert set(seqs) <= set(range(last + 1)), "a force echoed a pose that was never sent"
        assert seqs == sorted(seqs), "forces echoed poses out of order"
        assert all(np.isfinite(m["force_n"]).all() for m in forces)
        assert h["tick_wait"] == "spin"
        assert h["sessions"] == 1 and h["poses"] >= 1
        assert h["ticks"] <= (time.monotonic() - t0) * 1000 + 100, "spinning ticked faster than 1 kHz"
    finally:
        srv.stop()
    assert not srv.running


@pytest.mark.parametrize("tick_on", ["pose", "thread"])
def test_a_pose_ticks_its_session_on_the_thread_that_received_it_unless_told_not_to(coarse_phantom, tick_on):
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    conf = zenoh_config_json5([endpoint], mode="router")
    srv = start_engine(coarse_phantom.volume, coarse_phantom.path, conf, ServerSettings(tick_on=tick_on))
    try:
        forces: list[dict] = []
        with TraineeClient(endpoint, f"on-{tick_on}", on_force=forces.append) as c:
            a = np.array(c.create()["entry_m"])
            hand = Stylus(c, (1.0, 0.0, 0.0, 0.0))  # 1 kHz, hovering 5 mm off A
            try:
                hand.move(np.repeat([a - [0.0, 0.0, 5e-3]], 400, axis=0))
                wait_until(lambda: hand.idle() and len(forces) >= 400, 30.0, "400 poses sent and their forces")
            finally:
                hand.stop()
            h = srv.health()
        seqs = [m["pose_seq"] for m in list(forces)]
        assert seqs == sorted(seqs), "forces echoed poses out of order"
        assert h["tick_on"] == tick_on
        assert 0 <= h["ticks_on_pose_thread"] <= h["ticks"]
        assert h["tick_thread_wakes"] > 0, "the tick thread never woke, not even for the session's creation"
        if tick_on == "pose":
            # A pose that comes a period or more after the last tick ticks where it arrives; an
            # early one (sleep() overshoots, then catches up) or a late one is the tick thread's.
            # How many of each depends on this machine's load, so only that some did.
            assert h["ticks_on_pose_thread"] > 0, h
            # Every pose ticked where it arrived or was left to the tick thread, with its reason
            # (`poses` counts a pose before its tick is tried: wait for the last ones; the window
            # spans the server's whole life, as `poses` does).
            assert set(h["poses_to_tick_thread"]) == {"early", "claimed"}, h
            assert h["ticks_on_pose_thread_behind"] <= h["ticks_on_pose_thread"], h

            def accounted() -> bool:
                a = srv.health(window_s=3600.0)
                return a["ticks_on_pose_thread"] + sum(a["poses_to_tick_thread"].values()) == a["poses"]

            wait_until(accounted, 10.0, "every pose ticked on its thread or counted as left to the tick thread")
        else:
            assert h["ticks_on_pose_thread"] == 0, "a pose ticked its session although told not to"
            assert h["poses_to_tick_thread"] == {"early": 0, "claimed": 0}, h
            assert h["ticks_on_pose_thread_behind"] == 0, h
    finally:
        srv.stop()


@pytest.fixture()
def engine_and_screen(coarse_phantom: Any) -> Iterator[tuple[str, Any]]:
    """An engine on a free port (a router, as dhg-serve's) and a screen: a Zenoh client session
    connected to it. Yields the endpoint and the screen's session."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    conf = zenoh_config_json5([endpoint], mode="router")
    srv = start_engine(coarse_phantom.volume, coarse_phantom.path, conf, ServerSettings())
    try:
        screen = open_zenoh(zenoh_config_json5(connect=[endpoint], mode="client"))
        try:
            yield endpoint, screen
        finally:
            screen.close()
    finally:
        srv.stop()


def test_a_screen_hears_the_newest_force_and_pose_a_few_dozen_times_a_second_not_every_tick(engine_and_screen):
    endpoint, screen = engine_and_screen
    keys = protocol.keys("dhg", "shown")
    views: dict[str, list[dict]] = {"force": [], "pose": []}

    def heard(name: str) -> Any:
        return lambda s: views[name].append(protocol.decode(name, s.payload.to_bytes()))

    subs = [screen.declare_subscriber(keys[f"view/{n}"], heard(n)) for n in views]
    forces: list[dict] = []
    with TraineeClient(endpoint, "shown", on_force=forces.append) as c:
        a = np.array(c.create()["entry_m"])
        hand = Stylus(c, (1.0, 0.0, 0.0, 0.0))  # 1 kHz, hovering 5 mm off A
        try:
            hand.move(np.repeat([a - [0.0, 0.0, 5e-3]], 600, axis=0))
            done = lambda: hand.idle() and len(forces) >= 600 and len(views["pose"]) >= 5  # noqa: E731
            wait_until(done, 30.0, "600 forces and 5 views")
        finally:
            hand.stop()
    for s in subs:
        s.undeclare()
    vf, vp = list(views["force"]), list(views["pose"])
    # The server's copies of the newest: far fewer than the forces (50-60 a second against
    # 1,000), each one a force the session made, in order, with the pose that force used.
    assert len(vf) <= len(forces) / 8, (len(vf), len(forces))
    seqs = [m["pose_seq"] for m in vf]
    assert seqs == sorted(seqs) and max(seqs) <= max(m["pose_seq"] for m in forces)
    assert all(np.isfinite(m["force_n"]).all() and np.isfinite(m["tip_m"]).all() for m in vf)
    assert {m["seq"] for m in vp} <= {m["pose_seq"] for m in vf} | {0}
    assert all(np.allclose(m["orientation_wxyz"], (1.0, 0.0, 0.0, 0.0)) for m in vp if m["seq"] > 0)


def test_a_screen_that_comes_while_the_trainee_drills_hears_the_view_streams(engine_and_screen):
    """A view stream nobody watches is not put (docs/decisions/0025-view-streams.md); a screen that
    subscribes to a running session turns it on."""
    endpoint, screen = engine_and_screen
    keys = protocol.keys("dhg", "late")
    forces: list[dict] = []
    with TraineeClient(endpoint, "late", on_force=forces.append) as c:
        a = np.array(c.create()["entry_m"])
        hand = Stylus(c, (1.0, 0.0, 0.0, 0.0))
        try:
            hand.move(np.repeat([a - [0.0, 0.0, 5e-3]], 3000, axis=0))
            wait_until(lambda: len(forces) >= 300, 30.0, "300 forces before the screen")
            heard: list[int] = []
            sub = screen.declare_subscriber(keys["view/force"], lambda s: heard.append(1))
            wait_until(lambda: len(heard) >= 3, 30.0, "3 view forces after the screen subscribed")
            sub.undeclare()
        finally:
            hand.stop()


def test_an_idle_servers_tick_thread_sleeps_until_something_wakes_it(coarse_phantom):
    # With no session nothing is due: the tick thread sleeps until a command or a pose wakes it,
    # with a 20 ms backstop (IDLE_WAKE). It used to sleep a period at most, so that a command
    # would not wait longer: 1,000 wake-ups a second for nothing.
    conf = zenoh_config_json5([f"tcp/127.0.0.1:{free_port()}"], mode="router")
    srv = start_engine(coarse_phantom.volume, coarse_phantom.path, conf, ServerSettings())
    try:
        wait_until(lambda: srv.health()["uptime_s"] >= 1.5, 30.0, "the server up for 1.5 s")
        h = srv.health()
        assert h["sessions"] == 0
        assert h["tick_thread_wakes"] <= 60 * h["window_s"] + 20, h
    finally:
        srv.stop()


SLICE_NS = 100_000
"""The slice the server asks for (``LATENCY_SLICE_NS``)."""


def _sched(prefixes: tuple[str, ...]) -> dict[str, tuple[int, int | None]]:
    """Threads of this process named with one of ``prefixes`` → (policy, EEVDF slice in ns) as
    the kernel reports them (slice ``None`` where it reports none: kernels before 6.6)."""
    out: dict[str, tuple[int, int | None]] = {}
    for task in Path("/proc/self/task").iterdir():
        try:
            name = (task / "comm").read_text().strip()
            if not name.startswith(prefixes):
                continue
            fields = dict(
                (k.strip(), v.strip())
                for k, _, v in (ln.partition(":") for ln in (task / "sched").read_text().splitlines())
            )
        except FileNotFoundError:  # the thread ended while being read
            continue
        out[f"{name}/{task.name}"] = (int(fields["policy"]), int(fields["se.slice"]) if "se.slice" in fields else None)
    return out


_SCHED_ATTR = {"x86_64": (314, 315), "aarch64": (274, 275)}
"""sched_setattr and sched_getattr syscall numbers."""


def _kernel_grants_short_slices() -> tuple[bool, str]:
    """Asks the kernel, from a throwaway thread of the fair class, for the 0.1 ms slice
    (``sched_setattr``, as the server does but independently of its code); returns whether the
    kernel then reports it, and why not."""
    numbers = _SCHED_ATTR.get(platform.machine())
    if numbers is None:
        return False, f"no sched_setattr number known for {platform.machine()}"
    setattr_nr, getattr_nr = numbers
    libc = ctypes.CDLL(None, use_errno=True)
    libc.syscall.restype = ctypes.c_long
    zero, size = ctypes.c_long(0), ctypes.c_long(56)
    result: list[tuple[bool, str]] = []

    def probe() -> None:
        attr = (ctypes.c_uint8 * 56)()  # struct sched_attr, SCHED_ATTR_SIZE_VER1
        if libc.syscall(ctypes.c_long(getattr_nr), zero, attr, size, zero) != 0:
            result.append((False, f"sched_getattr failed: {os.strerror(ctypes.get_errno())}"))
            return
        if int.from_bytes(bytes(attr[4:8]), "little") not in (os.SCHED_OTHER, os.SCHED_BATCH):
            result.append((False, "this process is not in the fair scheduling class"))
            return
        attr[0:4] = (56).to_bytes(4, "little")
        attr[8:16] = bytes(8)  # sched_flags
        attr[24:32] = SLICE_NS.to_bytes(8, "little")  # sched_runtime
        if libc.syscall(ctypes.c_long(setattr_nr), zero, attr, zero) != 0:
            result.append((False, f"sched_setattr refused: {os.strerror(ctypes.get_errno())}"))
            return
        libc.syscall(ctypes.c_long(getattr_nr), zero, attr, size, zero)
        got = int.from_bytes(bytes(attr[24:32]), "little")
        result.append((got == SLICE_NS, f"the kernel accepts but ignores a custom slice (reports {got} ns)"))

    t = threading.Thread(target=probe, name="slice-probe")
    t.start()
    t.join()
    return result[0]


@pytest.mark.skipif(not Path("/proc/self/task").is_dir(), reason="reads /proc (Linux)")
def test_the_short_slices_reported_are_the_ones_the_kernel_gave(coarse_phantom):
    # The comm thread and Zenoh's I/O threads ask for a 0.1 ms slice (no privilege needed on
    # Linux 6.12+); the tick thread too when it has no SCHED_FIFO. Health must say what happened.
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    conf = zenoh_config_json5([endpoint], mode="router")
    srv = start_engine(coarse_phantom.volume, coarse_phantom.path, conf, ServerSettings())
    prefixes = ("dhg-comm", "dhg-tick", "rx-", "tx-")

    def io_sliced(threads: dict[str, tuple[int, int | None]]) -> int:
        return sum(sl == SLICE_NS for k, (_, sl) in threads.items() if k.startswith(("rx-", "tx-")))

    try:
        h = srv.health()["short_slices"]
        # On any kernel: the report's shape and types.
        assert set(h) == {"tick", "comm", "zenoh_io"}
        assert type(h["tick"]) is bool and type(h["comm"]) is bool
        assert type(h["zenoh_io"]) is int and h["zenoh_io"] >= 0
        with TraineeClient(endpoint, "slices-1") as c:
            a = np.array(c.create()["entry_m"])
            hover = a - [0.0, 0.0, 5e-3]

            def rescanned() -> bool:
                # The comm thread looks for new I/O threads at its once-a-second housekeeping
                # after the number of sessions changed. Poses keep the session from going idle.
                c.send_pose(hover, (1.0, 0.0, 0.0, 0.0), False, 0.0)
                threads = _sched(prefixes)
                comm_sliced = any(sl == SLICE_NS for k, (_, sl) in threads.items() if k.startswith("dhg-comm/"))
                n = srv.health()["short_slices"]["zenoh_io"]
                return n == io_sliced(threads) and (not comm_sliced or n >= 2)

            wait_until(rescanned, 15.0, "the I/O threads' slices reported as the kernel shows them")
            health = srv.health()
            threads = _sched(prefixes)
    finally:
        srv.stop()
    h = health["short_slices"]
    print(h, threads)
    comm = [v for k, v in threads.items() if k.startswith("dhg-comm/")]
    tick = [v for k, v in threads.items() if k.startswith("dhg-tick/")]
    assert len(comm) == 1 and len(tick) == 1
    # On any kernel: SCHED_FIFO (policy 1) is reported as the kernel has it, and such a tick
    # thread is left in its class, not moved to the fair class for a slice.
    assert health["tick_realtime"] == (tick[0][0] == os.SCHED_FIFO)
    # The poses' threads run the ticks (the default): the tick thread does not take SCHED_FIFO,
    # even where it may (decision 0033; cargo's engine tests check that it takes it when asked).
    assert health["tick_on"] == "pose" and tick[0][0] != os.SCHED_FIFO
    if health["tick_realtime"]:
        assert not h["tick"], "a SCHED_FIFO tick thread must not be moved to the fair class"
    if comm[0][1] is None:
        pytest.skip("this kernel (before 6.6) does not show a thread's slice in /proc: the report cannot be checked")
    # The kernel shows slices: the report must match them.
    assert h["comm"] == (comm[0][1] == SLICE_NS)
    assert h["tick"] == (tick[0][1] == SLICE_NS)
    assert h["zenoh_io"] == io_sliced(threads)
    granted, why = _kernel_grants_short_slices()
    if not granted:
        assert not h["comm"] and h["zenoh_io"] == 0, "slices reported where the kernel grants none"
        pytest.skip(f"the kernel grants no custom slice ({why}): that the server asks for one is untestable here")
    # The kernel grants them: the server must have asked for them, and found Zenoh's threads.
    assert h["comm"], "the force publisher did not get the short slice"
    assert h["tick"] or health["tick_realtime"], "the tick thread has neither SCHED_FIFO nor the short slice"
    assert h["zenoh_io"] >= 2, "Zenoh's receive and transmit threads were not found"


def test_sessions_are_limited_and_controlled(engine):
    info = engine.control("a", {"op": "create", "guidance_gain": 0.5})
    assert info["created"] and info["guidance_gain"] == 0.5
    engine.control("b", {"op": "create"})
    with pytest.raises(EngineError, match="session"):
        engine.control("c", {"op": "create"})  # two slots only
    assert sorted(engine.sessions()) == ["a", "b"]
    assert engine.health()["session_ids"] == ["a", "b"]
    with pytest.raises(InvalidInputError):
        engine.control("a", {"op": "set_guidance", "gain": float("nan")})
    # A NaN or infinity anywhere is refused, naming where, not read as "not given" (JSON's null).
    with pytest.raises(InvalidInputError, match="guidance_gain: NaN is not a finite number"):
        engine.control("c", {"op": "create", "guidance_gain": float("nan")})
    with pytest.raises(InvalidInputError, match="gain: inf is not a finite number"):
        engine.control("a", {"op": "set_guidance", "mode": "brake", "gain": float("inf")})
    with pytest.raises(InvalidInputError, match=r"entry_m\[1\]: NaN"):
        engine.control("a", {"op": "set_path", "entry_m": [0.0, float("nan"), 0.0], "target_m": [0.0, 0.0, 0.1]})
    assert "c" not in engine.sessions()
    with pytest.raises(InvalidInputError, match="burr_radius_m"):
        engine.control("a", {"op": "set_drill", "burr_radius_m": -1e-3})
    assert engine.control("b", {"op": "set_drill", "burr_radius_m": 1.5e-3})["burr_radius_m"] == 1.5e-3
    assert engine.control("a", {"op": "info"})["burr_radius_m"] == 1.25e-3, "a refusal changed a's burr"
    with pytest.raises(InvalidInputError, match="id"):
        engine.control("bad id!", {"op": "create"})
    engine.control("a", {"op": "close"})
    assert engine.sessions() == ["b"]
    # A slot is free again; a create with a bad value is refused whole and takes no slot.
    with pytest.raises(InvalidInputError, match="gain"):
        engine.control("c", {"op": "create", "guidance_gain": 9.0})
    with pytest.raises(InvalidInputError, match="burr_radius_m"):
        engine.control("c", {"op": "create", "burr_radius_m": 1.0})
    assert engine.sessions() == ["b"], "a refused create left a session behind"


def test_session_info_reports_the_planned_layers_along_its_path(engine, coarse_phantom):
    vol, path = coarse_phantom.volume, coarse_phantom.path
    info = engine.control("a", {"op": "create"})
    step = info["path_layer_step_m"]
    # The layers as numpy samples them from the volume, one sample per step from A.
    depths = np.arange(0.0, path.length_m + step / 2, step)
    ids = vol.layer_at(path.point_at(depths))
    names = [Layer(int(i)).name.lower() for i in ids]
    boundaries = [0, *(i for i in range(1, len(ids)) if ids[i] != ids[i - 1]), len(ids)]
    expected = [(names[a], depths[a], depths[b - 1]) for a, b in itertools.pairwise(boundaries)]
    got = [(r["layer"], r["start_m"], r["end_m"]) for r in info["path_layers"]]
    assert [g[0] for g in got] == [e[0] for e in expected]
    assert np.allclose([g[1:] for g in got], [e[1:] for e in expected], atol=1e-12)
    assert "cortical" in [g[0] for g in got]
    # The trainee reads the planned breakthrough off it, as the offline surgeons read the CT.
    planned = planned_depth_from_info(info)
    assert planned is not None
    assert planned == pytest.approx(planned_breakthrough_depth_m(vol, path, info["burr_radius_m"]), abs=1e-12)
    # A wider burr's front reaches the end of the cortex sooner.
    wider = engine.control("a", {"op": "set_drill", "burr_radius_m": 2e-3})
    assert planned_depth_from_info(wider) == pytest.approx(planned - (2e-3 - 1.25e-3), abs=1e-12)
    # A path through air has no cortex to plan for.
    far = [1.0, 1.0, 1.0]
    air = engine.control("a", {"op": "set_path", "entry_m": far, "target_m": [1.0, 1.0, 1.01]})
    assert {r["layer"] for r in air["path_layers"]} == {"outside"}
    assert planned_depth_from_info(air) is None
    assert planned_depth_from_info({"entry_m": far, "target_m": far}) is None  # a server without layers
    # A path of a thousand kilometres through the bone is sampled only where the volume is.
    long = engine.control("a", {"op": "set_path", "entry_m": list(path.entry_m), "target_m": [1e6, 0.0, 0.0]})
    assert long["path_layers"][-1]["layer"] == "outside" and long["path_layers"][-1]["end_m"] > 9.9e5


def test_xray_of_a_session_and_bad_timeouts(engine):
    engine.control("x", {"op": "create"})
    top, front, side = engine.xray("x", 2.0)
    assert top.ndim == front.ndim == side.ndim == 2 and top.max() > 0
    with pytest.raises(InvalidInputError, match="timeout_s"):
        engine.xray("x", float("nan"))
    with pytest.raises(EngineError):
        engine.xray("nobody", 0.5)


def test_stop_is_idempotent_and_later_calls_fail_clearly(engine):
    engine.stop()
    engine.stop()
    assert not engine.running
    with pytest.raises(EngineError, match="stopped"):
        engine.health()


def test_the_scheduling_hint_suggests_spinning_only_where_it_helps():
    sleeping = {"tick_realtime": False, "tick_wait": "sleep", "tick_on": "thread"}
    assert scheduling_hint({**sleeping, "tick_realtime": True}, 16) is None
    # Ticks on the poses' threads: the tick thread keeps normal scheduling on purpose (0033).
    assert scheduling_hint({**sleeping, "tick_on": "pose"}, 2) is None
    assert scheduling_hint({**sleeping, "tick_on": "pose"}, 16) is None
    assert scheduling_hint({**sleeping, "tick_wait": "spin"}, 16) is None
    many = scheduling_hint(sleeping, 16)
    assert many is not None and "--wait spin" in many and "16-core" in many
    few = scheduling_hint(sleeping, 2)
    assert few is not None and "spin" not in few and "CAP_SYS_NICE" in few and "slice" not in few
    sliced = scheduling_hint({**sleeping, "short_slices": {"tick": True, "comm": True, "zenoh_io": 4}}, 2)
    assert sliced is not None and sliced.startswith(few) and "0.1 ms slice" in sliced


def test_sessions_beyond_the_slots_and_bad_ids_are_refused_and_counted(coarse_phantom):
    """``refused.sessions`` counts every pose that could not get a session: all slots taken, or an
    id the engine refuses; the session that holds the slot is not disturbed."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    conf = zenoh_config_json5([endpoint], mode="router")
    srv = start_engine(coarse_phantom.volume, coarse_phantom.path, conf, ServerSettings(max_sessions=1))
    try:
        with TraineeClient(endpoint, "holder") as a, TraineeClient(endpoint, "latecomer") as b:
            entry = np.array(a.create()["entry_m"])
            pose = (entry - [0.0, 0.0, 5e-3], (1.0, 0.0, 0.0, 0.0), False, 0.0)
            a.send_pose(*pose)
            wait_until(lambda: srv.sessions() == ["holder"], 10.0, "the holder's session")
            before = srv.health()["refused"]["sessions"]
            for _ in range(20):
                b.send_pose(*pose)
            b._z.put("dhg/session/.hidden/pose", protocol.encode_pose(1, 1, pose[0], pose[1], False, 0.0))
            wait_until(lambda: srv.health()["refused"]["sessions"] - before == 21, 10.0, "21 refusals counted")
            a.send_pose(*pose)
            wait_until(lambda: a.force is not None, 10.0, "the holder's force")
            assert srv.sessions() == ["holder"]
    finally:
        srv.stop()
