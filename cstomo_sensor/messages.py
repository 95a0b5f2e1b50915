"""What the node publishes, built in one place for the live node and for ``cstomo replay``.

Both :mod:`cstomo_sensor.node` and :mod:`cstomo_sensor.replay` feed frames of 208 volts through a
:class:`FrameProcessor` (tare, bad-channel mask, :class:`~cstomo_sensor.pipeline.Pipeline`) and turn
its results into messages with :class:`OutputMessages`; so the same frames give the same numbers
in the same message types, live or replayed. :class:`ClockMapper` maps the board's microsecond
clock onto host time for header stamps.

Tare semantics (the same everywhere): when a tare is pending (``tare_on_start`` in the node, or no
``--reference`` given to replay), the next ``tare_frames`` frames of the input are averaged into the
reference and give no output; every later frame is processed against that reference.

Imports the ROS message packages (``std_msgs``, ``geometry_msgs``, ``sensor_msgs``) but not rclpy's
node machinery, so replay works without a running ROS graph.
"""
from __future__ import annotations

import logging
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from builtin_interfaces.msg import Time
from geometry_msgs.msg import WrenchStamped
from sensor_msgs.msg import PointCloud2, PointField
from std_msgs.msg import Float32MultiArray, Float64, MultiArrayDimension

from .errors import ConfigError, FrameError
from .pattern import MeasurementPattern

log = logging.getLogger(__name__)

N_MEAS = 208
N_ELECTRODES = 16
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
    v = np.asarray(msg.data, dtype=np.float64)
    if v.shape != (N_MEAS,):
        raise FrameError(f"raw_voltages message holds {v.size} values, expected {N_MEAS}")
    if not np.isfinite(v).all():
        raise FrameError("raw_voltages message holds non-finite values")
    return v


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


@dataclass(frozen=True)
class Excluded:
    """Channels excluded from the reconstruction by the latest frame's status flags."""

    saturated: int = 0
    dead_electrodes: tuple[int, ...] = ()
    channels: int = 0


