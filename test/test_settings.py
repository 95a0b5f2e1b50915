"""One declaration per setting (issue 27 item 4): cstomo_sensor/settings.py. Every place a setting
appears (the node's declared parameters, the config dataclasses, config/cstomo_sensor.yaml, the
parameter table of docs/node.md, ``cstomo_sensor_node --help``, the flags of ``cstomo`` that mirror
a setting and the launch arguments) says the same default, range and description, or a test here
fails naming the place."""
from __future__ import annotations

import argparse
import re
from dataclasses import fields
from pathlib import Path

import pytest
import yaml

from cstomo_sensor.settings import SETTING, SETTINGS, markdown_table, parameter_file, text_of

ROOT = Path(__file__).resolve().parent.parent

#: Flags that mirror a setting with another default on purpose: (command, setting) -> default.
OTHER_DEFAULTS = {("replay", "stress_field_every"): 0,  # replay writes no stress fields unless asked
                  ("calibrate", "creep_per_decade"): None}  # unset: fitted, else the node's applies


def test_the_parameter_file_and_the_docs_table_are_written_from_the_settings():
    """`python -m cstomo_sensor.settings yaml|markdown` rewrites them after a change."""
    assert (ROOT / "config" / "cstomo_sensor.yaml").read_text() == parameter_file(), \
        "config/cstomo_sensor.yaml: run python -m cstomo_sensor.settings yaml > config/cstomo_sensor.yaml"
    doc = (ROOT / "docs" / "node.md").read_text()
    table = re.search(r"<!-- settings table: [^\n]*-->\n(.*?)<!-- end of settings table -->", doc, re.S)
    assert table is not None and table[1] == markdown_table(), \
        "docs/node.md: paste python -m cstomo_sensor.settings markdown between the settings table markers"
    params = yaml.safe_load(parameter_file())["/**/cstomo_sensor"]["ros__parameters"]
    assert list(params) == list(SETTING)
    for s in SETTINGS:  # the file reads back as the defaults, with their types
        want = list(s.default) if isinstance(s.default, tuple) else s.default
        assert params[s.name] == want and type(params[s.name]) is type(want), s.name
        assert f"`{s.name}` | `{text_of(s.default)}` | {s.range} |" in table[1], s.name


def test_the_config_dataclasses_take_their_defaults_from_the_settings():
    pytest.importorskip("rclpy")
    from cstomo_sensor.frame_path.config import PipelineConfig, StreamConfig
    from cstomo_sensor.ros.params import PARAMETERS, NodeConfig

    seen = set()
    for cls in (PipelineConfig, StreamConfig, NodeConfig):
        for f in fields(cls):
            if f.name in SETTING:
                assert f.default == SETTING[f.name].default, (cls.__name__, f.name, f.default)
                seen.add(f.name)
    assert seen == set(SETTING)  # every setting is one of a config's fields
    # the stream's settings are the node's nested StreamConfig (no copies): parameters -> one frozen config
    assert not {f.name for f in fields(StreamConfig)} & {f.name for f in fields(NodeConfig)}
    given = {"tare_frames": 7, "max_sigma_n": 2.5, "drift_tracking": False}
    cfg = NodeConfig.from_parameters(lambda n: given.get(n, PARAMETERS[n][0]))
    assert cfg.stream == StreamConfig(**given)
    assert (cfg.stream.tare_frames, cfg.stream.max_sigma_n, cfg.stream.drift_tracking) == (7, 2.5, False)


@pytest.mark.parametrize("name, value, why", [
    ("tare_frames", 0, "1..100000"), ("tare_frames", True, "an integer, 1..100000"), ("stale_timeout", 0.0, "0.01..3600 seconds"),
    ("qos_reliability", "fast", "one of system_default, reliable, best_effort"), ("input", "usb", "one of serial"),
    ("creep_per_decade", 0.3, "0..0.2"), ("wrench_filter_hz", float("nan"), "a finite number")])
def test_the_node_config_refuses_a_value_outside_the_declared_range_naming_it(name, value, why):
    pytest.importorskip("rclpy")
    from cstomo_sensor.errors import ConfigError
    from cstomo_sensor.ros.params import PARAMETERS, NodeConfig

    with pytest.raises(ConfigError, match=re.escape(f"parameter '{name}'={value!r}: expected {why}")):
        NodeConfig.from_parameters(lambda n: value if n == name else PARAMETERS[n][0])


