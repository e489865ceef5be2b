"""The command line: help, the xray and demo commands, import, and exit codes."""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

import pytest
from pydicom.data import get_testdata_file

BIN = Path(sys.executable).parent


def run(*args: str, tool: str = "dhg") -> subprocess.CompletedProcess[str]:
    exe = shutil.which(tool, path=str(BIN)) or shutil.which(tool)
    assert exe, f"console script {tool} is not installed"
    return subprocess.run([exe, *args], capture_output=True, text=True, timeout=300)


def test_help_teaches():
    r = run("--help")
    assert r.returncode == 0
    for word in ("xray", "demo", "ct-import", "phantom", "exit codes"):
        assert word in r.stdout
    r = run("xray", "--help")
    assert r.returncode == 0 and "top.png" in r.stdout and "--ct" in r.stdout
    r = run("view", "--help")
    assert r.returncode == 0 and "instructor" in r.stdout and "--zenoh-config" in r.stdout
    r = run("train", "--help")
    assert r.returncode == 0 and "the last 13.5 % of windows" in r.stdout and "%%" not in r.stdout


def test_xray_writes_three_pngs(tmp_path):
    r = run("xray", "--out", str(tmp_path / "x"), "--voxel-mm", "1.5")
    assert r.returncode == 0, r.stderr
    for name in ("top", "front", "side"):
        png = tmp_path / "x" / f"{name}.png"
        assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
        assert str(png) in r.stdout


def test_ct_import_then_xray_from_the_file(tmp_path):
    out = tmp_path / "ct.npz"
    r = run("ct-import", get_testdata_file("CT_small.dcm"), "--out", str(out))
    assert r.returncode == 0, r.stderr
    r = run("xray", "--ct", str(out), "--out", str(tmp_path / "v"))
    assert r.returncode == 0, r.stderr
    assert (tmp_path / "v" / "front.png").is_file()


def test_demo_drills_and_reports(tmp_path):
    r = run("demo", "--out", str(tmp_path / "demo"), "--voxel-mm", "1.0")
    assert r.returncode == 0, r.stderr
    assert "necrosis" in r.stdout and "removed" in r.stdout and "peak tip temperature" in r.stdout
    assert (tmp_path / "demo" / "side.png").is_file()
    assert (tmp_path / "demo" / "drilling.png").read_bytes()[:4] == b"\x89PNG"


@pytest.mark.parametrize(
    ("args", "code", "message"),
    [
        (["xray", "--out", "{tmp}/o", "--ct", "{tmp}/missing.npz"], 3, "no such volume file"),
        (["xray", "--out", "{tmp}/o", "--ct", "{tmp}/notes.txt"], 3, "not a DICOM file"),
        (["xray", "--out", "{tmp}/o", "--voxel-mm", "-1"], 3, "voxel_m"),
        (["xray"], 2, "--out"),
        (["frobnicate"], 2, "invalid choice"),
        (["view", "--session", "../etc"], 3, "first a letter or digit"),
        (["view", "--port", "70000"], 3, "port must be within"),
        (["view", "--nice", "20"], 3, "--nice must be 0 (as the server) to 19"),
        (["view", "--connect", "tcp/127.0.0.1:9", "--session", "a-1"], 5, "cannot open a zenoh session"),
        (["view", "--connect", "notanendpoint"], 2, "is not a Zenoh endpoint"),
        (["view", "--duration", "1e12"], 3, "--duration must be > 0 and at most"),
        (["demo", "--out", "{tmp}/d", "--feed-mm-s", "0"], 3, "--feed-mm-s must be a feed rate > 0"),
        (["demo", "--out", "{tmp}/d", "--feed-mm-s", "nan"], 2, "'nan' is not a finite number"),
        (["demo", "--out", "{tmp}/d", "--rpm", "5000"], 3, "--rpm must be a spindle speed"),
        (["demo", "--out", "{tmp}/d", "--feed-mm-s", "0.01"], 3, "--feed-mm-s 0.01 would drill for longer"),
        (["trainee", "--duration", "inf"], 2, "'inf' is not a finite number"),
        (["trainee", "--duration", "7200"], 3, "--duration must be > 0 and at most 3600 s"),
        (["record", "--session", "a", "--out", "{tmp}/r", "--duration", "-1"], 3, "--duration must be > 0"),
        (["record", "--session", "a", "--out", "{tmp}/r", "--flush-every", "0"], 3, "--flush-every must be > 0"),
        (["live-demo", "--out", "{tmp}/l", "--duration", "0"], 3, "--duration must be > 0"),
        (["ablate", "--data", "{tmp}", "--out", "{tmp}/a", "--seeds", "0"], 3, "--seeds is how many seeds"),
        (["train", "--data", "{tmp}", "--out", "{tmp}/t", "--epochs", "0"], 3, "max_epochs must be at least 1"),
        (["ct-import", "{tmp}/notes.txt", "--out", "{tmp}/c.npz", "--crop-mm", "1,2,x"], 2, "--crop-mm takes six"),
        (["phantom", "--out", "{tmp}/p.npz", "--seed", "-1"], 3, "seed must be a whole number >= 0"),
    ],
)
def test_exit_codes_and_messages(tmp_path, args, code, message):
    (tmp_path / "notes.txt").write_text("hello")
    r = run(*[a.format(tmp=tmp_path) for a in args])
    assert r.returncode == code, (r.stdout, r.stderr)
    assert message in r.stderr
    assert "Traceback" not in r.stderr


def test_serve_help_teaches_the_roles_and_exit_codes():
    r = run("--help", tool="dhg-serve")
    assert r.returncode == 0
    for needle in ("--role", "--listen", "--connect", "--model", "exit codes", "docs/protocol.md"):
        assert needle in r.stdout


def test_serve_refuses_an_unknown_role():
    r = run("--role", "chef", tool="dhg-serve")
    assert r.returncode == 2
    assert "invalid choice" in r.stderr


@pytest.mark.parametrize(
    ("args", "code", "message"),
    [
        (["--status-every", "nan"], 2, "'nan' is not a finite number"),
        (["--status-every", "1e12"], 3, "--status-every must be > 0 and at most 3600 s"),
        (["--model-threads", "0"], 3, "--model-threads must be at least 1"),
        (["--listen", "7447"], 2, "is not a Zenoh endpoint"),
    ],
)
def test_serve_refuses_bad_numbers_and_endpoints_before_starting(args, code, message):
    r = run(*args, tool="dhg-serve")
    assert r.returncode == code, (r.stdout, r.stderr)
    assert message in r.stderr and "Traceback" not in r.stderr


def test_phantom_file_round_trip(tmp_path):
    out = tmp_path / "femur.npz"
    r = run("phantom", "--out", str(out), "--voxel-mm", "2", "--seed", "5")
    assert r.returncode == 0, r.stderr
    import dhg

    vol = dhg.Volume.load(out)
    assert vol.meta["seed"] == 5 and vol.spacing_m == (2e-3, 2e-3, 2e-3)
    assert "planned_path" in vol.meta


def test_synth_writes_a_dataset_and_refuses_to_overwrite(tmp_path):
    out = tmp_path / "ds"
    args = ["synth", "--out", str(out), "--subjects", "1", "--attempts", "1", "--novices", "0", "--voxel-mm", "1.0"]
    r = run(*args)
    assert r.returncode == 0, r.stderr
    assert (out / "records.parquet").is_file() and (out / "card.json").is_file()
    assert "completion time" in r.stdout
    r = run(*args)
    assert r.returncode == 3 and "--overwrite" in r.stderr
