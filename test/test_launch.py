"""The launch file and the parameter file agree with the parameters the node really declares.

launch/launch_ros do not install from the package index: the launch file's argument table is parsed
(ast) and checked against the parameters of a node created for the purpose; what it starts is decided
by :func:`cstomo_sensor.tools.common.launch_plan`, tested here directly. Not tested here: the launch
file's few lines that hand that plan to launch/launch_ros.
"""
from __future__ import annotations

import ast
from pathlib import Path

import pytest
import yaml

rclpy = pytest.importorskip("rclpy")

ROOT = Path(__file__).resolve().parent.parent
LAUNCH = ROOT / "launch" / "cstomo_sensor.launch.py"
CONFIG = ROOT / "config" / "cstomo_sensor.yaml"
LAUNCH_ONLY = {"config", "sim", "sim_load_script", "namespace"}  # arguments of the launch itself, not node parameters


@pytest.fixture(scope="module")
def declared():
    """name -> (type of the default, read_only) of a freshly created node."""
    from rclpy.parameter import Parameter

    from cstomo_sensor.ros.node import CstomoSensorNode

    ctx = rclpy.Context()
    rclpy.init(context=ctx)
    node = CstomoSensorNode("launch_introspect", context=ctx, parameter_overrides=[Parameter("autostart", value=False)])
    try:
        yield {name: node.get_parameter(name).value for name in node._parameters
               if name not in ("use_sim_time", "start_type_description_service")}
    finally:
        node.destroy_node()
        rclpy.try_shutdown(context=ctx)


def _arguments() -> dict:
    """The launch file's ARGUMENTS table (name -> (default, description)), read without importing
    launch (not installable from the package index)."""
    tree = ast.parse(LAUNCH.read_text())
    (table,) = [n.value for n in tree.body if isinstance(n, ast.Assign) and n.targets[0].id == "ARGUMENTS"]
    return ast.literal_eval(table)


def test_every_launch_argument_is_a_declared_parameter_and_defaults_to_the_file(declared):
    args = _arguments()
    assert {"port", "config", "sim", "sensor", "estimator", "namespace", "sim_load_script"} == set(args)
    node_args = set(args) - LAUNCH_ONLY
    assert node_args <= set(declared), node_args - set(declared)
    # an argument left at its default never overrides the parameter file
    assert all(args[name][0] == "" for name in node_args), {n: args[n][0] for n in node_args}
    src = LAUNCH.read_text()
    assert "PythonExpression" not in src and "eval(" not in src  # user text is never evaluated
    assert 'executable="cstomo_sensor_node"' in src and 'name="cstomo_sensor"' in src


def test_launch_plan_passes_arguments_verbatim_and_only_when_given():
    from cstomo_sensor.tools.common import launch_plan

    evil = "/dev/ttyACM0' + __import__('os').system('touch /tmp/pwned') + '"
    overrides, board, work = launch_plan({"port": evil, "config": str(CONFIG), "sim": "false", "sensor": "",
                                          "estimator": "", "namespace": "", "sim_load_script": ""})
    assert overrides == {"port": evil} and board is None and work is None
    overrides, _, _ = launch_plan({"port": "", "config": str(CONFIG), "sim": "false", "sensor": "disc",
                                   "estimator": "model"})
    assert overrides == {"sensor": "disc", "estimator": "model"}
    from cstomo_sensor.errors import ConfigError

    with pytest.raises(ConfigError, match="sim='yes please'"):
        launch_plan({"config": str(CONFIG), "sim": "yes please"})


def test_each_sim_launch_has_its_own_link_script_and_tare(tmp_path):
    import shutil

    from cstomo_sensor.tools.common import launch_plan

    cfg = tmp_path / "params.yaml"  # the sensor of the parameter file reaches the board when no argument names one
    cfg.write_text("/**/cstomo_sensor:\n  ros__parameters:\n    sensor: cylinder\n")
    plans = [launch_plan({"port": "/dev/cstomo", "config": str(cfg), "sim": "true"}) for _ in range(2)]
    try:
        (o1, b1, w1), (o2, b2, w2) = plans
        assert w1 != w2 and w1.is_dir() and w2.is_dir()
        for o, b, w in plans:
            assert o["port"] == b[b.index("--link") + 1] == str(w / "board")  # sim replaces the port
            assert Path(o["tare_file"]).parent == w  # the simulated board's tare is never a real board's
            assert b[b.index("--sensor") + 1] == "cylinder"
            script = Path(b[b.index("--load-script") + 1])
            assert script.parent == w and script.read_text().startswith("time,fx,fy,fz\n0,0,0,0\n")
            assert Path(b[0]).name == "cstomo" and Path(b[0]).is_file()
    finally:
        for _, _, w in plans:
            shutil.rmtree(w)


def test_executables_are_found_in_a_colcon_prefix(tmp_path, monkeypatch):
    from cstomo_sensor.tools.common import executable

    prefix = tmp_path / "install" / "cstomo_sensor"
    (prefix / "share" / "ament_index" / "resource_index" / "packages").mkdir(parents=True)
    (prefix / "share" / "ament_index" / "resource_index" / "packages" / "cstomo_sensor").write_text("")
    (prefix / "lib" / "cstomo_sensor").mkdir(parents=True)
    exe = prefix / "lib" / "cstomo_sensor" / "cstomo"
    exe.write_text("#!/bin/sh\n")
    exe.chmod(0o755)
    monkeypatch.setenv("AMENT_PREFIX_PATH", f"{tmp_path / 'other'}:{prefix}")
    assert executable("cstomo") == str(exe)
    monkeypatch.delenv("AMENT_PREFIX_PATH")
    assert executable("cstomo") != str(exe) and Path(executable("cstomo")).is_file()
    from cstomo_sensor.errors import CstomoError

    monkeypatch.setenv("PATH", str(tmp_path))
    with pytest.raises(CstomoError, match="no_such_tool"):
        executable("no_such_tool")


def test_parameter_file_applies_under_any_namespace(tmp_path):
    from rclpy.parameter import Parameter

    from cstomo_sensor.ros.node import CstomoSensorNode

    cfg = tmp_path / "params.yaml"
    cfg.write_text(CONFIG.read_text().replace("stale_timeout: 0.5 ", "stale_timeout: 0.7 "))
    ctx = rclpy.Context()
    rclpy.init(context=ctx, args=["x", "--ros-args", "--params-file", str(cfg)])
    try:
        for ns in ("", "left_knee", "/robot/left_knee"):
            node = CstomoSensorNode("cstomo_sensor", context=ctx, namespace=ns,
                                    parameter_overrides=[Parameter("autostart", value=False)])
            try:
                assert node.get_parameter("stale_timeout").value == 0.7, ns
            finally:
                node.destroy_node()
    finally:
        rclpy.try_shutdown(context=ctx)


def test_parameter_file_lists_every_parameter_with_the_declared_type(declared):
    params = yaml.safe_load(CONFIG.read_text())["/**/cstomo_sensor"]["ros__parameters"]
    assert set(params) == set(declared), set(params) ^ set(declared)
    from cstomo_sensor.ros.params import PARAMETERS

    for name, value in params.items():
        want = PARAMETERS[name][0]
        assert type(value) is type(want) or (isinstance(want, list) and isinstance(value, list)), name
        assert value == want, f"{name}: file {value!r}, node default {want!r}"
    # a comment on every parameter line
    lines = [ln for ln in CONFIG.read_text().splitlines() if ":" in ln and not ln.strip().startswith("#")]
    assert all("#" in ln for ln in lines if ln.strip().split(":")[0] in declared)
