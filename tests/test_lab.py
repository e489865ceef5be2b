"""The secure lab mode (``dhg lab-config``): TLS, passwords and access control, end to end over real
Zenoh sessions with certificates this test creates (openssl)."""

from __future__ import annotations

import json
import os
import shutil
import stat
import threading
import time

import numpy as np
import pytest
import zenoh

import dhg
from dhg.core import protocol
from dhg.core.errors import InvalidInputError, TransportError
from dhg.live.client import TraineeClient
from dhg.live.lab import acl, load_lab, write_lab
from dhg.live.process import ServerProcess, free_port
from support import Stylus, listening_tcp_ports, said, stream
from support import wait_until as _wait

pytestmark = pytest.mark.skipif(shutil.which("openssl") is None, reason="needs openssl to create certificates")

LAB = """
[server]
endpoint = "tls/localhost:{port}"
listen = "tls/127.0.0.1:{port}"
ca_certificate = "certs/ca.pem"
certificate = "certs/server.pem"
private_key = "certs/server-key.pem"
password = "server-secret-1"

[[station]]
name = "station-1"
password = "station-one-pw"

[[station]]
name = "station-2"
password = "station-two-pw"

[[instructor]]
name = "teacher"
password = "teacher-pw-1"

[[model_worker]]
name = "model-1"
password = "model-one-pw"
"""


@pytest.fixture(scope="module")
def lab(tmp_path_factory):
    root = tmp_path_factory.mktemp("lab")
    port = free_port()
    (root / "lab.toml").write_text(LAB.format(port=port))
    write_lab(root / "lab.toml", root / "out", certs=True)
    return root, f"tls/localhost:{port}", f"tls/127.0.0.1:{port}"


def test_the_lab_file_gives_each_identity_only_its_own_keys(lab):
    root, _, _ = lab
    parsed = load_lab(root / "lab.toml")
    rules = {r["id"]: r for r in acl(parsed)["rules"]}
    # A station publishes only its own poses; no client may put a force, guidance or state.
    assert rules["station:station-1:pose"]["key_exprs"] == [
        "dhg/session/station-1/pose",
        "dhg/session/station-1-$*/pose",
    ]
    for r in rules.values():
        if "put" in r["messages"] and "ingress" in r["flows"]:
            assert all(k.endswith("/pose") for k in r["key_exprs"]), r
    assert all(
        "station-2" not in k for r in rules.values() if r["id"].startswith("station:station-1:") for k in r["key_exprs"]
    )
    assert acl(parsed)["default_permission"] == "deny"
    for f in (root / "out").iterdir():  # passwords inside: the owner's only
        assert stat.S_IMODE(f.stat().st_mode) == 0o600
    # The keys --make-certs created are the owner's only, the certificates everyone's.
    modes = {f.name: stat.S_IMODE(f.stat().st_mode) for f in (root / "certs").glob("*.pem")}
    assert modes == {"ca.pem": 0o644, "ca-key.pem": 0o600, "server.pem": 0o644, "server-key.pem": 0o600}
    conf = json.loads((root / "out" / "station-1.json5").read_text())
    assert conf["transport"]["auth"]["usrpwd"]["user"] == "station-1" and conf["mode"] == "client"


def test_a_lab_file_with_mistakes_is_refused_with_the_reason(tmp_path):
    for text, match in (
        ('[server]\nendpoint = "tcp/1.2.3.4:7447"', "tls/ endpoint"),
        (LAB.format(port=1).replace('name = "station-2"', 'name = "station-1"'), "used twice"),
        (LAB.format(port=1).replace('"station-one-pw"', '"short"'), "at least 8"),
        (LAB.format(port=1).replace('name = "teacher"', 'name = "../x"'), "name"),
        (LAB.format(port=1).replace('name = "station-2"', 'name = "station-1-b"'), "would drive station"),
    ):
        (tmp_path / "lab.toml").write_text(text)
        with pytest.raises(InvalidInputError, match=match):
            load_lab(tmp_path / "lab.toml")


def _allowed(rules: list[dict], rid_prefix: str, message: str, key: str) -> bool:
    """Whether a rule of ``rid_prefix`` allows ``message`` on ``key`` (Zenoh's key inclusion)."""
    return any(
        r["id"].startswith(rid_prefix) and message in r["messages"] and zenoh.KeyExpr(k).includes(zenoh.KeyExpr(key))
        for r in rules
        for k in r["key_exprs"]
    )


