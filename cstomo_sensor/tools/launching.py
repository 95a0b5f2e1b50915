"""What ``launch/cstomo_sensor.launch.py`` starts, decided in plain Python: :func:`launch_plan`.

launch/launch_ros do not install from the package index, so the decisions live here, where the
tests reach them; the launch file only turns a :class:`LaunchPlan` into launch actions. Arguments
are strings and are never evaluated. A plan holds, per sensor, the node (namespace, parameter file
and the parameters over it), the simulated board's command (``sim``) and the static transform of
its frame (``parent_frame``); and, with ``rviz``, RViz2 on a configuration written for these
sensors. Several sensors come from one YAML list (``sensors:=FILE``, :func:`read_sensor_list`),
each fully independent: its own namespace, frame, board, tare file and parameters.
"""
from __future__ import annotations

import copy
import difflib
import math
import os
import re
import shutil
import tempfile
from dataclasses import dataclass
from pathlib import Path

import yaml

from ..board.sim import DEFAULT_RATE_HZ
from ..cache import default_cache_dir
from ..errors import ConfigError, CstomoError
from ..force.reference.files import tare_file_name
from ..frames_io import read_load_script
from ..model.geometry import load_sensor
from ..settings import SETTING, default
from .common import PACKAGE, config_parameter, executable, package_executable, package_file

NODE_NAME = "cstomo_sensor"  # the node's name in every namespace (the parameter file's key)
#: The sensor's pose in its parent frame: metres and radians (roll about x, pitch about y, yaw about z).
POSE = ("x", "y", "z", "roll", "pitch", "yaw")
#: Launch arguments that override the node parameter of the same name, only when given.
NODE_ARGUMENTS = ("port", "sensor", "estimator", "frame_id", "calibration_file", "tare_on_start")
#: Launch arguments of one sensor: with ``sensors:=FILE`` they belong in the file's entries.
SENSOR_ARGUMENTS = (*NODE_ARGUMENTS, "namespace", "sim", "sim_load_script", "parent_frame", *POSE)
#: Keys of an entry of a sensor list (:func:`read_sensor_list`).
ENTRY_KEYS = ("namespace", "frame_id", "port", "sim", "sim_load_script", "sensor", "calibration_file", "tare_file",
              "tare_on_start", "parent_frame", "pose", "parameters")
#: Node parameters an entry sets through its own keys, not through ``parameters:``.
ENTRY_PARAMETERS = ("port", "sensor", "frame_id", "calibration_file", "tare_file", "tare_on_start")

#: The simulated board's default load script in a launch (time,fx,fy,fz in s and N, wrench frame):
#: unloaded for the tare, then pressing straight down, tilted towards +x, towards +y, and released.
SIM_LOAD = "time,fx,fy,fz\n0,0,0,0\n3,0,0,-20\n6,10,0,-15\n9,0,10,-15\n12,0,0,0\n"

_ROS_NAME = re.compile(r"^/?[A-Za-z][A-Za-z0-9_]*(/[A-Za-z][A-Za-z0-9_]*)*$")
_FRAME = re.compile(r"^[A-Za-z0-9_][A-Za-z0-9_./-]*$")


def _node_argument(name: str) -> tuple[str, str]:
    """A launch argument overriding node parameter ``name``: empty (the parameter file's value) and the
    setting's description."""
    return "", f"{SETTING[name].description} (empty: the parameter file's value)"


