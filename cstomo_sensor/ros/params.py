"""The node's parameters: one table of descriptors, defaults taken from the config dataclasses
(:class:`NodeConfig` and :class:`~cstomo_sensor.force.pipeline.PipelineConfig`), and the frozen
:class:`NodeConfig` the node builds from them at configure. ``config/cstomo_sensor.yaml`` lists the
same parameters with the same defaults (a test holds them equal)."""
from __future__ import annotations

from dataclasses import dataclass, fields
from pathlib import Path

from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor
from rclpy.qos import QoSProfile, ReliabilityPolicy

from ..board.wire import PROTOCOLS
from ..cache import default_cache_dir
from ..errors import ConfigError
from ..force.creep import MAX_CREEP
from ..force.device import tare_file_name
from ..force.pipeline import PipelineConfig
from ..force.stream import StreamConfig
from ..model.geometry import SensorGeometry
from ..model.mesh import MESH_SIZE_RANGE

INPUTS = ("serial", "topic")
RELIABILITIES = ("system_default", "reliable", "best_effort")


def _d(description: str, *, read_only: bool = False, lo=None, hi=None, step=None) -> ParameterDescriptor:
    desc = ParameterDescriptor(description=description, read_only=read_only)
    if isinstance(lo, float) or isinstance(hi, float):
        desc.floating_point_range = [FloatingPointRange(from_value=float(lo), to_value=float(hi), step=0.0)]
    elif lo is not None:
        desc.integer_range = [IntegerRange(from_value=int(lo), to_value=int(hi), step=int(step or 1))]
    return desc


