"""Frame sources of ROS messages (:mod:`cstomo_sensor.frame_path.sources` for the base): a topic of raw frames
and a rosbag2 recording of one. Each frame is stamped with its message's header stamp (the time it
was measured, as the serial node stamps it), else the time it arrived (a topic: the node's clock on
reception; a bag: its receive time); NaN in a message marks a measurement the board flagged.
"""
from __future__ import annotations

from collections import deque
from collections.abc import Callable
from pathlib import Path

from rclpy.serialization import deserialize_message
from sensor_msgs.msg import Image
from std_msgs.msg import Float32MultiArray

from ..errors import ConfigError, FrameError
from ..frame_path.sources import FrameSource, StampedFrame
from .messages import RAW_TOPIC, TOPIC_TYPES, frame_from_raw_msg


class TopicSource(FrameSource):
    """Raw frames (sensor_msgs/Image 32FC1, as ``~/raw_voltages``) from the topic ``topic`` of ``node``.

    The subscription's callback (the executor's thread) turns each message into a frame and hands it
    to :attr:`handler` when one is set (the node: processed there, no hand-over), else keeps it for
    :meth:`recv` (at most ``keep`` frames, the oldest dropped). A message that is no frame goes to
    ``on_corrupt``.
    """

    def __init__(self, node, topic: str, qos, keep: int = 64) -> None:
        self._node = node
        self._clock = node.get_clock()
        self._kept: deque[StampedFrame] = deque(maxlen=keep)
        self.handler: Callable[[StampedFrame], None] | None = None
        self.frames = 0
        self.subscription = node.create_subscription(Image, topic, self._on_msg, qos)

    def _on_msg(self, msg: Image) -> None:
        host_ns = self._clock.now().nanoseconds
        try:
            values, flagged, stamp_ns = frame_from_raw_msg(msg)
        except FrameError as err:
            self._corrupt(err)
            return
        self.frames += 1
        stamp = stamp_ns or host_ns
        frame = StampedFrame(values, stamp, 0, flagged, None, stamp)
        if self.handler is not None:
            self.handler(frame)
        else:
            self._kept.append(frame)

    def recv(self, timeout: float | None = None) -> StampedFrame | None:
        return self._kept.popleft() if self._kept else None  # the executor spins the subscription

    def stats(self) -> dict:
        return {"frames": self.frames, "publishers": self._node.count_publishers(self.subscription.topic_name)}

    def close(self) -> None:
        if self.subscription is not None:
            self._node.destroy_subscription(self.subscription)
            self.subscription = None


def find_raw_topic(connections, topic: str | None = None) -> str:
    """The input topic of a bag: ``topic`` if given, else the one topic whose name ends in
    ``raw_voltages``; its messages must be of the raw voltages' type (or the legacy one)."""
    from .messages import LEGACY_RAW_TYPE

    names = sorted({c.topic for c in connections})
    if topic is not None:
        if topic not in names:
            raise ConfigError(f"topic={topic!r}: not in the bag; it holds {names}")
    else:
        raw = [n for n in names if n.rstrip("/").endswith(RAW_TOPIC)]
        if len(raw) != 1:
            raise ConfigError(f"bag topics {names}: expected exactly one ending in '{RAW_TOPIC}' (or name it with --topic)")
        topic = raw[0]
    types = sorted({c.msgtype for c in connections if c.topic == topic})
    if len(types) != 1 or types[0] not in (TOPIC_TYPES[RAW_TOPIC], LEGACY_RAW_TYPE):
        raise ConfigError(f"topic {topic}: message type {', '.join(types)}, expected {TOPIC_TYPES[RAW_TOPIC]} "
                          f"(or {LEGACY_RAW_TYPE} of older recordings)")
    return topic


def bag_path(path: str | Path) -> Path:
    """``path`` as a rosbag2 recording to read; :class:`ConfigError` when there is none (rosbags' own
    words, 'File 'x' does not exist.', say neither what it is nor what was expected)."""
    p = Path(path)
    what = ("not found" if not p.exists() else "a directory without metadata.yaml" if p.is_dir()
            and not (p / "metadata.yaml").is_file() else "")
    if what:
        raise ConfigError(f"bag {path}: {what}; expected a rosbag2 directory (metadata.yaml and its .db3 or "
                          ".mcap files, as `ros2 bag record` writes)")
    return p


class BagSource(FrameSource):
    """The raw frames of a rosbag2 recording (sqlite3 or mcap; the ``rosbags`` library): the topic
    ``topic``, else the one ending in ``raw_voltages`` (:func:`find_raw_topic`). A frame's
    :attr:`~cstomo_sensor.frame_path.sources.StampedFrame.t_ns` is its receive time in the bag."""

    def __init__(self, path: str | Path, topic: str | None = None) -> None:
        from rosbags.rosbag2 import Reader  # optional: the [full] extra

        self.path = bag_path(path)
        self._reader = Reader(self.path)
        self._reader.open()
        self.topic = find_raw_topic(self._reader.connections, topic)
        inputs = [c for c in self._reader.connections if c.topic == self.topic]
        self._cls = Image if inputs[0].msgtype == TOPIC_TYPES[RAW_TOPIC] else Float32MultiArray
        self._messages = self._reader.messages(connections=inputs)
        self.messages = 0
        self._peeked: StampedFrame | None = None

    def peek(self) -> StampedFrame | None:
        """The next frame (None: none left), kept for :meth:`recv` (replay's restart: the first frame's stamp)."""
        if self._peeked is None and not self.exhausted:
            self._peeked = self._next()
        return self._peeked

    def recv(self, timeout: float | None = None) -> StampedFrame | None:
        frame, self._peeked = self._peeked, None
        return frame if frame is not None else None if self.exhausted else self._next()

    def _next(self) -> StampedFrame | None:
        from rclpy._rclpy_pybind11 import RMWError

        for _conn, t_ns, raw in self._messages:
            self.messages += 1
            try:
                values, flagged, stamp_ns = frame_from_raw_msg(deserialize_message(bytes(raw), self._cls))
            except (RMWError, FrameError) as err:  # not a frame: dropped and counted, as the node does
                self._corrupt(FrameError(f"frame {self.messages - 1} at {t_ns} ns: {str(err).split(',')[0]}"))
                continue
            return StampedFrame(values, stamp_ns or t_ns, 0, flagged, None, t_ns)
        self.exhausted = True
        self.close()
        return None

    def stats(self) -> dict:
        return {"frames": self.messages}

    def close(self) -> None:
        if self._reader is not None:
            self._reader.close()
            self._reader = None
