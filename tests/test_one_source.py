"""Facts defined once, in the Rust core, and read by Python (issue 22, item 1): the settings
dataclasses' fields and defaults, the flag bits, the error kinds, and the conversions between
them (serde + pythonize in the binding, no field tables)."""

from __future__ import annotations

from dataclasses import asdict, fields

import numpy as np
import pytest

import dhg
from dhg import _bone_sim
from dhg.core import errors, protocol
from dhg.core.errors import InvalidInputError
from dhg.core.path import PlannedPath
from dhg.core.server import ServerSettings, start_engine
from dhg.core.session import MAX_GAIN, CuttingLaw, DeviceProfile, SessionConfig, ThermalParams
from dhg.core.volume import HuMapping
from dhg.live.process import free_port
from dhg.live.zenoh_config import zenoh_config_json5
from dhg.operators.styles import sample_style
from dhg.study.design import parse_arms

CORE = _bone_sim.defaults()
MIN_PATH_LENGTH_M = _bone_sim.MIN_PATH_LENGTH_M


@pytest.mark.parametrize(
    ("cls", "core"),
    [
        (DeviceProfile, CORE["session"]["device"]),
        (CuttingLaw, CORE["session"]["cutting"]),
        (ThermalParams, CORE["session"]["thermal"]),
        (HuMapping, CORE["hu_mapping"]),
        (ServerSettings, CORE["server"]),
    ],
)
def test_each_settings_dataclass_has_the_cores_fields_and_defaults(cls, core):
    assert [f.name for f in fields(cls)] == list(core) or {f.name for f in fields(cls)} == set(core)
    mine = asdict(cls())
    for name, value in core.items():
        if isinstance(value, list):  # Rust's Vec is a tuple on the frozen dataclass
            assert tuple(value) == tuple(mine[name]), name
        else:
            assert mine[name] == value, name


def test_the_session_config_has_the_cores_fields_and_defaults_except_the_coupling_rule():
    core = dict(CORE["session"])
    mine = asdict(SessionConfig())
    # None means "as stiff as the device allows", which is what the core's default is.
    assert mine.pop("coupling_stiffness_n_per_m") is None
    assert core.pop("coupling_stiffness_n_per_m") == DeviceProfile().max_stiffness_n_per_m
    assert mine == core


def test_a_config_crosses_the_binding_and_comes_back_the_same(coarse_phantom):
    cfg = SessionConfig(
        burr_radius_m=2e-3,
        device=DeviceProfile(peak_force_n=2.5, max_stiffness_n_per_m=300.0),
        thermal=ThermalParams(heat_fraction=0.2),
    )
    s = dhg.DrillingSession(coarse_phantom.volume, coarse_phantom.path, cfg)
    back = s._s.config()
    expected = cfg.to_native() | {"coupling_stiffness_n_per_m": 300.0}  # followed the device's maximum
    assert back == expected
    given = SessionConfig(coupling_stiffness_n_per_m=150.0)
    assert (
        dhg.DrillingSession(coarse_phantom.volume, coarse_phantom.path, given)._s.config()["coupling_stiffness_n_per_m"]
        == 150.0
    )
    mapping = HuMapping(cortical_min_hu=650.0)
    vol = dhg.Volume.from_hu(
        np.full((4, 4, 4), 800, np.int16), (1e-3,) * 3, (0.0, 0.0, 0.0), np.eye(3), mapping=mapping
    )
    assert HuMapping.from_dict(vol._vol.mapping) == mapping


@pytest.mark.parametrize(
    ("config", "said"),
    [
        (SessionConfig(device=DeviceProfile(peak_force_n="3")), "device.peak_force_n"),  # type: ignore[arg-type]
        (SessionConfig(thermal=ThermalParams(heat_fraction=None)), "thermal.heat_fraction"),  # type: ignore[arg-type]
    ],
)
def test_a_config_value_of_the_wrong_type_is_refused_naming_its_path(coarse_phantom, config, said):
    with pytest.raises(errors.InvalidInputError, match=f"invalid session config: {said}"):
        dhg.DrillingSession(coarse_phantom.volume, coarse_phantom.path, config)


def test_an_unknown_config_field_is_refused_naming_the_known_ones(coarse_phantom):
    p = coarse_phantom.path
    with pytest.raises(errors.InvalidInputError, match="unknown field `peak`.*peak_force_n"):
        _bone_sim.DrillingSession(
            coarse_phantom.volume._vol, tuple(p.entry_m), tuple(p.target_m), {"device": {"peak": 1}}
        )
    with pytest.raises(errors.InvalidInputError, match="unknown field `brake_holdn`"):
        dhg.DrillingSession(coarse_phantom.volume, p)._s.set_guidance_params({"brake_holdn": 1.0})


