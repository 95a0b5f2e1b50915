"""The launch file and the parameter file agree with the parameters the node really declares; what a
launch starts (one sensor or a list, static transforms, RViz) is right.

launch/launch_ros do not install from the package index: the launch file's argument table is parsed
(ast) and checked against the parameters of a node created for the purpose; what it starts is decided
by :func:`cstomo_sensor.tools.launching.launch_plan`, tested here directly; the launch file's few lines
that hand that plan to launch/launch_ros run here against stand-ins of launch's classes (recording the
keywords they get), so their names and keywords are as launch_ros documents them, not verified
against launch itself.
"""
from __future__ import annotations

from pathlib import Path

import pytest
import yaml

rclpy = pytest.importorskip("rclpy")

ROOT = Path(__file__).resolve().parent.parent
LAUNCH = ROOT / "launch" / "cstomo_sensor.launch.py"
CONFIG = ROOT / "config" / "cstomo_sensor.yaml"
RVIZ = ROOT / "config" / "cstomo_sensor.rviz"
EXAMPLE = ROOT / "config" / "sensors_example.yaml"
POSE = ("x", "y", "z", "roll", "pitch", "yaw")
# arguments of the launch itself, not node parameters
LAUNCH_ONLY = {"config", "sim", "sim_load_script", "namespace", "parent_frame", *POSE, "sensors", "rviz", "rviz_config",
               "rviz_fixed_frame"}


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
    """The launch file's arguments (name -> (default, description)): tools/launching.py's table, which
    the launch file declares (importing launch is not possible here: not installable from the index)."""
    from cstomo_sensor.tools.launching import ARGUMENTS

    assert "for name, (default, desc) in ARGUMENTS.items()" in LAUNCH.read_text()
    return ARGUMENTS


@pytest.mark.slow  # starts a node
def test_every_launch_argument_is_a_declared_parameter_and_defaults_to_the_file(declared):
    from cstomo_sensor.tools.launching import NODE_ARGUMENTS, SENSOR_ARGUMENTS

    args = _arguments()
    assert {"port", "config", "sim", "sensor", "estimator", "namespace", "sim_load_script", "frame_id",
            "calibration_file", "tare_on_start"} | LAUNCH_ONLY == set(args)
    node_args = set(args) - LAUNCH_ONLY
    assert node_args == set(NODE_ARGUMENTS) and set(SENSOR_ARGUMENTS) <= set(args)
    assert node_args <= set(declared), node_args - set(declared)
    # an argument left at its default never overrides the parameter file
    assert all(args[name][0] == "" for name in node_args), {n: args[n][0] for n in node_args}
    # `ros2 launch ... --show-args` prints "(default: '')" under each description: a description says what
    # empty means, never a "(default ...)" of its own beside launch's
    assert not [n for n, (default, desc) in args.items() if "(default" in desc], args
    src = LAUNCH.read_text()
    assert "PythonExpression" not in src and "eval(" not in src  # user text is never evaluated
    assert 'executable="cstomo_sensor_node"' in src and "name=NODE_NAME" in src


def _plan(**args):
    from cstomo_sensor.tools.launching import launch_plan

    return launch_plan({"config": str(CONFIG), **args})


def test_launch_plan_passes_arguments_verbatim_and_only_when_given():
    evil = "/dev/ttyACM0' + __import__('os').system('touch /tmp/pwned') + '"
    plan = _plan(port=evil, sim="false", sensor="", estimator="", namespace="", sim_load_script="")
    (one,) = plan.sensors
    assert one.overrides == {"port": evil} and one.board is None and plan.work is None and plan.rviz is None
    assert one.config == str(CONFIG) and one.transform is None and one.node == "/cstomo_sensor"
    (one,) = _plan(port="", sim="false", sensor="disc", estimator="model").sensors
    assert one.overrides == {"sensor": "disc", "estimator": "model"}
    (one,) = _plan(frame_id="tool_ft", calibration_file="/cal/left.yaml", tare_on_start="true").sensors
    assert one.overrides == {"frame_id": "tool_ft", "calibration_file": "/cal/left.yaml", "tare_on_start": True}
    assert one.frame_id == "tool_ft"
    assert _plan(tare_on_start="False").sensors[0].overrides == {"tare_on_start": False}  # a bool, not a string
    from cstomo_sensor.errors import ConfigError

    with pytest.raises(ConfigError, match="sim='yes please'"):
        _plan(sim="yes please")
    with pytest.raises(ConfigError, match="tare_on_start='maybe'"):
        _plan(tare_on_start="maybe")


