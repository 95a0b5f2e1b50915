"""The launch file and the parameter file agree with the parameters the node really declares.

launch/launch_ros do not install from the package index: the launch file is parsed (ast) and its
arguments are checked against the parameters of a node created for the purpose.
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


def _calls(tree, name):
    return [n for n in ast.walk(tree) if isinstance(n, ast.Call)
            and getattr(n.func, "id", getattr(n.func, "attr", None)) == name]


def test_every_launch_argument_maps_onto_a_declared_parameter(declared):
    tree = ast.parse(LAUNCH.read_text())
    args = {c.args[0].value for c in _calls(tree, "DeclareLaunchArgument")}
    assert {"port", "config", "sim", "sensor", "estimator", "namespace"} <= args
    (node,) = _calls(tree, "LifecycleNode")
    kw = {k.arg: k.value for k in node.keywords}
    assert kw["executable"].value == "cstomo_sensor_node" and kw["name"].value == "cstomo_sensor"
    dicts = [d for d in kw["parameters"].elts if isinstance(d, ast.Dict)]
    mapped = {k.value for d in dicts for k in d.keys}
    assert mapped <= set(declared), mapped - set(declared)
    assert args - LAUNCH_ONLY == mapped, (args - LAUNCH_ONLY) ^ mapped
    # the launch-only arguments are used: config as the parameter file, namespace for the node, sim as a condition
    src = LAUNCH.read_text()
    assert 'LaunchConfiguration("config")' in src and 'namespace=LaunchConfiguration("namespace")' in src
    assert "IfCondition(sim)" in src and "--link" in src


def test_parameter_file_lists_every_parameter_with_the_declared_type(declared):
    params = yaml.safe_load(CONFIG.read_text())["cstomo_sensor"]["ros__parameters"]
    assert set(params) == set(declared), set(params) ^ set(declared)
    from cstomo_sensor.ros.params import PARAMETERS

    for name, value in params.items():
        want = PARAMETERS[name][0]
        assert type(value) is type(want) or (isinstance(want, list) and isinstance(value, list)), name
        assert value == want, f"{name}: file {value!r}, node default {want!r}"
    # a comment on every parameter line
    lines = [ln for ln in CONFIG.read_text().splitlines() if ":" in ln and not ln.strip().startswith("#")]
    assert all("#" in ln for ln in lines if ln.strip().split(":")[0] in declared)