@pytest.mark.parametrize("cls, name, value, why", [
    ("StreamConfig", "tare_frames", 0, "1..100000"), ("StreamConfig", "stale_timeout", 0.0, "0.01..3600 seconds"),
    ("StreamConfig", "creep_per_decade", 0.3, "0..0.2"), ("StreamConfig", "wrench_filter_hz", float("nan"), "a finite number"),
    ("StreamConfig", "drift_tracking", 1, "true or false"), ("PipelineConfig", "estimator", "fast", "one of model, linear"),
    ("PipelineConfig", "max_force", 0.0, "1..100000 N"), ("PipelineConfig", "grid", (6, 6), "3 numbers, each 1..64")])
def test_the_config_dataclasses_refuse_a_value_outside_the_declared_range_naming_it(cls, name, value, why):
    from cstomo_sensor.errors import ConfigError
    from cstomo_sensor.frame_path import config

    with pytest.raises(ConfigError, match=re.escape(f"{name}={value!r}: expected {why}")):
        getattr(config, cls)(**{name: value})
    getattr(config, cls)(**{name: SETTING[name].default})  # the default is one of its values


@pytest.mark.slow  # starts a node
def test_the_node_declares_every_setting_with_its_default_range_and_description(ros):
    from rclpy.parameter import Parameter

    from cstomo_sensor.errors import ConfigError
    from cstomo_sensor.ros.node import CstomoSensorNode
    from cstomo_sensor.ros.startup import usage

    node = CstomoSensorNode("settings_probe", context=ros, parameter_overrides=[Parameter("autostart", value=False)])
    try:
        declared = set(node._parameters) - {"use_sim_time", "start_type_description_service"}
        assert declared == set(SETTING)
        for s in SETTINGS:
            d = node.describe_parameter(s.name)
            value = node.get_parameter(s.name).value
            assert s.name == "autostart" or (list(value) if isinstance(s.default, tuple) else value) == (
                list(s.default) if isinstance(s.default, tuple) else s.default), s.name  # autostart: overridden
            assert d.description == s.description and d.read_only == s.read_only, s.name
            ranges = list(d.floating_point_range) + list(d.integer_range)
            got = (ranges[0].from_value, ranges[0].to_value) if ranges else None
            scalar = not isinstance(s.default, (tuple, bool, str)) and s.lo is not None
            assert got == ((s.lo, s.hi) if scalar else None), s.name
            assert d.additional_constraints == (s.range if s.choices else ""), s.name
    finally:
        node.destroy_node()
    # rclpy enforces the declared range: just above hi is refused
    with pytest.raises(ConfigError, match="^parameter 'max_sigma_n'=.*: expected 0"):
        CstomoSensorNode("settings_hi", context=ros, parameter_overrides=[
            Parameter("autostart", value=False), Parameter("max_sigma_n", value=SETTING["max_sigma_n"].hi * 1.01)])
    lines = usage().splitlines()
    for s in SETTINGS:  # --help: name, default, description on one line
        value = list(s.default) if isinstance(s.default, tuple) else s.default
        assert any(ln.split()[:1] == [s.name] and f"{value!r}" in ln and s.description in ln for ln in lines), s.name
    # the defaults in one column, whatever the longest name (expected_wrench_sigma had pushed its own over)
    params = lines[lines.index("parameters (default):") + 1:]
    assert len({len(ln) - len(ln[2:].split(" ", 1)[1].lstrip()) for ln in params}) == 1, params


def _parsers() -> dict[str, argparse.ArgumentParser]:
    """Every parser of `cstomo`: command words -> parser."""
    from cstomo_sensor.tools import cli

    out = {name: cli.subcommand_parser([name])[0] for name in cli.OWN_PARSERS}
    for words in (["model", "build"], ["model", "voltages"], ["reconstruct"], ["estimate"], ["simulate"]):
        out[" ".join(words)] = cli.subcommand_parser(words)[0]
    return out