def test_each_sim_launch_has_its_own_link_script_and_tare(tmp_path):
    import shutil

    cfg = tmp_path / "params.yaml"  # the sensor of the parameter file reaches the board when no argument names one
    cfg.write_text("/**/cstomo_sensor:\n  ros__parameters:\n    sensor: cylinder\n")
    plans = [_plan(port="/dev/cstomo", config=str(cfg), sim="true") for _ in range(2)]
    try:
        assert plans[0].work != plans[1].work and all(p.work.is_dir() for p in plans)
        for plan in plans:
            (one,) = plan.sensors
            o, b, w = one.overrides, one.board, plan.work
            assert o["port"] == b[b.index("--link") + 1] == str(w / "board")  # sim replaces the port
            assert Path(o["tare_file"]).parent == w  # the simulated board's tare is never a real board's
            assert b[b.index("--sensor") + 1] == "cylinder"
            script = Path(b[b.index("--load-script") + 1])
            assert script.parent == w and script.read_text().startswith("time,fx,fy,fz\n0,0,0,0\n")
            assert Path(b[0]).name == "cstomo" and Path(b[0]).is_file()
    finally:
        for plan in plans:
            shutil.rmtree(plan.work)


def test_a_wrong_sim_load_script_is_refused_before_anything_starts(tmp_path, monkeypatch):
    """Before: sim_load_script:=missing.csv was handed to the board, which failed alone while the node
    waited for its port for ever; without sim:=true it was ignored. Now refused at launch, in one line,
    with no temporary directory left; a good script's relative path reaches the board absolute."""
    import shutil
    import tempfile

    from cstomo_sensor.errors import ConfigError

    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path / "tmp"))
    (tmp_path / "tmp").mkdir()
    monkeypatch.chdir(tmp_path)
    (tmp_path / "bare.csv").write_text("0,0,0,0\n3,0,0,-20\n")
    with pytest.raises(ConfigError, match=r"^sim_load_script:=missing\.csv: missing\.csv: cannot be read \(No such file"):
        _plan(sim="true", sim_load_script="missing.csv")
    with pytest.raises(ConfigError, match=r"^sim_load_script:=bare\.csv: bare\.csv:1: header .*time,fx,fy,fz"):
        _plan(sim="true", sim_load_script="bare.csv")
    with pytest.raises(ConfigError, match=r"^sim_load_script:=bare\.csv without sim:=true"):
        _plan(sim_load_script="bare.csv")
    assert not list((tmp_path / "tmp").iterdir())
    (tmp_path / "load.csv").write_text("time,fx,fy,fz\n0,0,0,0\n3,0,0,-20\n")
    plan = _plan(sim="true", sim_load_script="load.csv")
    try:
        b = plan.sensors[0].board
        assert b[b.index("--load-script") + 1] == str(tmp_path / "load.csv")
    finally:
        shutil.rmtree(plan.work)


