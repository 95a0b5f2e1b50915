"""What the node publishes, built in one place for the live node and for ``cstomo replay``.

Both :mod:`cstomo_sensor.ros.node` and :mod:`cstomo_sensor.tools.replay` push frames of 208 volts
through a :class:`~cstomo_sensor.frame_path.stream.FrameStream` and turn what it emits into messages with
:class:`OutputMessages`; so the same frames give the same numbers in the same message types, live or
replayed.

Imports the ROS message packages (``std_msgs``, ``geometry_msgs``, ``sensor_msgs``) but not rclpy's
node machinery, so replay works without a running ROS graph.
"""
from __future__ import annotations

import struct

import numpy as np
from geometry_msgs.msg import Vector3Stamped, WrenchStamped
from rclpy.serialization import serialize_message
from sensor_msgs.msg import Image, PointCloud2, PointField
from std_msgs.msg import Float32MultiArray, Float64, MultiArrayDimension

from ..board.wire import N_VALUES as N_MEAS
from ..errors import ConfigError, FrameError
from ..frame_path.outputs import CLOUD, FLOAT64, OUTPUTS, RAW_TOPIC, TOPIC_TYPES, VECTOR, WRENCH  # noqa: F401 - TOPIC_TYPES
from ..frames_io import check_frame

#: The raw frames' type before they carried a stamp: still read by replay and calibrate (old bags).
LEGACY_RAW_TYPE = "std_msgs/msg/Float32MultiArray"
#: The raw frame as an image: one row of 208 float32 volts (little endian).
RAW_ENCODING = "32FC1"
#: PointCloud2 fields of ``~/stress_field`` (float32 each, in this order).
CLOUD_FIELDS = ("x", "y", "z", "conductivity_change", "volumetric_compression", "pressure")
# little-endian CDR pieces: header stamp (int32 sec, uint32 nanosec), a 3-vector, a float64
_STAMP, _VEC3, _F64 = struct.Struct("<iI"), struct.Struct("<3d"), struct.Struct("<d")


def raw_voltages_msg(values: np.ndarray, stamp_ns: int = 0, frame_id: str = "cstomo_socket") -> Image:
    """``~/raw_voltages``: the 208 volts of one frame as a stamped one-row image (``32FC1``, width 208),
    stamped with the time the frame was measured: a message every ROS tool records and plays, that
    keeps the board's time in a bag (a Float32MultiArray has no header). NaN marks a measurement
    the board flagged (:func:`frame_from_raw_msg`)."""
    msg = Image()
    msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(int(stamp_ns), 1_000_000_000)
    msg.header.frame_id = frame_id
    msg.height, msg.width = 1, N_MEAS
    msg.encoding = RAW_ENCODING
    msg.is_bigendian = 0
    msg.step = 4 * N_MEAS
    msg.data = np.asarray(values, dtype="<f4").tobytes()
    return msg


def legacy_raw_voltages_msg(values: np.ndarray) -> Float32MultiArray:
    """The raw frame as older versions published it (no stamp): one dimension labelled ``measurement``."""
    msg = Float32MultiArray()
    msg.layout.dim = [MultiArrayDimension(label="measurement", size=N_MEAS, stride=N_MEAS)]
    msg.data = np.asarray(values, dtype=np.float32)
    return msg


def _raw_values(msg: Image | Float32MultiArray) -> np.ndarray:
    if isinstance(msg, Float32MultiArray):
        return np.asarray(msg.data, dtype=np.float64)
    if msg.encoding != RAW_ENCODING or msg.height != 1 or msg.is_bigendian or len(msg.data) != 4 * msg.width:
        raise FrameError(f"raw_voltages image: encoding {msg.encoding!r}, {msg.height} x {msg.width}, "
                         f"{len(msg.data)} bytes; expected {RAW_ENCODING!r}, 1 x {N_MEAS}, little endian")
    return np.frombuffer(bytes(msg.data), dtype="<f4").astype(np.float64)


