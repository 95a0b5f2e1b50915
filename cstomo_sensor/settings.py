"""Every setting of the node, declared once: name, default, range or choices, unit and description.

The node's parameters (their ROS descriptors: ros/params.py), the defaults and range checks
(:func:`check_config`) of :class:`~.frame_path.config.PipelineConfig`, :class:`~.frame_path.config.StreamConfig`
and the node's ``NodeConfig``, the command-line flags that mirror a setting (:func:`.tools.common.add_setting_arg`),
the launch arguments that override one (:mod:`.tools.launching`), ``cstomo_sensor_node --help``,
``config/cstomo_sensor.yaml`` and the parameter table of docs/node.md all come from :data:`SETTINGS`;
the last two are written by ``python -m cstomo_sensor.settings yaml|markdown`` and held equal by
test/test_settings.py. No ROS here, and nothing of the package but errors.py: a leaf every layer may read.
"""
from __future__ import annotations

import math
import sys
import textwrap
from dataclasses import dataclass, fields

from .errors import ConfigError

# settings.py imports nothing of the package but errors.py: the modules that read a setting (model/,
# force/, inverse/, board/, ros/, tools/) are never imported back by it. The values below are what both
# a setting and its owner use: declared here once, imported by the owner (named beside each).
#: The wire modes a board may speak (board/wire.py); the first is the default.
PROTOCOLS = ("binary", "text")
#: The force estimators by name (force/estimators/estimate.py); the first is the default: ``model``, the more accurate,
#: whose per-frame cost with the drift tracking (``cstomo bench --frame-cost``) is within the 0.1 ms aim.
ESTIMATORS = ("model", "linear")
#: The sensor of the node, the tools and the benchmark unless told otherwise (a preset name, model/geometry.py).
DEFAULT_SENSOR = "cuboid_joint"
#: m: the element sizes a mesh may be asked for (model/mesh.py).
MESH_SIZE_RANGE = (2.0e-4, 2.0e-2)
#: The typical rubber's creep per decade (model/material.py's creep law), the middle of the documented
#: 2..6 % per decade: the one declaration of both what the frame stream compensates without a calibration
#: (``creep_per_decade``, force/slow_states/creep.py) and how the simulated board's rubber creeps by default
#: (``cstomo board-sim --creep``), so that the node with its defaults reads a held load of the simulated
#: board with its defaults constant.
TYPICAL_CREEP_PER_DECADE = 0.04
#: The largest creep coefficient taken (rubbers: 0.02..0.06); the compensation (force/slow_states/creep.py) feeds back
#: its own output, stable to about 0.3 per decade.
MAX_CREEP = 0.2
#: The rated force range of the socket (docs/physics.md#loads): the calibration's largest load
#: (force/estimators/training.py ``CalibrationSpec.magnitudes``), N.
RATED_FORCE = 40.0

INPUTS = ("serial", "topic")
RELIABILITIES = ("system_default", "reliable", "best_effort")
_KINDS = {bool: "true or false", int: "an integer", float: "a finite number", str: "a string"}


@dataclass(frozen=True)
class Setting:
    """One setting. ``lo..hi`` (inclusive) bounds a number, or each number of a tuple; ``choices``
    a string; ``read_only`` False: it may change while the node runs."""

    name: str
    default: bool | int | float | str | tuple
    description: str
    lo: int | float | None = None
    hi: int | float | None = None
    unit: str = ""
    choices: tuple[str, ...] = ()
    read_only: bool = True

    @property
    def range(self) -> str:
        """The values it takes, in words ('' for any string)."""
        if self.choices:
            return "one of " + ", ".join(self.choices)
        if self.lo is None:
            return ""
        span = f"{_number(self.lo)}..{_number(self.hi)}" + (f" {self.unit}" if self.unit else "")
        return f"{len(self.default)} numbers, each {span}" if isinstance(self.default, tuple) else span

    def problem(self, value: object) -> str:
        """What ``value`` should be ('' if it is a value of this setting)."""
        if not isinstance(self.default, tuple):
            return self._problem(value, type(self.default))
        if not isinstance(value, (tuple, list)) or len(value) != len(self.default):
            return self.range
        return next(filter(None, (self._problem(v, type(self.default[0])) for v in value)), "")

    def _problem(self, v: object, kind: type) -> str:
        if kind is float:
            ok = isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)
        else:
            ok = type(v) is kind  # a bool is no int here, nor an int a bool
        if not ok:
            return _KINDS[kind] + (f", {self.range}" if self.range else "")
        if self.choices and v not in self.choices or self.lo is not None and not self.lo <= v <= self.hi:
            return self.range
        return ""

    def check(self, value: object) -> None:
        """Raise :class:`ConfigError` (``parameter 'name'=value: expected ...``) unless ``value`` fits."""
        why = self.problem(value)
        if why:
            raise ConfigError(f"parameter '{self.name}'={value!r}: expected {why}")

    def parse(self, text: str):
        """A command-line word as this setting's value (one number of a tuple); ValueError saying what
        is expected."""
        kind = type(self.default[0] if isinstance(self.default, tuple) else self.default)
        try:
            value = kind(text)
        except ValueError:
            raise ValueError(f"{text!r}: expected {_KINDS[kind]} (default {text_of(self.default)})") from None
        why = self._problem(value, kind)
        if why:
            raise ValueError(f"{text!r}: expected {why} (default {text_of(self.default)})")
        return value