def test_parent_frame_adds_the_static_transform_of_the_pose(tmp_path):
    (one,) = _plan(parent_frame="tool0", x="0.01", y="-0.02", z="0.115", roll="0", pitch="-1.5708", yaw="3.1416").sensors
    assert one.frame_id == "cstomo_socket"  # the parameter file's
    assert one.transform.arguments() == ["--x", "0.01", "--y", "-0.02", "--z", "0.115", "--roll", "0.0",
                                         "--pitch", "-1.5708", "--yaw", "3.1416", "--frame-id", "tool0",
                                         "--child-frame-id", "cstomo_socket"]
    assert "frame_id" not in one.overrides  # the node keeps the file's frame_id, the transform names it
    (one,) = _plan(parent_frame="base_link", frame_id="wrist_socket", namespace="wrist").sensors
    assert one.transform.arguments()[-4:] == ["--frame-id", "base_link", "--child-frame-id", "wrist_socket"]
    assert one.transform.pose == (0.0,) * 6 and one.overrides == {"frame_id": "wrist_socket"}
    cfg = tmp_path / "params.yaml"  # a frame_id in the user's parameter file is the transform's child
    cfg.write_text("/**/cstomo_sensor:\n  ros__parameters:\n    frame_id: knee_ft\n")
    assert _plan(config=str(cfg), parent_frame="shank").sensors[0].transform.child == "knee_ft"
    assert _plan(config=str(cfg)).sensors[0].transform is None
    from cstomo_sensor.errors import ConfigError

    with pytest.raises(ConfigError, match="without parent_frame"):
        _plan(z="0.1")
    with pytest.raises(ConfigError, match="yaw='quarter'"):
        _plan(parent_frame="tool0", yaw="quarter")
    with pytest.raises(ConfigError, match="x='nan'"):
        _plan(parent_frame="tool0", x="nan")
    with pytest.raises(ConfigError, match="own frame_id"):
        _plan(parent_frame="cstomo_socket")
    with pytest.raises(ConfigError, match="parent_frame='/world'"):
        _plan(parent_frame="/world")
    with pytest.raises(ConfigError, match="config:=/no/such.yaml: No such file"):
        _plan(config="/no/such.yaml")
    from cstomo_sensor.tools.launching import launch_plan

    assert launch_plan({"frame_id": "f"}).sensors[0].config == ""  # no parameter file: the node's defaults
    assert launch_plan({}).sensors[0].frame_id == "cstomo_socket"


def _sensor_list(tmp_path, entries: list[dict]) -> str:
    f = tmp_path / "sensors.yaml"
    f.write_text(yaml.safe_dump({"sensors": entries}))
    return str(f)


def test_the_example_list_starts_two_independent_simulated_sensors():
    import shutil

    plan = _plan(sensors=str(EXAMPLE), sim="false")  # the launch's default sim=false is no one-sensor argument
    try:
        left, right = plan.sensors
        assert (left.node, right.node) == ("/left_knee/cstomo_sensor", "/right_knee/cstomo_sensor")
        assert left.topic("wrench") == "/left_knee/cstomo_sensor/wrench"
        assert (left.frame_id, right.frame_id) == ("left_knee_socket", "right_knee_socket")
        assert left.overrides["frame_id"] == "left_knee_socket" and right.overrides["estimator"] == "model"
        for one in (left, right):
            o, b = one.overrides, one.board
            work = plan.work / one.namespace
            assert o["port"] == b[b.index("--link") + 1] == str(work / "board") and o["tare_file"] == str(work / "tare.csv")
            assert o["tare_on_start"] is True and o["sensor"] == "cuboid_joint" and one.config == str(CONFIG)
        assert left.overrides["tare_file"] != right.overrides["tare_file"]
        assert left.transform.arguments() == ["--x", "0.0", "--y", "0.0", "--z", "0.12", "--roll", "0.0",
                                              "--pitch", "0.0", "--yaw", "0.0", "--frame-id", "left_shank",
                                              "--child-frame-id", "left_knee_socket"]
        assert right.transform.parent == "right_shank" and right.transform.pose[5] == pytest.approx(3.14159265)
        assert plan.rviz is None
    finally:
        shutil.rmtree(plan.work)