#: Every argument of launch/cstomo_sensor.launch.py: name -> (default, description); a default None is
#: a file of the installed package (the launch file finds it); a node argument's description is the
#: setting's (cstomo_sensor/settings.py).
ARGUMENTS = {
    "port": _node_argument("port"), "config": (None, "parameter file of the node(s)"),
    "sim": ("false", "true: also start `cstomo board-sim` and read its pty link"),
    **{name: _node_argument(name) for name in NODE_ARGUMENTS[1:]},
    "namespace": ("", "namespace of the node's topics"),
    "sim_load_script": ("", "with sim: load script CSV for the simulated board (empty: the built-in one)"),
    "parent_frame": ("", "frame the sensor is fixed to: also publish the static transform to frame_id"),
    "x": ("", "with parent_frame: the socket centre's x in parent_frame, metres (empty: 0)"),
    "y": ("", "with parent_frame: y, metres (empty: 0)"),
    "z": ("", "with parent_frame: z, metres (empty: 0)"),
    "roll": ("", "with parent_frame: rotation about x, radians (empty: 0)"),
    "pitch": ("", "with parent_frame: rotation about y, radians (empty: 0)"),
    "yaw": ("", "with parent_frame: rotation about z, radians (empty: 0)"),
    "sensors": ("", "YAML list of sensors (docs/robot.md) instead of the one of the arguments above; a relative "
                    "path from the current directory, else from the installed package (config/sensors_example.yaml)"),
    "rviz": ("false", "true: also start RViz2 showing the wrench and the stress cloud"),
    "rviz_config": (None, "RViz2 configuration whose /cstomo_sensor/... displays are repeated per sensor"),
    "rviz_fixed_frame": ("", "RViz fixed frame (empty: the first sensor's parent_frame, else its frame_id)"),
}


@dataclass(frozen=True)
class Transform:
    """The static transform ``parent`` -> ``child`` (the sensor's frame_id) that tf2_ros's
    ``static_transform_publisher`` publishes: the sensor's pose in its parent frame."""

    parent: str
    child: str
    pose: tuple[float, float, float, float, float, float] = (0.0,) * 6

    def arguments(self) -> list[str]:
        """The publisher's new-style arguments (``--x .. --yaw --frame-id --child-frame-id``)."""
        out = []
        for name, value in zip(POSE, self.pose):
            out += [f"--{name}", repr(float(value))]
        return out + ["--frame-id", self.parent, "--child-frame-id", self.child]


@dataclass(frozen=True)
class SensorPlan:
    """One sensor of a launch.

    Attributes
    ----------
    namespace : str
        The node's namespace ('' = the root); the node is ``<namespace>/cstomo_sensor``.
    config : str
        The parameter file (keyed ``/**/cstomo_sensor``: any namespace).
    overrides : dict
        Node parameters over the file (launch_ros: ``parameters=[config, overrides]``).
    frame_id : str
        The frame of its wrench and stress cloud (an override, else the file's, else the default).
    board : list of str or None
        Command of its simulated board (``sim``), else None.
    transform : Transform or None
        Its static transform (``parent_frame``), else None.
    """

    namespace: str
    config: str
    overrides: dict
    frame_id: str
    board: list[str] | None = None
    transform: Transform | None = None

    @property
    def node(self) -> str:
        """The node's fully qualified name."""
        ns = self.namespace.strip("/")
        return f"/{ns}/{NODE_NAME}" if ns else f"/{NODE_NAME}"

    def topic(self, name: str) -> str:
        """The absolute name of the node's topic ``~/name``."""
        return f"{self.node}/{name}"


@dataclass(frozen=True)
class LaunchPlan:
    """Everything a launch starts; ``work`` (None when nothing needs it) is a new temporary
    directory of this launch (simulated boards' links, load scripts and tares; the RViz
    configuration) that the caller removes at shutdown."""

    sensors: tuple[SensorPlan, ...]
    rviz: list[str] | None = None  # rviz2's arguments
    work: Path | None = None


def _bool(name: str, value: object, default: bool | None = None) -> bool | None:
    """A launch argument or YAML value as a bool; '' or None gives ``default``."""
    if isinstance(value, bool):
        return value
    text = "" if value is None else str(value).strip().lower()
    if text == "":
        return default
    if text in ("true", "1", "yes", "on"):
        return True
    if text in ("false", "0", "no", "off"):
        return False
    raise ConfigError.bad_value(name, value, "true or false")


def _number(name: str, value: object) -> float:
    try:
        x = float(value)
    except (TypeError, ValueError):
        x = math.nan
    if isinstance(value, bool) or not math.isfinite(x):
        raise ConfigError.bad_value(name, value, "a finite number (metres or radians)")
    return x


def _frame(name: str, value: object) -> str:
    if not isinstance(value, str) or not _FRAME.match(value):
        raise ConfigError.bad_value(name, value, "a TF frame name (letters, digits, '_', no leading '/')")
    return value