def frame_from_raw_msg(msg: Image | Float32MultiArray) -> tuple[np.ndarray, np.ndarray | None, int | None]:
    """(volts (208,), flagged (208,) bool or None, stamp ns or None) of a raw frame message: NaN marks
    a measurement the board flagged (saturated, or on an electrode whose contact failed), as the node
    records them; the stamp is the image's header stamp (None for a legacy Float32MultiArray, or a
    zero stamp). :class:`FrameError` if malformed (wrong length or encoding, infinite values)."""
    v = _raw_values(msg)
    stamp = None
    if isinstance(msg, Image):
        stamp = msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec or None
    flagged = np.isnan(v)
    if not flagged.any() or v.shape != (N_MEAS,):
        return check_frame(v, N_MEAS, "raw_voltages message"), None, stamp
    return check_frame(v, N_MEAS, "raw_voltages message", used=~flagged), flagged, stamp


class OutputMessages:
    """Builds the output messages of one processed frame (wrench, angles, stress cloud) as CDR bytes.

    Parameters
    ----------
    centers : (n_cells, 3) ndarray
        Cell centres in the wrench frame (metres), the points of the stress cloud.
    frame_id : str
        ``header.frame_id`` of the wrench and the cloud (the wrench frame, docs/physics.md#coordinate-frames).

    Notes
    -----
    Every message is serialised here, not by rclpy: rclpy's own serialisation of each message
    once at construction gives a template (``serialize_message`` of the constant fields), and per
    frame only the stamp and the values are written into a copy of it at their CDR offsets (the
    stamp right after the 4-byte encapsulation header; the force, the float64 and the variable
    arrays at the fixed end of their message). ``Publisher.publish(bytes)`` and a bag writer take
    these bytes as they are; ``test_messages.py`` holds every one equal to rclpy's serialisation.

    The torque of the wrench is zero by construction: every traction on the socket is normal to
    its sphere, so the moment about the socket centre (the wrench frame's origin) vanishes.
    """

    def __init__(self, centers: np.ndarray, frame_id: str) -> None:
        c = np.asarray(centers, dtype=np.float32)
        if c.ndim != 2 or c.shape[1] != 3:
            raise ConfigError(f"centers.shape={c.shape}: expected (n_cells, 3)")
        self.frame_id = frame_id
        self._cloud = np.zeros((len(c), len(CLOUD_FIELDS)), np.float32)
        self._cloud[:, :3] = c
        w = WrenchStamped()
        w.header.frame_id = frame_id
        self._wrench = bytearray(serialize_message(w))
        self._wrench_at = len(self._wrench) - 48  # force (3 float64), then torque (3 float64, zero)
        v = Vector3Stamped()
        v.header.frame_id = frame_id
        self._vector = bytearray(serialize_message(v))
        self._vector_at = len(self._vector) - 24  # the vector (3 float64)
        cloud = self._cloud_msg()
        self._cloud_tpl = bytearray(serialize_message(cloud))
        self._cloud_at = len(self._cloud_tpl) - 1 - self._cloud.nbytes  # data, then is_dense (1 byte)
        self._float64 = bytearray(serialize_message(Float64()))
        self._encode = {WRENCH: self.wrench, VECTOR: self.vector, FLOAT64: lambda v, _s: self.float64(v),
                        CLOUD: self.stress_field}

    def _cloud_msg(self) -> PointCloud2:
        buf = self._cloud
        msg = PointCloud2()
        msg.header.frame_id = self.frame_id
        msg.height, msg.width = 1, len(buf)
        msg.fields = [PointField(name=n, offset=4 * i, datatype=PointField.FLOAT32, count=1)
                      for i, n in enumerate(CLOUD_FIELDS)]
        msg.is_bigendian = False
        msg.point_step = 4 * len(CLOUD_FIELDS)
        msg.row_step = msg.point_step * len(buf)
        msg.data = buf.tobytes()
        msg.is_dense = True
        return msg

    def wrench(self, force, stamp_ns: int) -> bytes:
        """``WrenchStamped`` (CDR) of ``force`` (3,) N at ``stamp_ns``; zero torque."""
        buf = self._wrench
        _STAMP.pack_into(buf, 4, *divmod(int(stamp_ns), 1_000_000_000))
        _VEC3.pack_into(buf, self._wrench_at, float(force[0]), float(force[1]), float(force[2]))
        return bytes(buf)

    def vector(self, v, stamp_ns: int) -> bytes:
        """``Vector3Stamped`` (CDR) of ``v`` (3,) at ``stamp_ns`` (the wrench's sigma)."""
        buf = self._vector
        _STAMP.pack_into(buf, 4, *divmod(int(stamp_ns), 1_000_000_000))
        _VEC3.pack_into(buf, self._vector_at, float(v[0]), float(v[1]), float(v[2]))
        return bytes(buf)

    def float64(self, value: float) -> bytes:
        """``std_msgs/Float64`` (CDR)."""
        buf = self._float64
        _F64.pack_into(buf, 4, float(value))
        return bytes(buf)

    def stress_field(self, field: object, stamp_ns: int) -> bytes:
        """A PointCloud2 (CDR) of every cell: x, y, z, conductivity_change, volumetric_compression, pressure."""
        buf = self._cloud
        buf[:, 3] = field.conductivity_change
        buf[:, 4] = field.volumetric_compression
        buf[:, 5] = field.pressure
        tpl = self._cloud_tpl
        _STAMP.pack_into(tpl, 4, *divmod(int(stamp_ns), 1_000_000_000))
        tpl[self._cloud_at:self._cloud_at + buf.nbytes] = buf.tobytes()
        return bytes(tpl)

    def build(self, result: object, stamp_ns: int, filtered=None, names=None) -> dict[str, bytes]:
        """CDR messages of one :class:`~cstomo_sensor.frame_path.pipeline.FrameResult` at ``stamp_ns``, keyed
        by topic name (relative to the node), of the outputs ``names`` (default: every output of
        :data:`~cstomo_sensor.frame_path.outputs.OUTPUTS`, in its order) whose value this frame has
        (:class:`~cstomo_sensor.frame_path.outputs.Output`: ``wrench_sigma`` when the result has its uncertainty,
        under the wrench's stamp; ``wrench_filtered`` when the filtered force ``filtered`` (3,) is given;
        ``consistency`` when the result has the statistic; the stress fields when it carries them)."""
        out = {}
        for name, value, encode in self.encoders(OUTPUTS if names is None else names):
            v = value(result, filtered)
            if v is not None:
                out[name] = encode(v, stamp_ns)
        return out

    def encoders(self, names) -> tuple[tuple[str, object, object], ...]:
        """(name, ``value(result, filtered)``, ``encode(value, stamp_ns)``) of each output of ``names``:
        what :meth:`build` does per output, for a caller that looks them up once, not per frame (the
        node's publishers)."""
        return tuple((name, OUTPUTS[name].value, self._encode[OUTPUTS[name].type]) for name in names)


class RawVoltagesCdr:
    """``~/raw_voltages`` as CDR bytes (the same message as :func:`raw_voltages_msg`), from a template
    of rclpy's serialisation: per frame the stamp (right after the 4-byte encapsulation header) and
    the 208 float32 values (the message's last bytes) are written into it."""

    def __init__(self, frame_id: str = "cstomo_socket") -> None:
        self._tpl = bytearray(serialize_message(raw_voltages_msg(np.zeros(N_MEAS), 0, frame_id)))
        self._at = len(self._tpl) - 4 * N_MEAS
        self._view = np.frombuffer(self._tpl, dtype="<f4", count=N_MEAS, offset=self._at)

    def __call__(self, values: np.ndarray, stamp_ns: int = 0, flagged: np.ndarray | None = None) -> bytes:
        """The message of ``values`` (208,) volts at ``stamp_ns``, NaN where ``flagged``."""
        _STAMP.pack_into(self._tpl, 4, *divmod(int(stamp_ns), 1_000_000_000))
        self._view[:] = values
        if flagged is not None:
            self._view[flagged] = np.nan
        return bytes(self._tpl)