def test_sensors_on_ports_or_topics_get_tare_files_of_their_own(tmp_path):
    from cstomo_sensor.force.reference.files import tare_file_name
    from cstomo_sensor.model.geometry import load_sensor

    entries = [{"namespace": "left_knee", "frame_id": "l_socket", "port": "/dev/cstomo_l", "calibration_file": "/c/l.yaml"},
               {"namespace": "robot/right_knee", "frame_id": "r_socket", "parameters": {"input": "topic"}},
               {"namespace": "hip", "frame_id": "h_socket", "parameters": {"input": "topic", "cache_dir": str(tmp_path)}},
               {"namespace": "ankle", "frame_id": "a_socket", "port": "/dev/cstomo_a", "tare_file": "~/ankle.csv",
                "pose": [0.0, 0.0, 0.1, 0.0, 0.0, 0.0], "parent_frame": "foot"}]
    plan = _plan(sensors=_sensor_list(tmp_path, entries))
    assert plan.work is None  # nothing simulated, no RViz: no temporary directory
    left, right, hip, ankle = plan.sensors
    g = load_sensor("cuboid_joint")
    cache = Path(__import__("os").environ["CSTOMO_CACHE_DIR"])
    assert left.overrides == {"frame_id": "l_socket", "port": "/dev/cstomo_l", "calibration_file": "/c/l.yaml",
                              "tare_file": str(cache / f"tare_left_knee-cuboid_joint-{g.digest()[:8]}-dev_cstomo_l.csv")}
    # two sensors on topic input have the same device key: the namespace keeps their tares apart
    assert Path(right.overrides["tare_file"]).name == tare_file_name(g.name, g.digest(), "topic", "robot/right_knee")
    assert Path(hip.overrides["tare_file"]) == tmp_path / tare_file_name(g.name, g.digest(), "topic", "hip")
    assert right.overrides["input"] == "topic" and "port" not in right.overrides and right.node == "/robot/right_knee/cstomo_sensor"
    assert ankle.overrides["tare_file"] == str(Path("~/ankle.csv").expanduser()) and ankle.transform.pose[2] == 0.1
    assert len({p.overrides["tare_file"] for p in plan.sensors}) == 4
    # the node's own default (no namespace) is unchanged: tare_<sensor>-<digest>-<port>.csv
    assert tare_file_name(g.name, g.digest(), "/dev/cstomo") == f"tare_cuboid_joint-{g.digest()[:8]}-dev_cstomo.csv"


@pytest.mark.parametrize("change, match", [
    (lambda e: e[1].update(namespace="left_knee"), "share the namespace '/left_knee/cstomo_sensor'"),
    (lambda e: e[1].update(namespace="/left_knee"), "share the namespace"),
    (lambda e: e[1].update(frame_id="l_socket"), "share the frame_id 'l_socket'"),
    (lambda e: e[1].update(port="/dev/cstomo_l"), "share the port '/dev/cstomo_l'"),
    (lambda e: [x.update(tare_file="/t/same.csv") for x in e], "share the tare_file '/t/same.csv'"),
    (lambda e: e[0].update(frame_ide="x"), "unknown key 'frame_ide' \\(did you mean 'frame_id'\\?\\)"),
    (lambda e: e[0].pop("frame_id"), "sensor 1: missing 'frame_id'"),
    (lambda e: e[0].update(sim=True), "exactly one of port: DEVICE, sim: true"),
    (lambda e: e[0].pop("port"), "exactly one of port: DEVICE, sim: true"),
    (lambda e: e[0].update(parameters={"frame_id": "x"}), "give \\['frame_id'\\] as the entry's own keys"),
    (lambda e: e[0].update(pose={"z": 0.1}), "pose \\['z'\\] given without parent_frame"),
    (lambda e: e[0].update(pose={"height": 0.1}, parent_frame="shank"), "expected a mapping of"),
    (lambda e: e[0].update(namespace="left knee"), "namespace='left knee'"),
    (lambda e: e[0].update(sim_load_script="x.csv"), "sim_load_script without sim"),
])
def test_a_wrong_sensor_list_is_refused_naming_the_entry(tmp_path, change, match):
    from cstomo_sensor.errors import ConfigError

    entries = [{"namespace": "left_knee", "frame_id": "l_socket", "port": "/dev/cstomo_l"},
               {"namespace": "right_knee", "frame_id": "r_socket", "port": "/dev/cstomo_r"}]
    change(entries)
    with pytest.raises(ConfigError, match=match):
        _plan(sensors=_sensor_list(tmp_path, entries))