def _transform(where: str, parent: str, child: str, pose: dict) -> Transform | None:
    """The sensor's static transform, or None without a parent frame (then no pose may be given)."""
    given = {k: v for k, v in pose.items() if v not in ("", None)}
    if not parent:
        if given:
            raise ConfigError(f"{where}pose {sorted(given)} given without parent_frame: the pose is the sensor's "
                              "frame in its parent frame; name the parent (e.g. parent_frame:=tool0)")
        return None
    _frame(f"{where}parent_frame", parent)
    if parent == child:
        raise ConfigError(f"{where}parent_frame={parent!r} is the sensor's own frame_id: name the link it is fixed to")
    return Transform(parent, child, tuple(_number(f"{where}{k}", given.get(k, 0.0)) for k in POSE))


def _from_file(config: str, name: str) -> object | None:
    """Parameter ``name`` of the parameter file ``config`` ('' = none), or None if it does not set it."""
    if not config:
        return None
    try:
        return config_parameter(config, name)
    except OSError as err:
        raise ConfigError(f"config:={config}: {err.strerror or err}") from err
    except (yaml.YAMLError, AttributeError) as err:
        raise ConfigError(f"config:={config}: not a ROS parameter file ({err})") from err


def _file_or_default(config: str, name: str) -> object:
    value = _from_file(config, name)
    return default(name) if value is None else value


class _Work:
    """The launch's temporary directory, made when first needed."""

    def __init__(self) -> None:
        self.path: Path | None = None

    def __call__(self, *parts: str) -> Path:
        if self.path is None:
            self.path = Path(tempfile.mkdtemp(prefix="cstomo_launch_"))
        d = self.path.joinpath(*parts)
        d.mkdir(parents=True, exist_ok=True)
        return d


def _sim_board(work: Path, sensor: str, script: str | None) -> tuple[list[str], str, str]:
    """(board command, link, tare file) of a simulated board living in ``work``; a ``script`` that is no
    load script is refused here, before anything starts (else the board would fail alone and the node
    wait for it for ever)."""
    if not script:
        script = str(work / "load.csv")
        (work / "load.csv").write_text(SIM_LOAD)
    else:
        try:
            read_load_script(script)
        except CstomoError as err:
            raise ConfigError(f"sim_load_script:={script}: {err}") from None
        script = str(Path(script).resolve())
    link = str(work / "board")
    try:
        program = executable("cstomo")
    except CstomoError:
        program = "cstomo"  # not installed: check_executables says so
    cmd = [program, "board-sim", "--sensor", str(sensor), "--rate", f"{DEFAULT_RATE_HZ:g}", "--link", link,
           "--load-script", script]
    return cmd, link, str(work / "tare.csv")


#: How to install each package whose executables a launch starts ({distro}: $ROS_DISTRO).
INSTALL = {"tf2_ros": "sudo apt install ros-{distro}-tf2-ros", "rviz2": "sudo apt install ros-{distro}-rviz2",
           PACKAGE: "colcon build in its workspace, then source install/setup.sh"}


def check_executables(plan: LaunchPlan) -> None:
    """Refuse a plan that would start an executable that is not installed, before anything starts:
    raises :class:`ConfigError` naming every missing one, what needs it and the package to install.
    Nodes are found as launch_ros finds them (``lib/<package>/`` of the first ``AMENT_PREFIX_PATH``
    prefix holding the package: :func:`.common.package_executable`); a simulated board's command
    is run as the plan gives it."""
    needs = {}  # (what needs it, package, executable) -> found
    for sensor in plan.sensors:
        needs[("the node", PACKAGE, "cstomo_sensor_node")] = package_executable(PACKAGE, "cstomo_sensor_node")
        if sensor.board is not None:
            needs[("sim:=true", PACKAGE, "cstomo")] = shutil.which(sensor.board[0])
        if sensor.transform is not None:
            found = package_executable("tf2_ros", "static_transform_publisher")
            needs[("parent_frame", "tf2_ros", "static_transform_publisher")] = found
    if plan.rviz is not None:
        needs[("rviz:=true", "rviz2", "rviz2")] = package_executable("rviz2", "rviz2")
    distro = os.environ.get("ROS_DISTRO") or "$ROS_DISTRO"
    missing = [f"{why} needs {name} (package '{package}': {INSTALL[package].format(distro=distro)}), not found"
               for (why, package, name), found in needs.items() if not found]
    if missing:
        raise ConfigError("; ".join(missing))