def mismatches(command: str, parser: argparse.ArgumentParser) -> list[str]:
    """What a parser's flags that mirror a setting (by dest, or by a flag spelled as a setting) say
    differently from the setting: default, choices, range (a value out of it accepted) or help."""
    out = []
    for action in parser._actions:
        names = {o.lstrip("-").removeprefix("no-").replace("-", "_") for o in action.option_strings}
        s = SETTING.get(action.dest) or next((SETTING[n] for n in names if n in SETTING), None)
        if s is None:
            continue
        where = f"cstomo {command} {'/'.join(action.option_strings)}"
        if action.dest != s.name:
            out.append(f"{where}: dest {action.dest!r}, the setting is {s.name!r}")
            continue
        want = OTHER_DEFAULTS.get((command, s.name), s.default)
        got = tuple(action.default) if isinstance(action.default, list) else action.default
        if got != want:
            out.append(f"{where}: default {action.default!r}, the setting's {want!r}")
        if (command, s.name) in OTHER_DEFAULTS and want is None:
            continue  # another meaning: only the default is held
        if tuple(action.choices or ()) != s.choices:
            out.append(f"{where}: choices {action.choices}, the setting's {s.choices}")
        if s.description.replace("%", "%%") not in (action.help or ""):
            out.append(f"{where}: help {action.help!r} is not the setting's description")
        if s.lo is not None and not isinstance(s.default, bool):
            try:
                action.type(str(s.hi * 2))
                out.append(f"{where}: {s.hi * 2} accepted, beyond the setting's range {s.range}")
            except (argparse.ArgumentTypeError, ValueError, TypeError):
                pass
    return out


def test_every_flag_that_mirrors_a_setting_says_what_the_setting_says():
    found = {(c, a.dest) for c, p in _parsers().items() for a in p._actions if a.dest in SETTING}
    # the flags this issue names are among them
    assert {("replay", "creep_per_decade"), ("estimate", "creep_per_decade"), ("estimate", "estimator"),
            ("calibrate", "estimator"), ("board-sim", "sensor"), ("board-sim", "protocol"), ("demo", "estimator"),
            ("replay", "tare_frames"), ("replay", "wrench_filter_hz"), ("replay", "drift_tracking"),
            ("estimate", "drift_tracking"), ("replay", "frame_id"), ("estimate", "max_force")} <= found
    wrong = [m for c, p in _parsers().items() for m in mismatches(c, p)]
    assert not wrong, "\n".join(wrong)


def test_the_flag_check_finds_a_flag_that_says_otherwise():
    from cstomo_sensor.tools.common import add_setting_arg

    p = argparse.ArgumentParser()
    p.add_argument("--tare-frames", type=int, default=40, help="frames of a tare")
    p.add_argument("--no-drift-tracking", action="store_true")
    add_setting_arg(p, "estimator", default="linear")
    got = "\n".join(mismatches("x", p))
    assert "--tare-frames: default 40" in got and "help 'frames of a tare'" in got and "200000 accepted" in got
    assert "--no-drift-tracking: dest 'no_drift_tracking'" in got and "--estimator: default 'linear'" in got


def test_a_flag_out_of_range_is_refused_naming_the_flag_and_the_range(capsys):
    from cstomo_sensor.tools import cli

    with pytest.raises(SystemExit) as done:
        cli.main(["estimate", "--reference", "r", "--frames", "f", "--out", "o", "--creep-per-decade", "0.5"])
    assert done.value.code == 2
    assert "argument --creep-per-decade: '0.5': expected 0..0.2 (default 0.04)" in capsys.readouterr().err
    a = cli.subcommand_parser(["replay"])[0].parse_args(["b", "--out", "o", "--no-drift-tracking", "--grid", "4", "4", "2"])
    assert a.drift_tracking is False and a.grid == [4, 4, 2] and a.stress_field_every == 0


def test_the_launch_arguments_that_override_a_parameter_carry_its_description():
    from cstomo_sensor.tools.launching import ARGUMENTS, NODE_ARGUMENTS

    for name in NODE_ARGUMENTS:
        default, desc = ARGUMENTS[name]
        assert default == "" and desc.startswith(SETTING[name].description), name