def test_a_list_excludes_the_one_sensor_arguments_and_leaves_no_directory(tmp_path, monkeypatch):
    import tempfile

    from cstomo_sensor.errors import ConfigError

    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))
    with pytest.raises(ConfigError, match="names every sensor: port:=/dev/x, namespace:=n: give these in its entries"):
        _plan(sensors=str(EXAMPLE), port="/dev/x", namespace="n")
    with pytest.raises(ConfigError, match="not YAML|expected 'sensors:'"):
        _plan(sensors=str(CONFIG))
    # the first sensor is simulated (a directory made), the second is wrong: nothing is left behind
    entries = [{"namespace": "a", "frame_id": "a_socket", "sim": True}, {"namespace": "b", "frame_id": "a_socket", "sim": True}]
    with pytest.raises(ConfigError, match="share the frame_id"):
        _plan(sensors=_sensor_list(tmp_path, entries))
    assert not list(tmp_path.glob("cstomo_launch_*"))


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


@pytest.mark.slow  # starts a node
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


@pytest.mark.slow  # starts a node
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


# --- RViz ---------------------------------------------------------------------------------------------

ROS_CLASSES = {"rviz_default_plugins/Wrench": "geometry_msgs/msg/WrenchStamped",
               "rviz_default_plugins/PointCloud2": "sensor_msgs/msg/PointCloud2"}


def _displays(doc: dict) -> dict:
    """topic -> display of an RViz configuration's displays that subscribe to a topic."""
    out = {}
    for d in doc["Visualization Manager"]["Displays"]:
        assert d["Class"].startswith(("rviz_default_plugins/", "rviz_common/")), d["Class"]
        if "Topic" in d:
            out[d["Topic"]["Value"]] = d
    return out


@pytest.mark.slow  # starts a node
def test_the_rviz_config_parses_and_shows_what_the_node_publishes(declared):
    from cstomo_sensor.ros.messages import CLOUD_FIELDS, TOPIC_TYPES

    doc = yaml.safe_load(RVIZ.read_text())
    assert {p["Class"] for p in doc["Panels"]} <= {"rviz_common/Displays", "rviz_common/Views"}
    assert doc["Visualization Manager"]["Global Options"]["Fixed Frame"] == declared["frame_id"] == "cstomo_socket"
    shown = _displays(doc)
    for topic, d in shown.items():
        node, name = topic.rsplit("/", 1)
        assert node == "/cstomo_sensor", topic  # the node's ~/ at the root (the launch rewrites namespaces)
        assert TOPIC_TYPES[name] == ROS_CLASSES[d["Class"]], topic  # a topic of the node, of the display's type
    wrench, cloud = shown["/cstomo_sensor/wrench"], shown["/cstomo_sensor/stress_field"]
    assert wrench["Enabled"] and cloud["Enabled"]
    assert cloud["Color Transformer"] == "Intensity" and cloud["Channel Name"] == "pressure" and "pressure" in CLOUD_FIELDS
    assert 0 < wrench["Force Arrow Scale"] * 40 < 0.2  # the rated 40 N is an arrow of a few cm, not metres


def test_rviz_shows_every_sensor_of_a_list_in_its_namespace(tmp_path, monkeypatch):
    import shutil
    import tempfile

    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))
    plan = _plan(sensors=str(EXAMPLE), rviz="true", rviz_config=str(RVIZ))
    try:
        assert plan.rviz[0] == "-d" and Path(plan.rviz[1]).parent == plan.work
        doc = yaml.safe_load(Path(plan.rviz[1]).read_text())
        assert doc["Visualization Manager"]["Global Options"]["Fixed Frame"] == "left_shank"  # the first's parent
        shown = _displays(doc)
        template = _displays(yaml.safe_load(RVIZ.read_text()))
        assert set(shown) == {t.replace("/cstomo_sensor/", f"/{ns}/cstomo_sensor/") for t in template
                              for ns in ("left_knee", "right_knee")}
        for one in plan.sensors:
            assert shown[one.topic("wrench")]["Name"].startswith(one.namespace) and shown[one.topic("stress_field")]["Enabled"]
    finally:
        shutil.rmtree(plan.work)
    plan = _plan(rviz="true", rviz_config=str(RVIZ))  # one sensor at the root, no parent: the file as it is
    try:
        doc = yaml.safe_load(Path(plan.rviz[1]).read_text())
        assert _displays(doc).keys() == template.keys() and "Wrench" in _displays(doc)["/cstomo_sensor/wrench"]["Name"]
        assert doc["Visualization Manager"]["Global Options"]["Fixed Frame"] == "cstomo_socket"
    finally:
        shutil.rmtree(plan.work)
    plan = _plan(rviz="true", rviz_config=str(RVIZ), parent_frame="tool0", rviz_fixed_frame="world", namespace="arm")
    try:
        doc = yaml.safe_load(Path(plan.rviz[1]).read_text())
        assert doc["Visualization Manager"]["Global Options"]["Fixed Frame"] == "world"
        assert "/arm/cstomo_sensor/wrench" in _displays(doc)
    finally:
        shutil.rmtree(plan.work)
    from cstomo_sensor.errors import ConfigError

    with pytest.raises(ConfigError, match="rviz_config"):
        _plan(rviz="true", rviz_config=str(tmp_path / "none.rviz"))
    assert not list(tmp_path.glob("cstomo_launch_*"))