def launch_plan(args: dict[str, str], check: bool = False) -> LaunchPlan:
    """The plan of a launch from its arguments (strings, never evaluated; a missing one is empty).

    One sensor from the arguments: ``port``, ``sensor``, ``estimator``, ``frame_id``,
    ``calibration_file`` and ``tare_on_start`` override the parameter file only when given; with
    ``sim`` true, the simulated board, its link, its load script (``sim_load_script`` or
    :data:`SIM_LOAD`) and the node's tare file live in the launch's temporary directory (two launches
    never share a link, a killed board leaves no stale link, and the simulated board's tare never
    replaces a real board's); with ``parent_frame``, a static transform from it to the node's frame
    at the pose ``x y z roll pitch yaw`` (metres, radians; 0 when not given).

    Several sensors with ``sensors:=FILE`` (:func:`read_sensor_list`); the one-sensor arguments
    must then be empty. ``rviz`` true adds RViz2 on a configuration written for these sensors from
    ``rviz_config`` (:func:`rviz_config`), fixed frame ``rviz_fixed_frame``, else the first sensor's
    parent frame, else its frame_id. With ``check`` (the launch file), every executable of the plan
    must be installed (:func:`check_executables`). Raises :class:`ConfigError` naming the argument or
    entry at fault, or what is not installed (nothing is started then, and no temporary directory is
    left).
    """
    work = _Work()
    try:
        sensors = _sensors(args, work)
        rviz_args = None
        if _bool("rviz", args.get("rviz"), False):
            template = args.get("rviz_config") or ""
            if not Path(template).is_file():
                raise ConfigError.bad_value("rviz_config", template, "an RViz configuration file")
            first = sensors[0]
            fixed = args.get("rviz_fixed_frame") or (first.transform.parent if first.transform else first.frame_id)
            path = work() / "cstomo_sensor.rviz"
            path.write_text(rviz_config(Path(template).read_text(), sensors, _frame("rviz_fixed_frame", fixed)))
            rviz_args = ["-d", str(path)]
        plan = LaunchPlan(tuple(sensors), rviz_args, work.path)
        if check:
            check_executables(plan)
    except BaseException:
        if work.path is not None:
            shutil.rmtree(work.path, ignore_errors=True)
        raise
    return plan


def _sensors(args: dict[str, str], work: _Work) -> list[SensorPlan]:
    config = args.get("config") or ""
    listing = args.get("sensors") or ""
    if listing:
        given = [k for k in SENSOR_ARGUMENTS if args.get(k) and not (k == "sim" and _bool("sim", args[k]) is False)]
        if given:
            raise ConfigError(f"sensors:={listing} names every sensor: {', '.join(f'{k}:={args[k]}' for k in given)}: "
                              "give these in its entries, not as arguments")
        found, places = package_file(listing)
        if found is None:
            raise ConfigError(f"sensors:={listing}: no such file: not {' nor '.join(map(str, places))}")
        listing = str(found)
        plans = [_entry_plan(entry, f"{listing}: sensor {i + 1} ({entry['namespace']}): ", config, work)
                 for i, entry in enumerate(read_sensor_list(listing))]
        _check_independent(listing, plans)
        return plans
    sim = _bool("sim", args.get("sim"), False)
    overrides: dict = {k: args[k] for k in NODE_ARGUMENTS if args.get(k) and k != "tare_on_start"}
    tare_on_start = _bool("tare_on_start", args.get("tare_on_start"))
    if tare_on_start is not None:
        overrides["tare_on_start"] = tare_on_start
    board = None
    if args.get("sim_load_script") and not sim:
        raise ConfigError(f"sim_load_script:={args['sim_load_script']} without sim:=true: it is the simulated "
                          "board's load script")
    if sim:
        sensor = args.get("sensor") or _from_file(config, "sensor") or default("sensor")
        board, link, tare = _sim_board(work(), str(sensor), args.get("sim_load_script"))
        overrides.update(port=link, tare_file=tare)
    frame_id = _frame("frame_id", overrides.get("frame_id") or _file_or_default(config, "frame_id"))
    transform = _transform("", args.get("parent_frame") or "", frame_id, {k: args.get(k) for k in POSE})
    return [SensorPlan(args.get("namespace") or "", config, overrides, frame_id, board, transform)]