#: Every setting of the node, in its declaration order.
SETTINGS: tuple[Setting, ...] = (
    Setting("input", INPUTS[0], "Frame source: serial (a board) or topic (~/raw_voltages_in, e.g. a bag played "
            "back)", choices=INPUTS),
    Setting("port", "/dev/cstomo", "Serial URL of the board: a device path (a udev symlink, config/99-cstomo.rules), "
            "socket://, rfc2217://, loop://; virtual://NAME: a simulated board made in this process (tests, "
            "benchmarks)"),
    Setting("baudrate", 921600, "Serial speed; ignored by USB CDC boards and pseudo-terminals", 1200, 16_000_000,
            "baud"),
    Setting("protocol", PROTOCOLS[0], "Wire protocol of the board: binary (COBS + CRC-32) or text (no checksum; "
            "docs/protocol.md)", choices=PROTOCOLS),
    Setting("rate_hz", 0.0, "Frame rate asked of a binary board in START; 0 = the board's default", 0.0, 10000.0,
            "frames/s"),
    Setting("sensor", DEFAULT_SENSOR, "Sensor preset (cuboid_joint, cylinder, disc) or a sensor YAML path"),
    Setting("cache_dir", "", "Model and tare cache directory; '' = $CSTOMO_CACHE_DIR, else "
            "$XDG_CACHE_HOME/cstomo_sensor (~/.cache/cstomo_sensor when XDG_CACHE_HOME is unset)"),
    Setting("estimator", ESTIMATORS[0], "Force estimator: model (the more accurate) or linear (the fastest)",
            choices=ESTIMATORS),
    Setting("mesh_size", 4.0e-3, "Forward-model mesh element size (smaller: slower build, finer model)",
            *MESH_SIZE_RANGE, "metres"),
    Setting("grid", (8, 8, 4), "Reconstruction voxel grid nx, ny, nz", 1, 64),
    Setting("iterations", 0, "Landweber iterations; 0 = chosen by the discrepancy rule", 0, 1_000_000_000),
    Setting("damping", 0.0, "Landweber damping, relative to s_max^2", 0.0, 1.0e6),
    Setting("max_force", 1.5 * RATED_FORCE, f"A frame implying a larger force, or a change no such load explains, is "
            f"implausible: not published, counted in the diagnostics (default: 1.5 x the rated {RATED_FORCE:g} N)",
            1.0, 100000.0, "N"),
    Setting("calibration_file", "", "Device calibration file written by `cstomo calibrate`; '' = the nominal model; "
            "a missing, damaged or other-model file makes configure fail with the reason"),
    Setting("tare_frames", 50, "Frames averaged by a tare (at start and by ~/tare)", 1, 100_000),
    Setting("tare_file", "", "Where the tare is saved and read back at start; '' = "
            "<cache_dir>/tare_[<namespace>-]<sensor>-<geometry digest>-<port>.csv"),
    Setting("tare_on_start", False, "true: tare on the first tare_frames frames at start (the joint must be "
            "unloaded: judged against the saved tare or the calibration's reference, if any); false: the saved "
            "tare of this device (tare_file), else a tare at start too (WARN); no force "
            "is published before a reference of this device exists"),
    Setting("frame_id", "cstomo_socket", "Frame of the wrench, the angles and the stress cloud: origin at the "
            "socket centre"),
    Setting("autostart", True, "Walk to active by itself; false leaves the node unconfigured for a lifecycle manager"),
    Setting("stress_field_every", 10, "Publish ~/stress_field (and ~/scene_stress_field) every N frames; 0 = off",
            0, 1_000_000),
    Setting("wrench_filter_hz", 20.0, "Cutoff (-3 dB) of the first-order low-pass of ~/wrench_filtered (delay "
            "1/(2 pi f): 8 ms at 20 Hz); 0 = off (no ~/wrench_filtered)", 0.0, 10000.0, "Hz"),
    Setting("drift_tracking", True, "Follow the device's slow uniform change after the tare (warming, drive drift) "
            "so the zero holds; the diagnostics show the tracked change"),
    Setting("creep_per_decade", TYPICAL_CREEP_PER_DECADE, "The rubber's creep per decade of time (rubbers: 0.02..0.06), "
            "compensated so a held load reads constant; a calibration's fitted value wins; "
            "0 = off (a calibration's too)", 0.0, MAX_CREEP),
    # above the 1-sigma of a 40 dB board's noise alone (about 1.9 N)
    Setting("max_sigma_n", 5.0, "A published force whose 1-sigma uncertainty (~/wrench_sigma, the rms of its "
            "error's norm) exceeds it is counted and said in /diagnostics (WARN); 0 = no check", 0.0, 100000.0, "N"),
    Setting("expected_wrench_sigma", 2.0, "The 1-sigma per axis of the load a controller expects on ~/expected_wrench "
            "(geometry_msgs/WrenchStamped): a measurement of the device's change under load, checked before it is "
            "used", 0.01, 1000.0, "N"),
    Setting("expected_wrench_tolerance", 0.5, "A ~/expected_wrench stamped further than this before or after the "
            "frames is refused; one within it is used for frames up to this long after its stamp", 0.001, 60.0,
            "seconds"),
    Setting("qos_depth", 10, "History depth of the publishers and of the ~/raw_voltages_in subscription", 1, 10_000),
    Setting("qos_reliability", RELIABILITIES[0], "Reliability of the publishers and the subscription (REP 2003: "
            "system_default is reliable)", choices=RELIABILITIES),
    Setting("stale_timeout", 0.5, "Without frames for this long the data is stale (force topics stop, the "
            "diagnostics say why); a frame older is dropped as late; may change at run time (ros2 param set)",
            0.01, 3600.0, "seconds", read_only=False),
    Setting("clock_window", 10.0, "Board time over which the board-to-host clock offset is the minimum",
            0.1, 3600.0, "seconds"),
)
SETTING: dict[str, Setting] = {s.name: s for s in SETTINGS}


