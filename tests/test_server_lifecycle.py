"""A server's and its clients' lives end to end: crashes, Ctrl-C, a lost model worker, bad flags
and configuration files, no server to talk to. Each test starts (or fails to start) its own processes."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from dhg.core import protocol
from dhg.learning.model_file import read_model_meta
from dhg.learning.profiles import DemoProfiles
from dhg.learning.weights import default_model_path
from dhg.live.client import TraineeClient
from dhg.live.process import ServerProcess, free_port
from dhg.live.services import MODEL_NICE
from support import ctrl_c, hold_until, listening_tcp_ports, read_until, readline_within, record_process, thread_nices
from support import entry as _entry
from support import serve as _serve
from support import stream as _stream
from support import wait_until as _wait


def test_record_survives_a_server_crash_and_keeps_everything_on_ctrl_c(tmp_path):
    from dhg.data.dataset import load_dataset, load_raw

    proc, endpoint = _serve("--idle-timeout", "5.0")
    out = tmp_path / "rec"
    started = time.monotonic()
    rec = record_process(
        endpoint, "--session", "crash-1", "--out", str(out), "--raw", "--flush-every", "0.5", "--status-every", "0.5"
    )
    try:
        assert "recording" in readline_within(rec, 60.0, "the recorder's start")
        with TraineeClient(endpoint, "crash-1") as c:
            a, d, q = _entry(c)
            _stream(c, a + d * np.linspace(-2e-3, 4e-3, 1500)[:, None], q)
            states = len(c.states)
            proc.proc.send_signal(signal.SIGKILL)  # the server dies mid-session
            proc.proc.wait(timeout=10)
            killed = time.monotonic() - started
        # The recorder keeps running against a dead server: it still reports 1 s after the kill
        # (its status clock starts after `started`, and prints whole seconds).
        while True:
            line = read_until(rec, " s: ")[-1]
            if float(line.split(" s:")[0]) >= killed + 1.5:
                break
        assert rec.poll() is None, "the recorder died with the server"
        output = ctrl_c(rec)  # a final flush, then a clean exit
    finally:
        for p in (rec, proc.proc):
            if p.poll() is None:
                p.kill()
                p.wait()
        proc.stop()
    ds = load_dataset(out)
    (ep,) = ds.episodes
    # Every 10 Hz state the trainee saw before the crash is in the dataset (the recorder is a
    # second subscriber: allow for one record in flight at the kill).
    assert len(ep.times_s) >= states - 1 >= 10, (len(ep.times_s), states)
    assert np.ptp(ep.features[:, 7]) > 0.5e-3, "the recorded tip never moved"
    # Ctrl-C joined the 1 kHz parts into one raw.parquet.
    assert sorted(ds.card["files"]) == ["raw.parquet", "records.parquet"]
    assert "1 kHz stream:" in output
    raw = load_raw(ds)
    # The server sends the 1 kHz ticks in batches of 100 at 10 Hz: the batch it was filling when
    # it was killed never left it, so every tick up to the last batch sent is kept, without a gap,
    # and the last kept tick is within one batch of the last 10 Hz record.
    ticks = raw.column("tick").to_numpy()
    assert np.array_equal(ticks, np.arange(ticks[0], ticks[0] + len(ticks))), "a gap in the raw ticks"
    assert len(ticks) >= 1500 - 2 * 100, len(ticks)  # 1500 streamed; the batch in flight; the first partial one
    assert ticks[-1] * 1e-3 >= ep.times_s[-1] - 0.1, (ticks[-1], ep.times_s[-1])


def test_trainee_course_refuses_bad_flags():
    for flags, needle in (
        (["--attempts", "0"], "--attempts"),
        (["--probe-every", "2"], "--probe-every needs --fading"),
        (["--fading", "--guidance", "off"], "--fading"),
    ):
        r = subprocess.run(
            [sys.executable, "-m", "dhg.cli.main", "trainee", *flags], capture_output=True, text=True, timeout=60
        )
        assert r.returncode == 3 and needle in r.stderr and "Traceback" not in r.stderr, (flags, r.stderr)


def test_trainee_without_a_server_fails_clearly():
    r = subprocess.run(
        [
            sys.executable,
            "-m",
            "dhg.cli.main",
            "trainee",
            "--connect",
            f"tcp/127.0.0.1:{free_port()}",
            "--duration",
            "1",
        ],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert r.returncode == 5, r.stderr
    assert "error:" in r.stderr and "Traceback" not in r.stderr
    bad = subprocess.run(
        [sys.executable, "-m", "dhg.cli.main", "trainee", "--drill-mm", "-2"],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert bad.returncode == 3 and "--drill-mm" in bad.stderr and "Traceback" not in bad.stderr, bad.stderr


def test_serve_with_a_missing_model_exits_with_a_clear_message(tmp_path):
    r = subprocess.run(
        [sys.executable, "-m", "dhg.cli.serve", "--model", str(tmp_path / "nope.ts"), "--listen", "tcp/127.0.0.1:1"],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert r.returncode == 3
    assert "no such model file" in r.stderr and "Traceback" not in r.stderr


def test_killing_the_model_worker_fades_guidance_and_a_restart_brings_it_back():
    engine, endpoint = _serve("--role", "sim", "--model-timeout", "0.1")
    worker, _ = _serve("--role", "model", endpoint=endpoint)
    stop = threading.Event()
    try:
        with TraineeClient(endpoint, "fault-1") as c:
            a, d, q = _entry(c)

            def hold() -> None:  # keep the session fresh: 1 kHz poses pressing on the cortex
                p = a + d * 0.5e-3
                while not stop.is_set():
                    c.send_pose(p, q, True, 1250.0)
                    time.sleep(0.001)

            pump = threading.Thread(target=hold, daemon=True)
            pump.start()
            _wait(lambda: c.force is not None and c.force["flags"] & protocol.FLAGS["model_available"], 5.0)
            # The engine alone guides with the corridor of the bundled model's expert profiles, as
            # --role all does, read from the file's metadata without loading torch; it names no
            # model of its own (the workers serve theirs).
            about = c._json(c.keys["about"])
            profiles = DemoProfiles.from_dict(read_model_meta(default_model_path())["profiles"])
            assert about["guidance"]["params"]["corridor_profile_n_per_m"] == pytest.approx(profiles.corridor_n_per_m)
            assert about["model"] is None
            # The worker serves the same model: its check of the engine's corridor says so.
            agree = "note: the engine's corridor follows this model's expert profiles"
            _wait(lambda: agree in worker.lines, 30.0, "the worker's corridor check")
            assert not any(line.startswith("warning:") for line in worker.lines), worker.lines
            assert "libtorch" not in Path(f"/proc/{engine.proc.pid}/maps").read_text()
            assert "libtorch" in Path(f"/proc/{worker.proc.pid}/maps").read_text(), "the check can tell"
            # ONNX Runtime runs the passes on CPU by default, TorchScript when asked (below).
            assert any("(onnxruntime)" in line for line in worker.lines), worker.lines
            # The worker's forward passes run at MODEL_NICE (decisions 0026, 0038); its other threads keep 0.
            assert thread_nices(worker.proc.pid) == {0, MODEL_NICE}
            # It reached the engine as a client: it opened no port that could be reached around it.
            assert listening_tcp_ports(worker.proc.pid) == set()
            assert listening_tcp_ports(engine.proc.pid), "the check can tell"
            worker.proc.send_signal(signal.SIGKILL)
            assert worker.stop() == -signal.SIGKILL
            _wait(lambda: not c.force["flags"] & protocol.FLAGS["model_available"], 15.0, "model unavailable")
            _wait(lambda: np.linalg.norm(c.force["guidance_n"]) == 0.0, 15.0, "guidance faded to zero")
            n0 = c.forces_received
            _wait(lambda: c.forces_received - n0 >= 400, 15.0, "400 more forces without the model")
            assert c.force["flags"] & protocol.FLAGS["model_available"] == 0
            worker, _ = _serve("--role", "model", "--model-nice", "7", "--executor", "torchscript", endpoint=endpoint)
            _wait(lambda: c.force["flags"] & protocol.FLAGS["model_available"], 30.0, "the restarted model answering")
            assert thread_nices(worker.proc.pid) == {0, 7}
            assert any("(torchscript)" in line for line in worker.lines), worker.lines
            stop.set()
            pump.join()
    finally:
        stop.set()
        worker.stop()
        code = engine.stop()
    assert code == 0


def test_ctrl_c_stops_a_busy_server_cleanly_with_a_zenoh_config_file(tmp_path):
    """Ctrl-C while a trainee streams: the server closes its sessions and exits 0, promptly."""
    conf = tmp_path / "zenoh.json5"
    conf.write_text("{ scouting: { multicast: { enabled: false } }, timestamping: { enabled: { router: true } } }")
    proc, endpoint = _serve("--zenoh-config", str(conf))
    stop = threading.Event()
    with TraineeClient(endpoint, "busy-1") as c:
        a, d, q = _entry(c)

        def pump() -> None:
            while not stop.is_set():
                c.send_pose(a, q, True, 1250.0)
                time.sleep(0.001)

        t = threading.Thread(target=pump, daemon=True)
        t.start()
        _wait(lambda: c.forces_received > 200, 10.0)
        proc.proc.send_signal(signal.SIGINT)
        code = proc.proc.wait(timeout=30)  # a generous deadline, not a speed target
        stop.set()
        t.join()
    assert proc.stop() == code == 0
    assert any("closing 1 session(s)" in line for line in proc.lines), proc.lines[-5:]
    assert proc.lines[-1] == "dhg-serve stopped"


def test_a_bad_zenoh_config_file_is_a_clear_error(tmp_path):
    conf = tmp_path / "broken.json5"
    conf.write_text("{ this is not json5")
    listen = f"tcp/127.0.0.1:{free_port()}"
    r = subprocess.run(
        [sys.executable, "-m", "dhg.cli.serve", "--zenoh-config", str(conf), "--listen", listen],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert r.returncode == 3, r.stderr
    assert "zenoh config" in r.stderr and "Traceback" not in r.stderr


@pytest.mark.parametrize(
    "command",
    [["dhg.cli.serve"], ["dhg.cli.main", "trainee", "--duration", "1"], ["dhg.cli.main", "view", "--duration", "1"]],
    ids=["dhg-serve", "trainee", "view"],
)
def test_an_unreadable_zenoh_runtime_is_bad_input_not_a_panic(command, monkeypatch):
    """Zenoh reads ``ZENOH_RUNTIME`` (its runtime threads, decision 0031) at a process's first
    session and panics on what it cannot parse (tokio on zero threads): the engine (dhg-serve) and
    every Python client say what is wrong instead, exit 3. A readable value starts them as usual."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    flag = "--listen" if command == ["dhg.cli.serve"] else "--connect"
    for bad, reason in (('(rx: (worker_threads: "two"))', "ExpectedInteger"), ("(app: (worker_threads: 0))", "app")):
        r = subprocess.run(
            [sys.executable, "-m", *command, flag, endpoint],
            env=dict(os.environ, ZENOH_RUNTIME=bad),
            capture_output=True,
            text=True,
            timeout=120,
        )
        assert r.returncode == 3, r.stderr
        assert "invalid ZENOH_RUNTIME" in r.stderr and reason in r.stderr, r.stderr
        assert "panicked" not in r.stderr and "Traceback" not in r.stderr, r.stderr
    monkeypatch.setenv("ZENOH_RUNTIME", "(rx: (worker_threads: 1))")
    server, endpoint = _serve()
    try:
        if command != ["dhg.cli.serve"]:
            r = subprocess.run(
                [sys.executable, "-m", *command, "--connect", endpoint], capture_output=True, text=True, timeout=120
            )
            assert r.returncode == 0, r.stderr
    finally:
        assert server.stop() == 0