def read_sensor_list(path: str | Path) -> list[dict]:
    """The entries of a sensor list: a YAML file holding ``sensors:``, a list of mappings (or the
    list itself), each with

    - ``namespace`` (required): the node's namespace, e.g. ``left_knee``;
    - ``frame_id`` (required): its wrench frame, distinct from every other sensor's;
    - ``port: /dev/...`` or ``sim: true`` (a simulated board of this launch), or
      ``parameters: {input: topic}``; ``sim_load_script`` with ``sim``;
    - optional ``sensor``, ``calibration_file``, ``tare_file``, ``tare_on_start``;
    - optional ``parent_frame`` and ``pose: {x, y, z, roll, pitch, yaw}`` (metres, radians; missing
      ones 0) or ``pose: [x, y, z, roll, pitch, yaw]``;
    - optional ``parameters``: any other node parameter (``estimator``, ``rate_hz``, ...).

    Raises :class:`ConfigError` naming the file, the entry and the key at fault.
    """
    p = Path(path)
    try:
        doc = yaml.safe_load(p.read_text(encoding="utf-8"))
    except OSError as err:
        raise ConfigError(f"sensors:={path}: {err.strerror or err}") from err
    except yaml.YAMLError as err:
        raise ConfigError(f"sensors:={path}: not YAML ({err})") from err
    if isinstance(doc, dict) and set(doc) == {"sensors"}:
        doc = doc["sensors"]
    if not isinstance(doc, list) or not doc:
        raise ConfigError(f"sensors:={path}: expected 'sensors:' holding a list of sensors (namespace, frame_id, "
                          "port or sim, ...)")
    out = []
    for i, entry in enumerate(doc):
        where = f"{path}: sensor {i + 1}"
        if not isinstance(entry, dict):
            raise ConfigError(f"{where}: expected a mapping (namespace:, frame_id:, port: or sim:, ...), got {entry!r}")
        for key in entry:
            if key not in ENTRY_KEYS:
                near = difflib.get_close_matches(str(key), ENTRY_KEYS, n=1)
                raise ConfigError(f"{where}: unknown key {key!r}" + (f" (did you mean {near[0]!r}?)" if near else "")
                                  + f"; expected {list(ENTRY_KEYS)}")
        for key in ("namespace", "frame_id"):
            if not entry.get(key):
                raise ConfigError(f"{where}: missing {key!r} (every sensor of a list names its own)")
        if not isinstance(entry["namespace"], str) or not _ROS_NAME.match(entry["namespace"]):
            raise ConfigError(f"{where}: namespace={entry['namespace']!r}: expected a ROS name (e.g. left_knee)")
        params = entry.get("parameters") or {}
        if not isinstance(params, dict):
            raise ConfigError(f"{where}: parameters={params!r}: expected a mapping of node parameters")
        managed = sorted(set(params) & set(ENTRY_PARAMETERS))
        if managed:
            raise ConfigError(f"{where}: give {managed} as the entry's own keys, not under parameters:")
        sim = _bool(f"{where}: sim", entry.get("sim"), False)
        topic = params.get("input") == "topic"
        if sum([sim, bool(entry.get("port")), topic]) != 1:
            raise ConfigError(f"{where}: give exactly one of port: DEVICE, sim: true or parameters: {{input: topic}}")
        if entry.get("sim_load_script") and not sim:
            raise ConfigError(f"{where}: sim_load_script without sim: true")
        out.append(dict(entry, sim=sim, parameters=dict(params)))
    return out