# --- the launch file's own lines, on stand-ins of launch's classes ------------------------------------


def _load_launch_file(monkeypatch):
    """Import launch/cstomo_sensor.launch.py with stand-ins of launch, launch_ros and
    ament_index_python that record their keywords."""
    import importlib.util
    import sys
    import types

    class Rec:
        made: list = []  # every action made, in order

        def __init__(self, *args, **kwargs):
            self.args, self.kwargs = args, kwargs
            Rec.made.append(self)

    kinds = {}
    for kind in ("DeclareLaunchArgument", "ExecuteProcess", "OpaqueFunction", "RegisterEventHandler", "OnShutdown",
                 "LifecycleNode", "Node", "LaunchDescription", "Shutdown"):
        kinds[kind] = type(kind, (Rec,), {})

    class LaunchConfiguration:
        def __init__(self, name):
            self.name = name

        def perform(self, context):
            return context[self.name]

    mods = {"launch": {"LaunchDescription": kinds["LaunchDescription"]},
            "launch.actions": {k: kinds[k] for k in ("DeclareLaunchArgument", "ExecuteProcess", "OpaqueFunction",
                                                     "RegisterEventHandler", "Shutdown")},
            "launch.event_handlers": {"OnShutdown": kinds["OnShutdown"]},
            "launch.substitutions": {"LaunchConfiguration": LaunchConfiguration},
            "launch_ros": {}, "launch_ros.actions": {"LifecycleNode": kinds["LifecycleNode"], "Node": kinds["Node"]},
            "ament_index_python": {},
            "ament_index_python.packages": {"get_package_share_directory": lambda pkg: str(ROOT)}}
    for name, attrs in mods.items():
        monkeypatch.setitem(sys.modules, name, types.SimpleNamespace(**attrs, __path__=[]))
    spec = importlib.util.spec_from_file_location("cstomo_launch_under_test", LAUNCH)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module, kinds


def _ament_prefix(root: Path, packages: dict[str, list[str]]) -> Path:
    """A colcon install prefix holding ``packages`` (name -> its executables, stub scripts)."""
    index = root / "share" / "ament_index" / "resource_index" / "packages"
    index.mkdir(parents=True, exist_ok=True)
    for package, names in packages.items():
        (index / package).write_text("")
        (root / "lib" / package).mkdir(parents=True, exist_ok=True)
        for name in names:
            exe = root / "lib" / package / name
            exe.write_text("#!/bin/sh\n")
            exe.chmod(0o755)
    return root


#: What a full launch (node, static transform, RViz) starts through launch_ros, by package.
INSTALLED = {"cstomo_sensor": ["cstomo_sensor_node"], "tf2_ros": ["static_transform_publisher"], "rviz2": ["rviz2"]}