@pytest.mark.parametrize(
    "command",
    [
        ["trainee", "--duration", "1"],
        ["record", "--session", "x-1", "--out", "OUT", "--duration", "1"],
        ["study", "--out", "OUT", "--seeds", "1", "--arms", "none", "--train", "1", "--live", "ENDPOINT"],
    ],
    ids=["trainee", "record", "study-live"],
)
def test_every_networked_command_reads_its_zenoh_config(tmp_path, command):
    """Issue 21, item 7: dhg trainee, record and study --live take --zenoh-config (and say what is
    wrong with a broken one, exit 3, instead of ignoring it)."""
    conf = tmp_path / "broken.json5"
    conf.write_text("{ this is not json5")
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    args = [a.replace("OUT", str(tmp_path / "out")).replace("ENDPOINT", endpoint) for a in command]
    if "--live" not in args:
        args += ["--connect", endpoint]
    r = subprocess.run(
        [sys.executable, "-m", "dhg.cli.main", *args, "--zenoh-config", str(conf)],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert r.returncode == 3, r.stderr
    assert "zenoh config" in r.stderr and "Traceback" not in r.stderr


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="per-thread nice values are Linux's")
def test_a_screen_runs_at_nice_10_in_every_thread_unless_told_otherwise():
    """``dhg view`` yields the cores to the haptic loop it shares a machine with (decision 0027)."""
    server, endpoint = _serve()
    try:
        for flags, expected in (((), {10}), (("--nice", "3"), {3})):
            with subprocess.Popen(
                [sys.executable, "-m", "dhg.cli.main", "view", "--connect", endpoint, "--port", "0", *flags],
                stdout=subprocess.PIPE, text=True,
            ) as view:  # fmt: skip
                try:
                    line = readline_within(view, 60.0, "the viewer's ready line")
                    assert "dhg view:" in line, line
                    assert thread_nices(view.pid) == expected
                finally:
                    view.send_signal(signal.SIGINT)
                    assert view.wait(timeout=30) == 0
    finally:
        assert server.stop() == 0