def test_recovery_and_read_only_keys_are_allowed_and_nothing_more(tmp_path):
    """What key inclusion the router applies: a recorder's recovery of the advanced publishers'
    streams (heartbeats, liveliness tokens and cache queries under ``<stream>/@adv/...``, a
    verbatim chunk ``**`` does not match) is allowed on one's own sessions; an instructor reads
    every session but cannot change one; rule ids stay unique whatever the names."""
    (tmp_path / "lab.toml").write_text(LAB.format(port=1).replace('name = "station-2"', 'name = "instructor"'))
    parsed = load_lab(tmp_path / "lab.toml")
    rules = acl(parsed)["rules"]
    ids = [r["id"] for r in rules]
    assert len(ids) == len(set(ids)), "a station named instructor shares no rule id"
    heartbeat = "dhg/session/{}/ticks/@adv/pub/abcd/1/_"
    for who, sid in (("station:station-1:", "station-1"), ("station:station-1:", "station-1-a"), ("instructors:", "x")):
        assert _allowed(rules, who, "put", heartbeat.format(sid)), (who, sid)
        assert _allowed(rules, who, "liveliness_token", heartbeat.format(sid)), (who, sid)
        assert _allowed(rules, who, "query", f"dhg/session/{sid}/state/@adv/pub/abcd/1/_"), (who, sid)
        assert _allowed(rules, who, "query", f"dhg/session/{sid}/info"), (who, sid)
    assert not _allowed(rules, "station:station-1:", "put", heartbeat.format("instructor"))
    assert not _allowed(rules, "station:instructor:", "put", heartbeat.format("station-1"))
    # An instructor changes nothing: no control, no pose, no model query.
    for message, key in (
        ("query", "dhg/session/station-1/control"),
        ("put", "dhg/session/station-1/pose"),
        ("query", "dhg/model/predict"),
        ("query", "dhg/model/workers/model-1/predict"),
    ):
        assert not _allowed(rules, "instructors:", message, key), (message, key)


def _client(root, endpoint, name, session_id=None, **kw) -> TraineeClient:
    conf = root / "out" / f"{name}.json5"
    return TraineeClient(endpoint, session_id or name, zenoh_config_file=str(conf), **kw)


def _drill_path(c: TraineeClient, poses: int) -> np.ndarray:
    """Creates the client's session; returns ``poses`` positions (m) a millisecond apart, from
    3 mm before A into the bone at 1 mm/s for 2 mm."""
    info = c.create()
    a, b = np.array(info["entry_m"]), np.array(info["target_m"])
    d = (b - a) / np.linalg.norm(b - a)
    return a + d * (-3e-3 + 1e-3 * np.minimum(np.arange(poses) / 1000, 2.0))[:, None]


def _stream(c: TraineeClient, seconds: float) -> None:
    """Drills for ``seconds`` worth of poses at 1 kHz (on absolute deadlines: a loaded machine
    sends them late, not fewer)."""
    stream(c, _drill_path(c, int(seconds * 1000)), (1.0, 0.0, 0.0, 0.0))


