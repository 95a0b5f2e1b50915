"""The output set of a sensor, in one place: every output's name, message type, description and the
value it carries, and which of them a configuration produces. No ROS imports.

The node publishes each output as ``~/<name>`` (:mod:`cstomo_sensor.ros.node`), ``cstomo replay`` writes each as a
topic, ``cstomo_sensor_node --help`` lists them (:func:`help_lines`); the messages are encoded by type
in :mod:`cstomo_sensor.ros.messages` (:class:`~cstomo_sensor.ros.messages.OutputMessages`), from the value :attr:`Output.value`
takes out of a processed frame (:class:`FrameOutput`: what the frame stream emits). An output whose
value is None for a frame (no sigma, a NaN consistency, no field on this frame) is not built for it.
"""
from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

#: The raw frames' topic (the serial node's input as measured) and its type (rosbag2's spelling).
RAW_TOPIC = "raw_voltages"
RAW_TYPE = "sensor_msgs/msg/Image"

WRENCH, VECTOR, FLOAT64, CLOUD = ("geometry_msgs/msg/WrenchStamped", "geometry_msgs/msg/Vector3Stamped",
                                  "std_msgs/msg/Float64", "sensor_msgs/msg/PointCloud2")


@dataclass
class FrameOutput:
    """What the frame stream emits for one processed frame (:meth:`~.stream.FrameStream.push`):
    the result, the filtered force (None without the filter) and the frame's stamp (ns)."""

    result: Any  # a FrameResult (frame_path/pipeline.py): not imported, force/ imports this module
    filtered: tuple[float, float, float] | None
    stamp_ns: int


def _consistency(r, _f):
    c = getattr(r, "consistency", None)
    return None if c is None else c if c == c else None  # NaN: not computed, not published


@dataclass(frozen=True)
class Output:
    """One output: its message type (rosbag2's spelling), what it holds (the node's ``--help``), the
    value of a processed frame ``value(result, filtered)`` (None: not built for this frame), and
    ``heavy``: built only on the frames that carry the fields (``stress_field_every``)."""

    type: str
    description: str
    value: Callable
    heavy: bool = False


#: Every output a stream can produce, in publishing order.
OUTPUTS: dict[str, Output] = {
    "wrench": Output(WRENCH, "geometry_msgs/WrenchStamped: the force on the socket (N) in frame_id, zero torque",
                     lambda r, f: r.force),
    "wrench_sigma": Output(VECTOR, "geometry_msgs/Vector3Stamped: the 1-sigma uncertainty (N) of the wrench's fx, "
                           "fy, fz, under the wrench's stamp and frame_id "
                           "(force/slow_states/sigma.py)", lambda r, f: getattr(r, "sigma", None)),
    "wrench_filtered": Output(WRENCH, "the wrench through a first-order low-pass (wrench_filter_hz; none when 0)",
                              lambda r, f: f),
    "force_magnitude": Output(FLOAT64, "std_msgs/Float64: |F| (N)", lambda r, f: r.magnitude),
    "force_elevation": Output(FLOAT64, "std_msgs/Float64: the force's elevation (rad)", lambda r, f: r.elevation),
    "force_azimuth": Output(FLOAT64, "std_msgs/Float64: the force's azimuth (rad)", lambda r, f: r.azimuth),
    "consistency": Output(FLOAT64, "std_msgs/Float64: how well the frame fits a load on the socket (above its "
                          "limit: a foreign load)", _consistency),
    "stress_field": Output(CLOUD, "sensor_msgs/PointCloud2: the EIT image (conductivity change, compression, "
                           "pressure) every stress_field_every frames (none when 0)", lambda r, f: getattr(r, "field", None), True),
    "scene_stress_field": Output(CLOUD, "sensor_msgs/PointCloud2: the mechanics' field of the estimated force, "
                                 "with stress_field (socket sensors)", lambda r, f: getattr(r, "scene_field", None), True),
}

#: Message type of every topic, as rosbag2 names it: the outputs and the raw frames.
TOPIC_TYPES: dict[str, str] = {**{n: o.type for n, o in OUTPUTS.items()}, RAW_TOPIC: RAW_TYPE}


def output_set(config, scene_field: bool) -> tuple[str, ...]:
    """The outputs a stream with ``config`` (a :class:`~.stream.StreamConfig`) produces (a subset
    of :data:`OUTPUTS`, in its order); ``scene_field``: the pipeline has the mechanics' field (a socket
    sensor)."""
    off = set()
    if not config.wrench_filter_hz:
        off.add("wrench_filtered")
    if not config.stress_field_every:
        off |= {"stress_field", "scene_stress_field"}
    if not scene_field:
        off.add("scene_stress_field")
    return tuple(n for n in OUTPUTS if n not in off)


def help_lines() -> list[str]:
    """The node's ``--help`` lines of its outputs and its raw frames."""
    return [f"  ~/{name:<19} {o.description}" for name, o in OUTPUTS.items()] + [
        f"  ~/{RAW_TOPIC:<19} sensor_msgs/Image (32FC1, 1 x 208): the board's volts, stamped when measured "
        "(serial input; NaN where the board flagged a measurement), for ros2 bag record"]
