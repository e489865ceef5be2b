"""The native server's Python surface, in-process: settings are checked, bad values are refused
with a clear error, and it stops cleanly (no Zenoh peers involved beyond loopback)."""

from __future__ import annotations

import itertools
import platform
import time
from pathlib import Path

import numpy as np
import pytest

from dhg import _bone_sim, serve
from dhg.client import TraineeClient
from dhg.errors import EngineError, InvalidInputError
from dhg.layers import Layer
from dhg.live_demo import free_port
from dhg.surgeons import planned_breakthrough_depth_m
from dhg.trainee import planned_depth_from_info


@pytest.fixture()
def engine(coarse_phantom):
    conf = serve.zenoh_config_json5([f"tcp/127.0.0.1:{free_port()}"], mode="router")
    srv = serve.start_engine(coarse_phantom.volume, coarse_phantom.path, conf, serve.ServerSettings(max_sessions=2))
    yield srv
    srv.stop()


def test_unknown_server_settings_are_refused_with_the_allowed_keys(coarse_phantom):
    conf = serve.zenoh_config_json5([f"tcp/127.0.0.1:{free_port()}"], mode="router")
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


def test_a_spinning_engine_serves_a_zenoh_client_says_so_sleeps_when_idle_and_stops(coarse_phantom):
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    conf = serve.zenoh_config_json5([endpoint], mode="router")
    srv = serve.start_engine(coarse_phantom.volume, coarse_phantom.path, conf, serve.ServerSettings(wait="spin"))
    try:
        # Without a session it sleeps: two spinning threads would use about 1 s of CPU in 0.5 s.
        cpu0, wall0 = time.process_time(), time.monotonic()
        time.sleep(0.5)
        idle_cpu = (time.process_time() - cpu0) / (time.monotonic() - wall0)
        assert idle_cpu < 0.3, f"an idle spinning engine used {idle_cpu:.2f} cores"
        forces: list[dict] = []
        with TraineeClient(endpoint, "spin-1", on_force=forces.append) as c:
            a = np.array(c.create()["entry_m"])
            t0 = time.monotonic()
            for k in range(300):  # 0.3 s at 1 kHz, hovering 5 mm off A with the drill off
                c.send_pose(a - [0.0, 0.0, 5e-3], (1.0, 0.0, 0.0, 0.0), False, 0.0)
                time.sleep(max(0.0, t0 + (k + 1) * 1e-3 - time.monotonic()))
            time.sleep(0.1)
            h = srv.health()
        echoed = {m["pose_seq"] for m in forces}
        # Lenient: on a 2-core machine the two spinning threads share it with this client.
        assert len(echoed) >= 150, f"forces echoed {len(echoed)} of 300 poses"
        assert all(np.isfinite(m["force_n"]).all() for m in forces)
        assert h["tick_wait"] == "spin"
        assert h["ticks"] <= (time.monotonic() - t0) * 1000 + 100, "spinning ticked faster than 1 kHz"
    finally:
        srv.stop()
    assert not srv.running


def _slices_ns(prefixes: tuple[str, ...]) -> dict[str, int | None]:
    """Threads of this process named with one of ``prefixes`` → the EEVDF slice (ns) the kernel
    reports for each (``None`` where it reports none: kernels before 6.6)."""
    out: dict[str, int | None] = {}
    for task in Path("/proc/self/task").iterdir():
        name = (task / "comm").read_text().strip()
        if name.startswith(prefixes):
            line = next((ln for ln in (task / "sched").read_text().splitlines() if ln.startswith("se.slice")), None)
            out[f"{name}/{task.name}"] = int(line.split(":")[1]) if line else None
    return out


def _kernel_at_least(major: int, minor: int) -> bool:
    """Whether this Linux kernel is ``major.minor`` or later."""
    release = platform.release().split("-")[0].split(".")
    try:
        return (int(release[0]), int(release[1])) >= (major, minor)
    except (IndexError, ValueError):
        return False


@pytest.mark.skipif(not Path("/proc/self/task").is_dir(), reason="reads /proc (Linux)")
def test_the_short_slices_reported_are_the_ones_the_kernel_gave(coarse_phantom):
    # The comm thread and Zenoh's I/O threads ask for a 0.1 ms slice (no privilege needed on
    # Linux 6.12+); the tick thread too when it has no SCHED_FIFO. Health must say what happened.
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    conf = serve.zenoh_config_json5([endpoint], mode="router")
    srv = serve.start_engine(coarse_phantom.volume, coarse_phantom.path, conf, serve.ServerSettings())
    try:
        assert set(srv.health()["short_slices"]) == {"tick", "comm", "zenoh_io"}
        with TraineeClient(endpoint, "slices-1") as c:
            a = np.array(c.create()["entry_m"])
            for _ in range(50):
                c.send_pose(a - [0.0, 0.0, 5e-3], (1.0, 0.0, 0.0, 0.0), False, 0.0)
                time.sleep(1e-3)
            time.sleep(1.2)  # the comm thread looks for new I/O threads once a second
            health = srv.health()
            threads = _slices_ns(("dhg-comm", "dhg-tick", "rx-", "tx-"))
    finally:
        srv.stop()
    h = health["short_slices"]
    print(h, threads)
    comm = [v for k, v in threads.items() if k.startswith("dhg-comm/")]
    assert len(comm) == 1
    if _kernel_at_least(6, 12):  # custom slices exist: they must have been asked for
        assert h["comm"] and comm[0] == 100_000
    if comm[0] is not None:  # the kernel shows slices: the report must match them
        assert h["comm"] == (comm[0] == 100_000)
        io = [v for k, v in threads.items() if k.startswith(("rx-", "tx-"))]
        assert h["zenoh_io"] == sum(v == 100_000 for v in io)
        if h["comm"]:
            assert h["zenoh_io"] >= 2, "Zenoh's receive and transmit threads were not found"
    assert not (health["tick_realtime"] and h["tick"]), "a SCHED_FIFO tick thread must not be moved to the fair class"


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
    sleeping = {"tick_realtime": False, "tick_wait": "sleep"}
    assert serve.scheduling_hint({**sleeping, "tick_realtime": True}, 16) is None
    assert serve.scheduling_hint({**sleeping, "tick_wait": "spin"}, 16) is None
    many = serve.scheduling_hint(sleeping, 16)
    assert many is not None and "--wait spin" in many and "16-core" in many
    few = serve.scheduling_hint(sleeping, 2)
    assert few is not None and "spin" not in few and "CAP_SYS_NICE" in few and "slice" not in few
    sliced = serve.scheduling_hint({**sleeping, "short_slices": {"tick": True, "comm": True, "zenoh_io": 4}}, 2)
    assert sliced is not None and sliced.startswith(few) and "0.1 ms slice" in sliced