def _pose(where: str, pose: object) -> dict:
    if pose is None:
        return {}
    if isinstance(pose, (list, tuple)):
        if len(pose) != 6:
            raise ConfigError(f"{where}pose={pose!r}: expected [x, y, z, roll, pitch, yaw] (metres, radians)")
        return dict(zip(POSE, pose))
    if not isinstance(pose, dict) or set(pose) - set(POSE):
        raise ConfigError(f"{where}pose={pose!r}: expected a mapping of {list(POSE)} (metres, radians)")
    return dict(pose)


def _entry_plan(entry: dict, where: str, config: str, work: _Work) -> SensorPlan:
    """The plan of one entry of a sensor list (read_sensor_list checked its shape)."""
    namespace = entry["namespace"]
    params = entry["parameters"]
    frame_id = _frame(f"{where}frame_id", entry["frame_id"])
    sensor = str(entry.get("sensor") or _from_file(config, "sensor") or default("sensor"))
    overrides = dict(params, frame_id=frame_id)
    for key in ("sensor", "calibration_file"):
        if entry.get(key):
            overrides[key] = str(entry[key])
    tare_on_start = _bool(f"{where}tare_on_start", entry.get("tare_on_start"))
    if tare_on_start is not None:
        overrides["tare_on_start"] = tare_on_start
    board = None
    if entry["sim"]:
        slug = re.sub(r"[^A-Za-z0-9]+", "_", namespace).strip("_")
        board, port, tare = _sim_board(work(slug), sensor, entry.get("sim_load_script"))
    else:
        port = str(entry["port"]) if entry.get("port") else ""
        cache = params.get("cache_dir") or _from_file(config, "cache_dir") or default_cache_dir()
        geometry = load_sensor(sensor)
        tare = str(Path(cache) / tare_file_name(geometry.name, geometry.digest(), port or "topic", namespace))
    if port:
        overrides["port"] = port
    overrides["tare_file"] = str(Path(str(entry["tare_file"])).expanduser()) if entry.get("tare_file") else tare
    transform = _transform(where, entry.get("parent_frame") or "", frame_id, _pose(where, entry.get("pose")))
    return SensorPlan(namespace, config, overrides, frame_id, board, transform)


def _check_independent(listing: str, plans: list[SensorPlan]) -> None:
    """Two sensors of a list never share a node, a frame, a board or a tare file."""
    for what, key in (("namespace", lambda p: p.node), ("frame_id", lambda p: p.frame_id),
                      ("port", lambda p: p.overrides.get("port")), ("tare_file", lambda p: p.overrides["tare_file"])):
        seen: dict = {}
        for i, plan in enumerate(plans):
            value = key(plan)
            if value is None:
                continue
            if value in seen:
                raise ConfigError(f"sensors:={listing}: sensors {seen[value] + 1} and {i + 1} share the {what} "
                                  f"{value!r}: each sensor needs its own")
            seen[value] = i


def rviz_config(template: str, sensors: list[SensorPlan] | tuple[SensorPlan, ...], fixed_frame: str) -> str:
    """An RViz2 configuration for ``sensors`` from ``template`` (config/cstomo_sensor.rviz): every
    display of the template on a topic of the node at the root (``/cstomo_sensor/...``) is repeated
    for each sensor on that sensor's topic (named after its namespace when there are several or a
    namespace); every other display is kept as it is; the fixed frame is ``fixed_frame``."""
    doc = yaml.safe_load(template)
    manager = doc["Visualization Manager"]
    displays = []
    for d in manager.get("Displays") or []:
        topic = (d.get("Topic") or {}).get("Value", "") if isinstance(d.get("Topic"), dict) else ""
        if not topic.startswith(f"/{NODE_NAME}/"):
            displays.append(d)
            continue
        for plan in sensors:
            c = copy.deepcopy(d)
            c["Topic"]["Value"] = plan.topic(topic[len(NODE_NAME) + 2:])
            if len(sensors) > 1 or plan.namespace.strip("/"):
                c["Name"] = f"{plan.namespace.strip('/')} {d.get('Name', '')}".strip()
            displays.append(c)
    manager["Displays"] = displays
    manager.setdefault("Global Options", {})["Fixed Frame"] = fixed_frame
    return yaml.safe_dump(doc, sort_keys=False, default_flow_style=False, width=1000)