#: name -> descriptor, in declaration order; the defaults are the config dataclasses' own.
_DESCRIPTORS: dict[str, ParameterDescriptor] = {
    "input": _d("Frame source: 'serial' (a board) or 'topic' (~/raw_voltages_in)", read_only=True),
    "port": _d("Serial URL: device path, socket://, rfc2217://, loop://; "
               "virtual://NAME: a simulated board made in this process (tests, benchmarks)",
               read_only=True),
    "baudrate": _d("Serial speed (ignored by USB CDC and ptys)", read_only=True, lo=1200, hi=16_000_000),
    "protocol": _d("Wire protocol of the board: 'binary' or 'text' (docs/protocol.md)", read_only=True),
    "rate_hz": _d("Frame rate asked of a binary board in START; 0 = the board's default",
                        read_only=True, lo=0.0, hi=10000.0),
    "sensor": _d("Sensor preset name or YAML path", read_only=True),
    "cache_dir": _d("Model and tare cache directory; '' = $CSTOMO_CACHE_DIR or ~/.cache/cstomo_sensor",
                         read_only=True),
    "estimator": _d("Force estimator: 'model' (accurate) or 'linear' (fastest)", read_only=True),
    "mesh_size": _d("Forward mesh element size in metres", read_only=True, lo=MESH_SIZE_RANGE[0], hi=MESH_SIZE_RANGE[1]),
    "grid": _d("Reconstruction voxel grid (nx, ny, nz), each 1..64", read_only=True),
    "iterations": _d("Landweber iterations; 0 = discrepancy rule", read_only=True, lo=0, hi=1_000_000_000),
    "damping": _d("Landweber damping relative to s_max^2", read_only=True, lo=0.0, hi=1.0e6),
    "max_force": _d("Newtons; a frame implying a larger force, or a change no such load explains, is "
                    "implausible: not published, counted in diagnostics", read_only=True, lo=1.0, hi=100000.0),
    "calibration_file": _d("Device calibration file written by `cstomo calibrate`; '' = the nominal model. A "
                           "missing, damaged or other-model file makes configure fail with the reason", read_only=True),
    "tare_frames": _d("Frames averaged by a tare", read_only=True, lo=1, hi=100_000),
    "tare_file": _d("Where the tare is saved and read back at start; '' = "
                    "<cache_dir>/tare_<sensor>-<geometry digest>-<port>.csv",
                         read_only=True),
    "tare_on_start": _d("Tare on the first tare_frames frames at start (else the saved tare of this "
                        "device, else a tare at start too)", read_only=True),
    "frame_id": _d("frame_id of the wrench and the stress cloud (the wrench frame)",
                                     read_only=True),
    "autostart": _d("Walk to active by itself (no lifecycle manager needed)", read_only=True),
    "stress_field_every": _d("Publish ~/stress_field every N frames; 0 = off", read_only=True,
                                  lo=0, hi=1_000_000),
    "wrench_filter_hz": _d("Cutoff (-3 dB) in Hz of the first-order low-pass of ~/wrench_filtered; 0 = off "
                           "(no ~/wrench_filtered)", read_only=True, lo=0.0, hi=10000.0),
    "drift_tracking": _d("Follow the device's slow uniform change after the tare (warming, drive drift) so the "
                         "zero holds; diagnostics show the tracked change (force/drift.py)", read_only=True),
    "creep_per_decade": _d("The rubber's creep per decade of time (0.02..0.06), compensated so a held load reads "
                           "constant (force/creep.py); a calibration file's fitted value wins; 0 = off (a calibration's too)",
                           read_only=True, lo=0.0, hi=MAX_CREEP),
    "max_sigma_n": _d("Newtons: a published force whose 1-sigma uncertainty (the rms of its error's norm, "
                      "~/wrench_sigma) exceeds it is counted and said in the diagnostics (WARN); 0 = no check",
                      read_only=True, lo=0.0, hi=100000.0),
    "expected_wrench_sigma": _d("Newtons: the 1-sigma per axis of the load a controller expects on ~/expected_wrench "
                                "(geometry_msgs/WrenchStamped, its force used for 0.5 s after its stamp), a measurement "
                                "of the device's change under load (force/drift.py JointScale)", read_only=True,
                                lo=0.01, hi=1000.0),
    "qos_depth": _d("History depth of publishers and subscription", read_only=True, lo=1, hi=10_000),
    "qos_reliability": _d("'system_default', 'reliable' or 'best_effort' (REP 2003)",
                                             read_only=True),
    "stale_timeout": _d("Seconds without frames after which the data is stale (force topics stop, "
                        "diagnostics say why), and the age beyond which a frame is dropped as late; "
                        "may change at run time", lo=0.01, hi=3600.0),
    "clock_window": _d("Seconds of board time over which the board-to-host clock offset is "
                              "the minimum", read_only=True, lo=0.1, hi=3600.0),
}


def _choice(name: str, value: str, choices: tuple[str, ...]) -> None:
    if value not in choices:
        raise ConfigError(f"parameter '{name}'={value!r}: expected one of {list(choices)}")