class FrameProcessor:
    """Tare, bad-channel mask and per-frame processing around a Pipeline (node and replay share it).

    Parameters
    ----------
    pipe : Pipeline
        The per-frame core (its reference is set here by a tare or by the caller).
    layers : int
        Electrode rings of the sensor (1 or 2), for the rows of a dead electrode.
    stress_field_every : int
        Attach the stress field to every N-th processed frame (the first one included); 0 never.
    on_tare : callable or None
        Called with the (208,) averaged reference when a tare completes (e.g. to save it).
    """

    def __init__(self, pipe: object, layers: int = 2, stress_field_every: int = 0,
                 on_tare: Callable[[np.ndarray], None] | None = None) -> None:
        if stress_field_every < 0:
            raise ConfigError(f"{stress_field_every=}: expected >= 0 (0 = off)")
        self.pipe = pipe
        self.stress_field_every = int(stress_field_every)
        self.on_tare = on_tare
        pattern = MeasurementPattern(N_ELECTRODES, layers)
        self._electrode_rows = np.stack([pattern.electrode_rows(e) for e in range(N_ELECTRODES)])
        self._mask = np.zeros(pipe.n_meas, bool)
        self._all_good = np.ones(N_ELECTRODES, bool)
        self.excluded = Excluded()
        self.processed = 0
        self._tare_sum = np.zeros(pipe.n_meas)
        self._tare_left = self._tare_n = 0

    # --- tare ------------------------------------------------------------------------------------

    def start_tare(self, n_frames: int) -> None:
        """Average the next ``n_frames`` frames into the reference (they give no output)."""
        if n_frames < 1:
            raise ConfigError(f"tare_frames={n_frames!r}: expected >= 1")
        self._tare_sum[:] = 0.0
        self._tare_left = self._tare_n = int(n_frames)

    @property
    def taring(self) -> bool:
        return self._tare_left > 0

    @property
    def ready(self) -> bool:
        """A reference is set and no tare is pending: frames give results."""
        return not self.taring and self.pipe.reference is not None

    # --- per frame -------------------------------------------------------------------------------

    def update_mask(self, saturated: np.ndarray | None, contact_ok: np.ndarray | None) -> bool:
        """Exclude saturated values and every row of a dead electrode; True if the mask changed
        (only then is ``pipe.set_bad_channels`` called)."""
        contact = self._all_good if contact_ok is None else np.asarray(contact_ok, bool)
        dead = ~contact
        mask = self._electrode_rows[dead].any(axis=0) if dead.any() else np.zeros_like(self._mask)
        if saturated is not None:
            mask |= np.asarray(saturated, bool)
        if np.array_equal(mask, self._mask):
            return False
        self._mask = mask
        self.pipe.set_bad_channels(mask.copy())
        self.excluded = Excluded(
            saturated=0 if saturated is None else int(np.count_nonzero(saturated)),
            dead_electrodes=tuple(int(e) for e in np.flatnonzero(dead)),
            channels=int(mask.sum()),
        )
        if mask.any():
            log.warning("excluding %d measurements (saturated: %d, dead electrodes: %s)",
                        self.excluded.channels, self.excluded.saturated, self.excluded.dead_electrodes)
        return True

    def process(self, values: np.ndarray, saturated: np.ndarray | None = None,
                contact_ok: np.ndarray | None = None) -> object | None:
        """The FrameResult of one frame, or None while the frame goes into a pending tare (or no
        reference exists yet)."""
        if self._tare_left:
            self._tare_sum += values
            self._tare_left -= 1
            if not self._tare_left:
                ref = self._tare_sum / self._tare_n
                self.pipe.set_reference(ref)
                log.info("tare: new reference from %d frames", self._tare_n)
                if self.on_tare is not None:
                    self.on_tare(ref)
            return None
        if self.pipe.reference is None:
            return None
        self.update_mask(saturated, contact_ok)
        every = self.stress_field_every
        with_field = every > 0 and self.processed % every == 0
        self.processed += 1
        return self.pipe.process(values, with_field=with_field)


class ClockMapper:
    """Maps a board's microsecond clock onto host time (nanoseconds) for header stamps.

    The offset is the minimum of ``host_time - board_time`` over a sliding window of the last
    ``window_s`` seconds of board time. Transport and scheduling only ever delay a frame, so the
    smallest observed offset is the one closest to the true one (the lower envelope); taking it
    over a sliding window (not since the start) lets the offset follow a board crystal that drifts
    against the host clock: with a drift of d (e.g. 1e-4) the stamps lag by at most about d *
    window_s. A stamp is never later than the host time at which its frame was handed over.
    When the board clock jumps backwards (board reset) the window restarts.

    Text-mode boards carry no clock: the node stamps their frames with host time on reception.

    Parameters
    ----------
    window_s : float
        Length of the sliding window in seconds of board time.
    """

    def __init__(self, window_s: float = 10.0) -> None:
        if not window_s > 0:
            raise ConfigError(f"{window_s=}: expected a positive number of seconds")
        self.window_us = int(window_s * 1e6)
        self._q: deque[tuple[int, int]] = deque()  # (board_us, offset_ns), offsets increasing
        self._last_board: int | None = None

    def reset(self) -> None:
        self._q.clear()
        self._last_board = None

    @property
    def offset_ns(self) -> int | None:
        """Current offset host - board in nanoseconds; None before the first frame."""
        return self._q[0][1] if self._q else None

    def stamp_ns(self, board_us: int, host_ns: int) -> int:
        """Host-time stamp (ns) of a frame measured at ``board_us`` and received at ``host_ns``."""
        if self._last_board is not None and board_us < self._last_board:
            self.reset()
        self._last_board = board_us
        off = int(host_ns) - int(board_us) * 1000
        q = self._q
        while q and q[-1][1] >= off:
            q.pop()
        q.append((board_us, off))
        while board_us - q[0][0] > self.window_us:
            q.popleft()
        return int(board_us) * 1000 + q[0][1]