def _with_other_profiles(model: Path, out: Path) -> Path:
    """A copy of ``model`` whose stored expert profiles are halved (its metadata rewritten with
    zipfile alone: the engine reads nothing else of it)."""
    import json
    import zipfile

    with zipfile.ZipFile(model) as src, zipfile.ZipFile(out, "w") as dst:
        for item in src.infolist():
            data = src.read(item.filename)
            if item.filename.endswith("/extra/dhg.json"):
                meta = json.loads(data)
                meta["profiles"]["corridor_n_per_m"] = [0.5 * k for k in meta["profiles"]["corridor_n_per_m"]]
                data = json.dumps(meta).encode()
            dst.writestr(item, data)
    return out


def test_a_worker_warns_when_the_engines_corridor_is_another_models(tmp_path):
    """The engine alone (--role sim) takes its corridor from its own --model: a worker serving
    another model says so, once the engine answers."""
    other = _with_other_profiles(default_model_path(), tmp_path / "other.ts")
    engine, endpoint = _serve("--role", "sim", "--model", str(other))
    worker = None
    try:
        worker, _ = _serve("--role", "model", endpoint=endpoint)
        _wait(lambda: any(line.startswith("warning:") for line in worker.lines), 60.0, "the worker's warning")
        (warning,) = [line for line in worker.lines if line.startswith("warning:")]
        assert "other expert profiles" in warning and "--model" in warning, warning
    finally:
        if worker is not None:
            assert worker.stop() == 0
        assert engine.stop() == 0