@dataclass(frozen=True)
class NodeConfig:
    """Every setting of the node, built once from its parameters (validated here); with
    :class:`PipelineConfig`, the one source of the parameters' defaults and choices."""

    pipeline: PipelineConfig
    input: str = INPUTS[0]
    port: str = "/dev/cstomo"
    baudrate: int = 921600
    protocol: str = PROTOCOLS[0]
    rate_hz: float = 0.0
    tare_frames: int = StreamConfig.tare_frames
    tare_file: str = ""
    tare_on_start: bool = False
    frame_id: str = "cstomo_socket"
    autostart: bool = True
    stress_field_every: int = StreamConfig.stress_field_every
    wrench_filter_hz: float = StreamConfig.wrench_filter_hz
    drift_tracking: bool = StreamConfig.drift_tracking
    creep_per_decade: float = StreamConfig.creep_per_decade
    max_sigma_n: float = StreamConfig.max_sigma_n
    expected_wrench_sigma: float = 2.0
    qos_depth: int = 10
    qos_reliability: str = RELIABILITIES[0]
    stale_timeout: float = StreamConfig.stale_timeout
    clock_window: float = 10.0

    def __post_init__(self) -> None:
        _choice("input", self.input, INPUTS)
        _choice("protocol", self.protocol, PROTOCOLS)
        _choice("qos_reliability", self.qos_reliability, RELIABILITIES)
        if self.input == "serial" and not self.port:
            raise ConfigError("parameter 'port'='': expected a serial URL")
        if not self.frame_id:
            raise ConfigError("parameter 'frame_id'='': expected a frame name")
        for name in ("tare_frames", "qos_depth"):
            if getattr(self, name) < 1:
                raise ConfigError(f"parameter '{name}'={getattr(self, name)!r}: expected >= 1")
        if not self.wrench_filter_hz >= 0:
            raise ConfigError(f"parameter 'wrench_filter_hz'={self.wrench_filter_hz!r}: expected >= 0 Hz (0 = off)")
        for name in ("stale_timeout", "clock_window"):
            if not getattr(self, name) > 0:
                raise ConfigError(f"parameter '{name}'={getattr(self, name)!r}: expected > 0")

    @classmethod
    def from_parameters(cls, get) -> NodeConfig:
        """Build from ``get(name) -> value``; a bad value raises ConfigError naming the parameter."""
        try:
            pipe = PipelineConfig(**{n: get(n) for n in PipelineConfig.__dataclass_fields__})
        except ConfigError as err:
            if err.key is None:
                raise ConfigError(f"parameter {err}") from err
            raise ConfigError(f"parameter '{err.key}'={err.value!r}: expected {err.expected}") from err
        names = [n for n in cls.__dataclass_fields__ if n != "pipeline"]
        return cls(pipeline=pipe, **{n: get(n) for n in names})

    @property
    def stream(self) -> StreamConfig:
        """The frame stream's settings."""
        return StreamConfig(tare_frames=self.tare_frames, stress_field_every=self.stress_field_every,
                            wrench_filter_hz=self.wrench_filter_hz, stale_timeout=self.stale_timeout,
                            drift_tracking=self.drift_tracking, creep_per_decade=self.creep_per_decade,
                            max_sigma_n=self.max_sigma_n)

    @property
    def cache_path(self) -> Path:
        if self.pipeline.cache_dir:
            return Path(self.pipeline.cache_dir)

        return default_cache_dir()

    def tare_path_for(self, geometry: SensorGeometry, namespace: str = "") -> Path:
        """Where the tare of this device is saved (frames-file format) and read back at start:
        ``tare_file``, else ``<cache_dir>/tare_[<namespace>-]<name>-<digest>-<port>.csv``, keyed by the
        node's namespace, a digest of the whole geometry and the port (``topic`` for topic input): a
        tare belongs to one board on one sensor, so two sensors of one robot, two sensor files with
        the same name, or a simulated board and the real one, never share it."""
        if self.tare_file:
            return Path(self.tare_file)
        return self.cache_path / tare_file_name(geometry.name, geometry.digest(),
                                                self.port if self.input == "serial" else "topic", namespace)

    def qos(self) -> QoSProfile:
        rel = {"system_default": ReliabilityPolicy.SYSTEM_DEFAULT, "reliable": ReliabilityPolicy.RELIABLE,
               "best_effort": ReliabilityPolicy.BEST_EFFORT}[self.qos_reliability]
        return QoSProfile(depth=self.qos_depth, reliability=rel)


def _default(name: str) -> object:
    for cls in (PipelineConfig, NodeConfig):
        f = {f.name: f for f in fields(cls)}.get(name)
        if f is not None:
            return list(f.default) if isinstance(f.default, tuple) else f.default
    raise KeyError(name)


#: name -> (default, descriptor), in declaration order: every parameter of the node.
PARAMETERS: dict[str, tuple[object, ParameterDescriptor]] = {n: (_default(n), d) for n, d in _DESCRIPTORS.items()}