def test_the_launch_file_turns_the_plan_into_its_actions(monkeypatch, tmp_path):
    import tempfile

    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))
    monkeypatch.setenv("AMENT_PREFIX_PATH", str(_ament_prefix(tmp_path / "install", INSTALLED)))
    module, kinds = _load_launch_file(monkeypatch)
    ld = module.generate_launch_description()
    declared_args = {a.args[0]: a.kwargs["default_value"] for a in ld.args[0] if isinstance(a, kinds["DeclareLaunchArgument"])}
    assert declared_args["config"] == str(CONFIG) and declared_args["rviz_config"] == str(RVIZ)
    assert set(declared_args) == set(_arguments())
    (setup,) = [a for a in ld.args[0] if isinstance(a, kinds["OpaqueFunction"])]
    context = dict(declared_args, sensors=str(EXAMPLE), rviz="true")
    actions = setup.kwargs["function"](context)
    by_kind = {}
    for a in actions:
        by_kind.setdefault(type(a).__name__, []).append(a)
    (cleanup,) = by_kind["RegisterEventHandler"]
    work = next(tmp_path.glob("cstomo_launch_*"))
    boards = [a.kwargs["cmd"] for a in by_kind["ExecuteProcess"]]
    assert [b[b.index("--link") + 1] for b in boards] == [str(work / ns / "board") for ns in ("left_knee", "right_knee")]
    nodes = by_kind["LifecycleNode"]
    assert [(n.kwargs["namespace"], n.kwargs["name"], n.kwargs["executable"]) for n in nodes] == [
        ("left_knee", "cstomo_sensor", "cstomo_sensor_node"), ("right_knee", "cstomo_sensor", "cstomo_sensor_node")]
    assert nodes[0].kwargs["parameters"][0] == str(CONFIG)
    assert nodes[1].kwargs["parameters"][1]["frame_id"] == "right_knee_socket"
    # a node that exits with an error (a refused parameter) ends the launch, naming it; a clean exit or
    # one while the launch stops does not
    from types import SimpleNamespace as NS

    (stop,) = nodes[1].kwargs["on_exit"](NS(returncode=1), NS(is_shutdown=False))
    assert isinstance(stop, kinds["Shutdown"]) and stop.kwargs["reason"] == "/right_knee/cstomo_sensor exited with code 1"
    assert nodes[1].kwargs["on_exit"](NS(returncode=0), NS(is_shutdown=False)) is None
    assert nodes[1].kwargs["on_exit"](NS(returncode=-9), NS(is_shutdown=True)) is None
    tf = [n for n in by_kind["Node"] if n.kwargs["package"] == "tf2_ros"]
    assert [(n.kwargs["executable"], n.kwargs["namespace"]) for n in tf] == [
        ("static_transform_publisher", "left_knee"), ("static_transform_publisher", "right_knee")]
    assert tf[1].kwargs["arguments"][-4:] == ["--frame-id", "right_shank", "--child-frame-id", "right_knee_socket"]
    (rviz,) = [n for n in by_kind["Node"] if n.kwargs["package"] == "rviz2"]
    assert rviz.kwargs["executable"] == "rviz2" and rviz.kwargs["arguments"] == ["-d", str(work / "cstomo_sensor.rviz")]
    cleanup.args[0].kwargs["on_shutdown"]()  # the launch's end removes its directory
    assert not work.exists()
    # the defaults: one node at the root, nothing else
    actions = setup.kwargs["function"](declared_args)
    assert [type(a).__name__ for a in actions] == ["LifecycleNode"] and actions[0].kwargs["parameters"] == [str(CONFIG), {}]