def test_one_worker_started_before_its_engines_serves_both_and_listens_nowhere():
    """A model worker may start first and serve several engines (`--connect` repeated): it reaches
    each once it is up, and opens no port of its own (as a peer left to Zenoh's defaults it would
    listen on a random one, around the engines' access control)."""
    endpoints = [f"tcp/127.0.0.1:{free_port()}" for _ in range(2)]
    worker = ServerProcess(
        ["--role", "model", "--connect", endpoints[0], "--connect", endpoints[1], "--status-every", "1"], echo=False
    )
    engines: list[ServerProcess] = []
    try:
        assert listening_tcp_ports(worker.proc.pid) == set()
        for endpoint in endpoints:
            engines.append(_serve("--role", "sim", endpoint=endpoint)[0])
        model_up = protocol.FLAGS["model_available"]
        for k, endpoint in enumerate(endpoints):
            with TraineeClient(endpoint, f"shared-worker-{k}") as c:
                a, d, q = _entry(c)
                hold_until(c, a + d * 0.5e-3, q, lambda m: m["flags"] & model_up, 60.0, f"engine {k}'s model")
                assert c.health(1.0)["model"]["workers"], "the worker is in this engine's pool"
        assert listening_tcp_ports(worker.proc.pid) == set()
    finally:
        assert worker.stop() == 0, worker.lines[-20:]
        for engine in engines:
            assert engine.stop() == 0