def test_secure_mode_lets_each_identity_do_its_job_and_nothing_else(lab, tmp_path):
    root, endpoint, listen = lab
    server_conf = str(root / "out" / "server.json5")
    server = ServerProcess(
        ["--role", "sim", "--listen", listen, "--zenoh-config", server_conf, "--voxel-mm", "1.0"], echo=False
    )
    worker = None
    try:
        # An unauthenticated client (TLS, no password) is refused.
        anon = tmp_path / "anon.json5"
        conf = json.loads((root / "out" / "station-1.json5").read_text())
        del conf["transport"]["auth"]
        anon.write_text(json.dumps(conf))
        with pytest.raises(TransportError):
            TraineeClient(endpoint, "anon-1", zenoh_config_file=str(anon)).control("info", timeout_s=1.0)

        # A model worker identity serves the model.
        worker = ServerProcess(
            ["--role", "model", "--connect", endpoint, "--zenoh-config", str(root / "out" / "model-1.json5")],
            echo=False,
        )
        with _client(root, endpoint, "station-1") as s1, _client(root, endpoint, "station-2") as s2:
            # Station 1 tries to be the model: its queryable is not allowed, its replies never count.
            rogue_n = (0.0, 0.0, 2.5)

            def rogue(q):
                seqs, _ = protocol.decode_predict(q.payload.to_bytes())
                answers = (
                    protocol.encode_prediction(int(s), rogue_n, 0.0, "rogue", entry=i) for i, s in enumerate(seqs)
                )
                q.reply("dhg/model/predict", b"".join(answers))

            rogue_q = s1._z.declare_queryable("dhg/model/predict", rogue, complete=True)
            # ...and to join the worker pool: its token and queryable are refused as well.
            rogue_pool_q = s1._z.declare_queryable("dhg/model/workers/station-1/predict", rogue, complete=True)
            rogue_token = s1._z.liveliness().declare_token("dhg/model/workers/station-1")
            s2.create()
            seen_by_2: list[tuple] = []
            s2._on_force = lambda m: seen_by_2.append(m["force_n"])
            forged = protocol.encode("force", force_n=(0.0, 0.0, 0.123))
            stop = threading.Event()

            def forge():  # station 1 puts forces on station 2's key the whole time
                while not stop.is_set():
                    s1._z.put("dhg/session/station-2/force", forged)
                    time.sleep(0.005)

            t = threading.Thread(target=forge, daemon=True)
            t.start()
            streamer = threading.Thread(target=_stream, args=(s2, 3.0), daemon=True)
            streamer.start()
            _stream(s1, 3.0)
            streamer.join()
            stop.set()
            t.join()
            # Station 1 drilled its own session and was guided by the model worker.
            _wait(lambda: len(s1.guidance) >= 10, 10.0)
            assert s1.force is not None and s1.forces_received > 1000
            predicted = np.array([g["predicted_force_n"] for g in s1.guidance])
            assert not np.any(np.all(np.isclose(predicted, rogue_n, atol=1e-6), axis=1))
            # The pool holds the model worker, under its own name, and nobody else.
            assert [w["id"] for w in s1.health(1.0)["model"]["workers"]] == ["model-1"]
            # The worker may ask the server's about, to check the engine's corridor is its model's.
            agree = "note: the engine's corridor follows this model's expert profiles"
            _wait(lambda: agree in worker.lines, 30.0, "the worker's corridor check")
            # It listens on no port of its own: none in the clear, past the router's TLS,
            # passwords and access control (a peer with no listen endpoint).
            assert listening_tcp_ports(worker.proc.pid) == set()
            # Station 2 heard its own forces only: none of station 1's forgeries.
            assert len(seen_by_2) > 1000 and not any(abs(f[2] - 0.123) < 1e-6 for f in seen_by_2)
            # Station 1 cannot reset, re-gain or query station 2.
            for op in ("reset", "info"):
                with pytest.raises(TransportError):
                    s1._json("dhg/session/station-2/control", {"op": op}, timeout_s=1.0)
            for entity in (rogue_q, rogue_pool_q, rogue_token):
                entity.undeclare()
            # A station may ask what the server runs (a recording's card takes it).
            assert s1._json("dhg/server/about")["volume"]["spacing_m"] == [1e-3] * 3
        # The instructor reads every session.
        with _client(root, endpoint, "teacher", "teacher-view") as teacher:
            health = teacher.health(1.0)
            assert {"station-1", "station-2"} <= set(health["session_ids"])
            metrics = teacher._json("dhg/session/station-1/metrics")
            assert metrics["records"] > 0
            assert teacher._json("dhg/session/station-1/info")["session"] == "station-1"
            # ...and changes none: its control query is refused.
            with pytest.raises(TransportError):
                teacher._json("dhg/session/station-1/control", {"op": "reset"}, timeout_s=1.0)
            assert teacher._json("dhg/server/about")["dhg_version"] == dhg.__version__
    finally:
        if worker is not None:
            worker.stop()
        assert server.stop() == 0, said(server)