def default(name: str):
    """The default of setting ``name``."""
    return SETTING[name].default


#: The largest socket force (N) a load script or a scene may ask of the simulated sensor: the node's
#: default ``max_force``, 1.5 x the rated range of docs/physics.md (the calibration's largest load);
#: beyond it the node publishes nothing and the simulation's small-strain mechanics means nothing either.
MAX_LOAD = default("max_force")


def check_value(name: str, value: object) -> None:
    """Raise :class:`ConfigError` ``name=value: expected ...`` unless ``value`` is one of setting ``name``'s."""
    why = SETTING[name].problem(value)
    if why:
        raise ConfigError.bad_value(name, value, why)


def check_config(config) -> None:
    """:func:`check_value` of every field of the config dataclass ``config`` that is a setting (a string
    without choices, e.g. a path, is taken as it comes)."""
    for f in fields(config):
        s = SETTING.get(f.name)
        if s is not None and (s.choices or not isinstance(s.default, str)):
            check_value(f.name, getattr(config, f.name))


def _number(x: float) -> str:
    return str(int(x)) if float(x).is_integer() else f"{x:g}"


def text_of(value: object) -> str:
    """A value as the parameter file and the docs write it."""
    if isinstance(value, bool):
        return str(value).lower()
    if isinstance(value, tuple):
        return "[" + ", ".join(map(str, value)) + "]"
    if isinstance(value, str):
        return value or '""'
    return repr(value)


def parameter_file() -> str:
    """``config/cstomo_sensor.yaml``: every setting at its default, commented."""
    out = ["# Parameters of cstomo_sensor_node (docs/node.md): every parameter the node declares, at its default.",
           "# Read-only ones take effect at start (configure): change them and restart the node.",
           "# Written by `python -m cstomo_sensor.settings yaml` from cstomo_sensor/settings.py.",
           "/**/cstomo_sensor:           # any namespace (launch namespace:=left_knee, ros2 run ... -r __ns:=/left_knee)",
           "  ros__parameters:"]
    for s in SETTINGS:
        head = f"    {s.name}: {text_of(s.default)} ".ljust(30)
        note = f"[{s.range}] " if s.range else ""
        lines = textwrap.wrap(note + s.description, 110 - 32, break_on_hyphens=False)
        out.append(f"{head}# {lines[0]}")
        out += [" " * 30 + f"# {line}" for line in lines[1:]]
    return "\n".join(out) + "\n"


def markdown_table() -> str:
    """The parameter table of docs/node.md."""
    out = ["| parameter | default | values | read-only | description |", "|---|---|---|---|---|"]
    for s in SETTINGS:
        desc = s.description.replace("|", "\\|")
        out.append(f"| `{s.name}` | `{text_of(s.default)}` | {s.range} | {'yes' if s.read_only else 'no'} | {desc} |")
    return "\n".join(out) + "\n"


if __name__ == "__main__":
    what = sys.argv[1:] or [""]
    if what[0] not in ("yaml", "markdown"):
        sys.exit("usage: python -m cstomo_sensor.settings yaml|markdown")
    sys.stdout.write(parameter_file() if what[0] == "yaml" else markdown_table())