def test_a_launch_missing_an_executable_is_refused_before_anything_starts(monkeypatch, tmp_path):
    import re
    import tempfile

    from cstomo_sensor.errors import ConfigError

    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))
    monkeypatch.delenv("ROS_DISTRO", raising=False)
    without_rviz = {k: v for k, v in INSTALLED.items() if k != "rviz2"}
    monkeypatch.setenv("AMENT_PREFIX_PATH", str(_ament_prefix(tmp_path / "install", without_rviz)))
    module, kinds = _load_launch_file(monkeypatch)
    ld = module.generate_launch_description()
    declared_args = {a.args[0]: a.kwargs["default_value"] for a in ld.args[0] if isinstance(a, kinds["DeclareLaunchArgument"])}
    (setup,) = [a for a in ld.args[0] if isinstance(a, kinds["OpaqueFunction"])]
    before = len(kinds["Node"].made)
    args = dict(declared_args, sim="true", parent_frame="shank", rviz="true")
    with pytest.raises(ConfigError) as err:
        setup.kwargs["function"](args)
    assert str(err.value) == "rviz:=true needs rviz2 (package 'rviz2': sudo apt install ros-$ROS_DISTRO-rviz2), not found"
    assert len(kinds["Node"].made) == before  # no action made: no board, no node, no transform started
    assert not list(tmp_path.glob("cstomo_launch_*"))  # nor its directory left
    # every missing one at once, with the package to install
    monkeypatch.setenv("AMENT_PREFIX_PATH", str(_ament_prefix(tmp_path / "empty", {})))
    monkeypatch.setenv("ROS_DISTRO", "kilted")
    with pytest.raises(ConfigError) as err:
        setup.kwargs["function"](args)
    assert str(err.value).split("; ") == [
        "the node needs cstomo_sensor_node (package 'cstomo_sensor': colcon build in its workspace, then source "
        "install/setup.sh), not found",
        "parent_frame needs static_transform_publisher (package 'tf2_ros': sudo apt install ros-kilted-tf2-ros), not found",
        "rviz:=true needs rviz2 (package 'rviz2': sudo apt install ros-kilted-rviz2), not found"]
    assert len(kinds["Node"].made) == before and not list(tmp_path.glob("cstomo_launch_*"))
    # a board that cannot be found is named too
    monkeypatch.setenv("AMENT_PREFIX_PATH", str(tmp_path / "install"))
    from cstomo_sensor.tools import launching

    monkeypatch.setattr(launching, "executable", lambda name: (_ for _ in ()).throw(launching.CstomoError(name)))
    monkeypatch.setenv("PATH", str(tmp_path / "empty"))
    with pytest.raises(ConfigError, match=re.escape("sim:=true needs cstomo (package 'cstomo_sensor'")):
        setup.kwargs["function"](dict(declared_args, sim="true"))
    assert len(kinds["Node"].made) == before and not list(tmp_path.glob("cstomo_launch_*"))
    # without launch's check (the tests' plans), the same plan is made
    plan = launching.launch_plan(args)
    assert plan.rviz is not None and plan.sensors[0].board[0] == "cstomo"
    import shutil

    shutil.rmtree(plan.work)


def test_a_sensor_list_is_found_here_else_in_the_installed_package(monkeypatch, tmp_path):
    from cstomo_sensor.errors import ConfigError

    prefix = _ament_prefix(tmp_path / "install", {"cstomo_sensor": []})
    (prefix / "share" / "cstomo_sensor" / "config").mkdir(parents=True)
    listing = "config/sensors.yaml"
    (prefix / "share" / "cstomo_sensor" / listing).write_text(
        yaml.safe_dump({"sensors": [{"namespace": "installed", "frame_id": "f", "port": "/dev/x"}]}))
    monkeypatch.setenv("AMENT_PREFIX_PATH", str(prefix))
    ws = tmp_path / "ws"
    ws.mkdir()
    monkeypatch.chdir(ws)  # a workspace root: no config/ here
    assert [s.namespace for s in _plan(sensors=listing).sensors] == ["installed"]
    (ws / "config").mkdir()
    (ws / listing).write_text(yaml.safe_dump({"sensors": [{"namespace": "here", "frame_id": "f", "port": "/dev/x"}]}))
    assert [s.namespace for s in _plan(sensors=listing).sensors] == ["here"]  # the current directory first
    with pytest.raises(ConfigError) as err:
        _plan(sensors="config/none.yaml")
    assert str(err.value) == (f"sensors:=config/none.yaml: no such file: not {ws / 'config/none.yaml'} nor "
                              f"{prefix / 'share/cstomo_sensor/config/none.yaml'}")


def test_package_xml_declares_tf2_ros_for_the_static_transform():
    import xml.etree.ElementTree as ET

    deps = {e.text for e in ET.parse(ROOT / "package.xml").getroot().iter("exec_depend")}
    assert "tf2_ros" in deps