def test_dhg_lab_config_cli_writes_the_files_and_says_how_to_use_them(tmp_path):
    import subprocess
    import sys

    (tmp_path / "lab.toml").write_text(LAB.format(port=7447))
    done = subprocess.run(
        [
            sys.executable,
            "-m",
            "dhg.cli.main",
            "lab-config",
            "--lab",
            str(tmp_path / "lab.toml"),
            "--out",
            str(tmp_path / "o"),
            "--make-certs",
        ],  # fmt: skip
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert done.returncode == 0, done.stderr
    assert "--zenoh-config" in done.stdout and "station-1" in done.stdout
    assert sorted(p.name for p in (tmp_path / "o").iterdir()) == [
        "model-1.json5", "server.json5", "station-1.json5", "station-2.json5", "teacher.json5", "users.txt",
    ]  # fmt: skip
    assert os.path.isfile(tmp_path / "certs" / "server.pem")
    missing = tmp_path / "lab2.toml"
    missing.write_text(LAB.format(port=7447).replace("certs/", "nocerts/"))
    done = subprocess.run(
        [sys.executable, "-m", "dhg.cli.main", "lab-config", "--lab", str(missing), "--out", str(tmp_path / "o2")],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert done.returncode == 3 and "--make-certs" in done.stderr


def test_dhg_serve_with_the_lab_file_caps_each_stations_sessions(lab):
    """A station names its sessions after itself (its access-control list allows no other); with
    ``--lab`` the server lets it hold at most ``sessions_per_station`` (2) of them, so one station
    cannot take every slot. Over plain TCP: the cap does not depend on the transport."""
    from dhg.core.errors import EngineError

    root, _, _ = lab
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    server = ServerProcess(["--listen", endpoint, "--lab", str(root / "lab.toml"), "--voxel-mm", "1.0"], echo=False)
    try:
        with TraineeClient(endpoint, "station-1") as a, TraineeClient(endpoint, "station-2") as b:
            a.create()
            a._json("dhg/session/station-1-retry/control", {"op": "create"})
            with pytest.raises(EngineError, match="station-1 already holds 2 sessions"):
                a._json("dhg/session/station-1-third/control", {"op": "create"})
            assert b.create()["session"] == "station-2"  # another station is not held back
            a._json("dhg/session/station-1-retry/control", {"op": "close"})
            assert a._json("dhg/session/station-1-third/control", {"op": "create"})["session"] == "station-1-third"
            assert a._json("dhg/session/visitor/control", {"op": "create"})["session"] == "visitor"  # not a station's
    finally:
        assert server.stop() == 0, said(server)


def test_the_viewer_works_in_lab_mode_with_a_station_or_an_instructor_identity(lab):
    """``dhg view`` is one more client: a station sees its own session (the volume, its bone as
    drilled, its X-rays, its drill) and not another station's; the instructor sees every session.
    (The X-ray and bone queryables live in the server's own Python client, which must not apply
    the router's access-control list to itself: it did, and dropped every query.)"""
    from dhg.view import Viewer
    from dhg.view.browser import PageWatcher
    from dhg.view.feed import SessionFeed

    root, endpoint, listen = lab
    server = ServerProcess(
        ["--listen", listen, "--zenoh-config", str(root / "out" / "server.json5"), "--voxel-mm", "1.0"], echo=False
    )
    conf = {n: str(root / "out" / f"{n}.json5") for n in ("station-1", "teacher")}
    try:
        with _client(root, endpoint, "station-1") as s1, _client(root, endpoint, "station-2") as s2:
            s2.create()
            station_view = Viewer(
                endpoint, port=free_port(), session_id="station-1", zenoh_config_file=conf["station-1"]
            )
            teacher_view = Viewer(endpoint, port=free_port(), zenoh_config_file=conf["teacher"])
            hand = Stylus(s1, (1.0, 0.0, 0.0, 0.0))  # the session lives while its stylus streams
            hand.move(_drill_path(s1, 2000))
            watchers: list[PageWatcher] = []  # a page draws only while watched
            try:
                page = station_view.pages["station-1"]
                # Watched, it hears its own forces and states, asks its bone and draws its drill.
                watchers.append(PageWatcher(page.url))
                _wait(
                    lambda: page.feed.forces > 0 and page.feed.states > 0 and page.bone_updates > 0 and page.frames > 0,
                    30,
                    "station-1's streams, bone and drill",
                )
                assert page.feed.xray("top").startswith(b"\x89PNG")
                other = SessionFeed(station_view._z, "station-2")
                try:
                    with pytest.raises(TransportError):
                        other.bricks(timeout_s=1.0)  # the access control drops the query
                finally:
                    other.close()
                instructor = teacher_view.instructor
                assert instructor is not None
                _wait(lambda: {"station-1", "station-2"} <= set(instructor.sessions), 30, "both stations listed")
                watchers.append(PageWatcher(teacher_view.page_url("station-1")))
                _wait(lambda: teacher_view.pages["station-1"].bone_updates > 0, 30, "the teacher's page of station-1")
            finally:
                for w in watchers:
                    w.close()
                hand.stop()  # before the clients close under it
                station_view.close()
                teacher_view.close()
    finally:
        assert server.stop() == 0, said(server)
