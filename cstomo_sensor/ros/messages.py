"""What the node publishes, built in one place for the live node and for ``cstomo replay``.

Both :mod:`cstomo_sensor.ros.node` and :mod:`cstomo_sensor.tools.replay` feed frames of 208 volts
through a :class:`~cstomo_sensor.force.pipeline.FrameProcessor` (tare, bad-channel mask, pipeline)
and turn its results into messages with :class:`OutputMessages`; so the same frames give the same
numbers in the same message types, live or replayed.

Imports the ROS message packages (``std_msgs``, ``geometry_msgs``, ``sensor_msgs``) but not rclpy's
node machinery, so replay works without a running ROS graph.
"""
from __future__ import annotations

import numpy as np
from builtin_interfaces.msg import Time
from geometry_msgs.msg import WrenchStamped
from sensor_msgs.msg import PointCloud2, PointField
from std_msgs.msg import Float32MultiArray, Float64, MultiArrayDimension

from ..board.wire import N_VALUES as N_MEAS
from ..errors import ConfigError
from ..frames_io import check_frame

#: Output topics relative to the node (``~/<name>``), in the order :meth:`OutputMessages.build` fills.
FORCE_TOPICS = ("wrench", "force_magnitude", "force_elevation", "force_azimuth")
STRESS_TOPIC = "stress_field"
RAW_TOPIC = "raw_voltages"
#: Message type of every output topic, as rosbag2 names it.
TOPIC_TYPES = {
    "wrench": "geometry_msgs/msg/WrenchStamped",
    "force_magnitude": "std_msgs/msg/Float64",
    "force_elevation": "std_msgs/msg/Float64",
    "force_azimuth": "std_msgs/msg/Float64",
    "stress_field": "sensor_msgs/msg/PointCloud2",
    "raw_voltages": "std_msgs/msg/Float32MultiArray",
}
#: PointCloud2 fields of ``~/stress_field`` (float32 each, in this order).
CLOUD_FIELDS = ("x", "y", "z", "conductivity_change", "volumetric_compression", "pressure")


def stamp(ns: int) -> Time:
    """A ``builtin_interfaces/Time`` from integer nanoseconds."""
    sec, nsec = divmod(int(ns), 1_000_000_000)
    return Time(sec=sec, nanosec=nsec)


def raw_voltages_msg(values: np.ndarray) -> Float32MultiArray:
    """``~/raw_voltages``: the 208 volts as float32, one dimension labelled ``measurement``."""
    msg = Float32MultiArray()
    msg.layout.dim = [MultiArrayDimension(label="measurement", size=N_MEAS, stride=N_MEAS)]
    msg.data = np.asarray(values, dtype=np.float32)
    return msg


def values_from_raw_msg(msg: Float32MultiArray) -> np.ndarray:
    """The (208,) float64 volts of a ``raw_voltages`` message; :class:`FrameError` if malformed."""
    return check_frame(np.asarray(msg.data, dtype=np.float64), N_MEAS, "raw_voltages message")


class OutputMessages:
    """Builds the output messages of one processed frame (wrench, angles, stress cloud).

    Parameters
    ----------
    centers : (n_cells, 3) ndarray
        Cell centres in the wrench frame (metres), the points of the stress cloud.
    frame_id : str
        ``header.frame_id`` of the wrench and the cloud (the wrench frame, REFERENCE_SENSOR.md 1).

    Notes
    -----
    The torque of the wrench is zero by construction: every traction on the socket is normal to
    its sphere, so the moment about the socket centre (the wrench frame's origin) vanishes.
    The cloud's float32 buffer is allocated once; each cloud copies three columns into it.
    """

    def __init__(self, centers: np.ndarray, frame_id: str) -> None:
        c = np.asarray(centers, dtype=np.float32)
        if c.ndim != 2 or c.shape[1] != 3:
            raise ConfigError(f"centers.shape={c.shape}: expected (n_cells, 3)")
        self.frame_id = frame_id
        self._cloud = np.zeros((len(c), len(CLOUD_FIELDS)), np.float32)
        self._cloud[:, :3] = c
        self._fields = [
            PointField(name=n, offset=4 * i, datatype=PointField.FLOAT32, count=1) for i, n in enumerate(CLOUD_FIELDS)
        ]

    def wrench(self, force: np.ndarray, stamp_ns: int) -> WrenchStamped:
        msg = WrenchStamped()
        msg.header.stamp = stamp(stamp_ns)
        msg.header.frame_id = self.frame_id
        fx, fy, fz = (float(v) for v in force)
        msg.wrench.force.x, msg.wrench.force.y, msg.wrench.force.z = fx, fy, fz
        return msg

    def stress_field(self, field: object, stamp_ns: int) -> PointCloud2:
        """A PointCloud2 of every cell: x, y, z, conductivity_change, volumetric_compression, pressure."""
        buf = self._cloud
        buf[:, 3] = field.conductivity_change
        buf[:, 4] = field.volumetric_compression
        buf[:, 5] = field.pressure
        msg = PointCloud2()
        msg.header.stamp = stamp(stamp_ns)
        msg.header.frame_id = self.frame_id
        msg.height, msg.width = 1, len(buf)
        msg.fields = self._fields
        msg.is_bigendian = False
        msg.point_step = 4 * len(CLOUD_FIELDS)
        msg.row_step = msg.point_step * len(buf)
        msg.data = buf.tobytes()
        msg.is_dense = True
        return msg

    def build(self, result: object, stamp_ns: int) -> dict[str, object]:
        """Messages of one :class:`~cstomo_sensor.pipeline.FrameResult`, keyed by topic name
        (relative to the node); ``stress_field`` only when the result carries a field."""
        out = {
            "wrench": self.wrench(result.force, stamp_ns),
            "force_magnitude": Float64(data=float(result.magnitude)),
            "force_elevation": Float64(data=float(result.elevation)),
            "force_azimuth": Float64(data=float(result.azimuth)),
        }
        if getattr(result, "field", None) is not None:
            out[STRESS_TOPIC] = self.stress_field(result.field, stamp_ns)
        return out
