"""Sinks of the frame loop (:mod:`cstomo_sensor.frame_path.loop`) that speak ROS: the node's publishers and a
rosbag2 writer. Both build the messages of :class:`~.messages.OutputMessages` (CDR bytes, the same
for both), the publishers only those of the topics someone subscribes to.
"""
from __future__ import annotations

import importlib
from collections.abc import Callable

from rclpy.event_handler import PublisherEventCallbacks

from ..frame_path.mask import ChannelMask
from ..frame_path.outputs import OUTPUTS, RAW_TOPIC, TOPIC_TYPES
from .messages import OutputMessages, RawVoltagesCdr


def msg_class(type_name: str):
    """The message class of a rosbag2 type name (``geometry_msgs/msg/WrenchStamped``)."""
    pkg, _, name = type_name.split("/")
    return getattr(importlib.import_module(f"{pkg}.msg"), name)


def _publish(pub, data: bytes) -> None:
    """``pub.publish(data)`` of a lifecycle publisher and CDR bytes, without the Python layers between
    (its enabled check, as it makes it, without the warning; the type tests; ~20 us per frame)."""
    if pub.is_activated:
        handle = pub.handle
        with handle:
            handle.publish_raw(data)


class _Topic:
    """One output topic's per-frame plan (:meth:`Publishers._update`): its publisher, how its value is
    taken from a frame's result and encoded (:meth:`~.messages.OutputMessages.encoders`)."""

    __slots__ = ("name", "pub", "value", "encode")

    def __init__(self, name: str, pub, value, encode) -> None:
        self.name, self.pub, self.value, self.encode = name, pub, value, encode


class Publishers:
    """The node's publishers of ``topics`` (outputs, and :data:`RAW_TOPIC` for the raw frames as
    measured), as a sink: a frame's messages are built and published while ``active()``, for the
    topics with a subscriber only. Who subscribes is followed by the publishers' matched events (the
    executor's thread) and :meth:`refresh` (the node's diagnostics timer), never asked per frame.
    ``published``: messages per topic since they were made (the diagnostics' ``messages_published``).

    ``geometry``: the sensor's (a raw frame's flagged measurements, NaN in its message: its own
    :class:`~cstomo_sensor.frame_path.mask.ChannelMask`); ``on_fields(wanted)`` is told whether someone subscribes to
    a field's topic (:attr:`fields_wanted`: the stream computes the fields only then,
    :meth:`~cstomo_sensor.frame_path.stream.FrameStream.want_fields`).
    """

    def __init__(self, node, topics: tuple[str, ...], centers, frame_id: str, qos, geometry,
                 active: Callable[[], bool], on_fields: Callable[[bool], None] | None = None) -> None:
        self.node, self.active, self.on_fields = node, active, on_fields
        self.flags = ChannelMask(geometry)
        self.out = OutputMessages(centers, frame_id)
        self.raw = RawVoltagesCdr(frame_id)
        self.pubs = {}
        for t in topics:
            events = PublisherEventCallbacks(matched=lambda info, t=t: self._matched(t, info.current_count))
            self.pubs[t] = node.create_lifecycle_publisher(msg_class(TOPIC_TYPES[t]), f"~/{t}", qos,
                                                           event_callbacks=events)
        self.published: dict[str, int] = {}
        self._subscribed: set[str] = set()
        self.wanted: tuple[str, ...] = ()  # the outputs with a subscriber, in publishing order
        self._plan: tuple[_Topic, ...] = ()  # theirs, looked up once (not per frame)
        self.raw_wanted = False
        self.fields_wanted = True  # someone subscribes to a field's topic (refresh: the topics' subscribers)
        self.refresh()

    def _matched(self, topic: str, count: int) -> None:
        (self._subscribed.add if count > 0 else self._subscribed.discard)(topic)
        self._update()

    def refresh(self) -> None:
        """Ask every publisher how many subscribe (a subscriber the matched events missed)."""
        self._subscribed = {t for t, p in self.pubs.items() if p.get_subscription_count() > 0}
        self._update()

    def _update(self) -> None:
        subs = self._subscribed
        self.wanted = tuple(t for t in self.pubs if t in subs and t in OUTPUTS)
        self._plan = tuple(_Topic(name, self.pubs[name], value, encode) for name, value, encode in self.out.encoders(self.wanted))
        self.raw_wanted = RAW_TOPIC in subs
        self.fields_wanted = any(OUTPUTS[t].heavy for t in self.wanted)
        if self.on_fields is not None:
            self.on_fields(self.fields_wanted)

    def __call__(self, frame, output) -> None:
        if not self.active():
            return
        counts = self.published
        if self.raw_wanted:  # the raw frame as measured, NaN where the board flagged a measurement
            flagged = self.flags.flagged(frame.saturated, frame.contact_ok)
            _publish(self.pubs[RAW_TOPIC], self.raw(frame.values, frame.stamp_ns, flagged))
            counts[RAW_TOPIC] = counts.get(RAW_TOPIC, 0) + 1
        plan = self._plan
        if output is None or not plan or not output.result.valid:
            return  # an implausible frame is no force: counted by the stream, shown in diagnostics
        # what OutputMessages.build does, with each topic's lookups done once (_update)
        result, filtered, stamp_ns = output.result, output.filtered, output.stamp_ns
        for t in plan:
            v = t.value(result, filtered)
            if v is not None:
                _publish(t.pub, t.encode(v, stamp_ns))
                counts[t.name] = counts.get(t.name, 0) + 1

    def close(self) -> None:
        """Destroy the publishers."""
        for pub in self.pubs.values():
            self.node.destroy_lifecycle_publisher(pub)
        self.pubs = {}
        self.wanted, self.raw_wanted, self._plan = (), False, ()


class BagWriter:
    """A sink writing the outputs ``names`` of every valid frame into a rosbag2 ``writer`` (rosbags)
    under ``prefix``, at the input frame's bag time, stamped as the node stamps them."""

    def __init__(self, writer, names: tuple[str, ...], prefix: str, centers, frame_id: str, typestore) -> None:
        self.writer, self.names = writer, names
        self.out = OutputMessages(centers, frame_id)
        self.conns = {n: writer.add_connection(prefix + n, TOPIC_TYPES[n], typestore=typestore) for n in names}
        self.results = 0

    def __call__(self, frame, output) -> None:
        if output is None or not output.result.valid:
            return  # implausible: no message, as the node publishes none
        self.results += 1
        for name, data in self.out.build(output.result, output.stamp_ns, output.filtered, self.names).items():
            self.writer.write(self.conns[name], frame.t_ns, data)
