"""The node's parameters: ROS descriptors made from the one declaration of every setting
(:data:`~cstomo_sensor.settings.SETTINGS`: default, range, choices, description), and the frozen
:class:`NodeConfig` the node builds from them at configure."""
from __future__ import annotations

from dataclasses import dataclass, field, fields
from pathlib import Path

from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor
from rclpy.qos import QoSProfile, ReliabilityPolicy

from ..cache import default_cache_dir
from ..errors import ConfigError
from ..force.reference.files import tare_file_name
from ..frame_path.config import PipelineConfig, StreamConfig
from ..model.geometry import SensorGeometry
from ..settings import SETTING, SETTINGS, Setting, default


def descriptor(s: Setting) -> ParameterDescriptor:
    """The ROS descriptor of a setting: its description, read-only flag, range (of a number) and choices."""
    desc = ParameterDescriptor(description=s.description, read_only=s.read_only,
                               additional_constraints=s.range if s.choices else "")
    if isinstance(s.default, float) and s.lo is not None:
        desc.floating_point_range = [FloatingPointRange(from_value=float(s.lo), to_value=float(s.hi), step=0.0)]
    elif isinstance(s.default, int) and not isinstance(s.default, bool) and s.lo is not None:
        desc.integer_range = [IntegerRange(from_value=int(s.lo), to_value=int(s.hi), step=1)]
    return desc


@dataclass(frozen=True)
class NodeConfig:
    """Every setting of the node, built once from its parameters and validated (ranges and choices:
    :data:`~cstomo_sensor.settings.SETTINGS`): those of the per-frame path in :attr:`pipeline`, those
    of the frame stream in :attr:`stream` (each config checks its own), the node's own here."""

    pipeline: PipelineConfig
    stream: StreamConfig = field(default_factory=StreamConfig)
    input: str = default("input")
    port: str = default("port")
    baudrate: int = default("baudrate")
    protocol: str = default("protocol")
    rate_hz: float = default("rate_hz")
    tare_file: str = default("tare_file")
    tare_on_start: bool = default("tare_on_start")
    autostart: bool = default("autostart")
    expected_wrench_sigma: float = default("expected_wrench_sigma")
    qos_depth: int = default("qos_depth")
    qos_reliability: str = default("qos_reliability")
    clock_window: float = default("clock_window")

    def __post_init__(self) -> None:
        for f in fields(self):
            if f.name in SETTING:
                SETTING[f.name].check(getattr(self, f.name))
        if self.input == "serial" and not self.port:
            raise ConfigError("parameter 'port'='': expected a serial URL")
        if not self.stream.frame_id:
            raise ConfigError("parameter 'frame_id'='': expected a frame name")

    @classmethod
    def from_parameters(cls, get) -> NodeConfig:
        """Build from ``get(name) -> value``; a bad value raises ConfigError naming the parameter."""
        def build(kind):
            try:
                return kind(**{f.name: get(f.name) for f in fields(kind) if f.name in SETTING})
            except ConfigError as err:
                if err.key is None:
                    raise ConfigError(f"parameter {err}") from err
                raise ConfigError(f"parameter '{err.key}'={err.value!r}: expected {err.expected}") from err

        pipe, stream = build(PipelineConfig), build(StreamConfig)
        names = [n for n in cls.__dataclass_fields__ if n not in ("pipeline", "stream")]
        return cls(pipeline=pipe, stream=stream, **{n: get(n) for n in names})

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


#: name -> (default, descriptor), in declaration order: every parameter of the node.
PARAMETERS: dict[str, tuple[object, ParameterDescriptor]] = {
    s.name: (list(s.default) if isinstance(s.default, tuple) else s.default, descriptor(s)) for s in SETTINGS}