def test_flags_are_the_cores():
    assert protocol.FLAGS == dict(_bone_sim.FLAGS)
    bits = list(protocol.FLAGS.values())
    assert len(set(bits)) == len(bits) and all(b & (b - 1) == 0 for b in bits)  # distinct single bits


def test_every_error_kind_the_core_raises_has_its_own_python_class():
    assert set(errors.ERROR_KINDS) == set(_bone_sim.ERROR_KINDS)
    classes = [errors.ERROR_KINDS[k] for k in _bone_sim.ERROR_KINDS]
    assert len(set(classes)) == len(classes), "two kinds share a class"
    assert all(issubclass(c, errors.DhgError) for c in classes)


def test_each_error_kind_arrives_as_its_class(coarse_phantom):
    """One native error of every kind, raised for real, and the class it arrives as."""
    vol, p = coarse_phantom.volume, coarse_phantom.path
    raised: dict[str, type[BaseException]] = {}

    def catch(kind, f):
        with pytest.raises(errors.DhgError) as info:
            f()
        raised[kind] = type(info.value)

    catch("invalid_input", lambda: _bone_sim.check_session_id(".."))
    catch("shape", lambda: vol._vol.layer_at(np.zeros((2, 2))))
    catch("transport", lambda: _bone_sim.Server(vol._vol, list(p.entry_m), list(p.target_m), "{ mode: 7 }"))
    conf = zenoh_config_json5([f"tcp/127.0.0.1:{free_port()}"], mode="router")
    srv = start_engine(vol, p, conf, ServerSettings(max_sessions=1))
    try:
        catch("engine", lambda: srv.metrics("nobody"))
    finally:
        srv.stop()
    assert set(raised) == set(_bone_sim.ERROR_KINDS)
    for kind, cls in raised.items():
        assert cls is errors.ERROR_KINDS[kind], (kind, cls)


def test_the_command_lines_take_their_defaults_from_the_config_types():
    """The flags are written by hand (docs/decisions/0021-cli-flags.md) but their defaults are the
    config types' own: ``dhg train``'s make exactly ``TrainConfig()``, ``dhg-serve``'s the core's
    ``ServerSettings()``, ``dhg study``'s the ``Protocol()`` of a study."""
    from dhg.cli.commands import _train_config
    from dhg.cli.main import build_parser
    from dhg.cli.serve import serve_parser
    from dhg.learning.presets import TrainConfig
    from dhg.study.design import Protocol

    train = build_parser().parse_args(["train", "--data", "d", "--out", "o"])
    assert _train_config(train) == TrainConfig()
    serve, settings = serve_parser().parse_args([]), ServerSettings()
    assert (serve.max_sessions, serve.idle_timeout, serve.model_timeout) == (
        settings.max_sessions,
        settings.idle_timeout_s,
        settings.model_timeout_s,
    )
    assert (serve.guidance_mode, serve.guidance_gain, serve.wait) == (
        settings.guidance_mode,
        settings.guidance_gain,
        settings.wait,
    )
    study, protocol = build_parser().parse_args(["study", "--out", "o"]), Protocol()
    assert (study.train, study.duration, study.probe_every) == (
        protocol.train,
        protocol.duration_s,
        protocol.probe_every,
    )


def test_a_study_arm_and_a_session_take_the_same_largest_gain(coarse_phantom):
    """The study's arms check gains before any session runs: by the core's bound, not a copy."""
    s = dhg.DrillingSession(coarse_phantom.volume, coarse_phantom.path)
    s.set_guidance("shaped", MAX_GAIN)
    _, arm = parse_arms(f"none,shaped@{MAX_GAIN!r}")
    assert arm.gain == MAX_GAIN
    over = MAX_GAIN + 0.01
    with pytest.raises(InvalidInputError, match="gain"):
        s.set_guidance("shaped", over)
    with pytest.raises(InvalidInputError, match="gain"):
        parse_arms(f"none,shaped@{over!r}")


def test_a_path_is_refused_below_the_cores_shortest_length_and_taken_above_it():
    a = np.zeros(3)
    style = sample_style("novice", np.random.default_rng(1)).to_dict()
    for length, ok in [(MIN_PATH_LENGTH_M * 0.99, False), (MIN_PATH_LENGTH_M * 1.01, True)]:
        b = np.array([0.0, 0.0, length])
        if ok:
            PlannedPath(a, b)
            _bone_sim.SurgeonController(a.tolist(), b.tolist(), style, 1, 1.0)  # the core agrees
        else:
            with pytest.raises(InvalidInputError, match="apart"):
                PlannedPath(a, b)
            with pytest.raises(InvalidInputError, match="path length"):
                _bone_sim.SurgeonController(a.tolist(), b.tolist(), style, 1, 1.0)
