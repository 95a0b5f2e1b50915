"""The library's log records on ``/rosout``: a :class:`logging.Handler` that hands every record of
the ``cstomo_sensor`` logger tree to a node's ROS logger, levels kept.

The core logs with :func:`logging.getLogger` (one logger per module) and knows nothing of ROS; while a
node runs, :func:`attach` joins the two, so the driver's reconnects, the tare and the core's warnings
reach ``/rosout`` (and the console) under the node's logger, the message prefixed with the module
(``board.driver: ... connected``).
"""
from __future__ import annotations

import contextlib
import logging
import threading

from rclpy.impl.rcutils_logger import RcutilsLogger

ROOT = logging.getLogger(__name__.split(".")[0])  # the package's logger tree


class RosLogHandler(logging.Handler):
    """Forwards records to ``ros_logger`` while ``context_ok()`` (the node's ROS context is up);
    after a shutdown (SIGINT, SIGTERM: the node is ending), errors go to stderr as Python's own
    last-resort handler writes them, and warnings are dropped: they are the board's port closing
    as a launch or a terminal stops the board together with the node."""

    def __init__(self, ros_logger: RcutilsLogger, context_ok=lambda: True, label=None) -> None:
        super().__init__()
        self.ros_logger = ros_logger
        self.context_ok = context_ok
        self.label = label  # record -> a prefix ('' for none): which sensor, in a process of several

    def emit(self, record: logging.LogRecord) -> None:
        if not self.context_ok():  # /rosout is gone (SIGINT): rcl would print an error per record
            if record.levelno >= logging.ERROR:
                logging.lastResort.handle(record)
            return
        try:
            msg = f"{self.label(record) if self.label else ''}{record.name.partition('.')[2] or record.name}: " \
                  f"{self.format(record)}"
            level, log = record.levelno, self.ros_logger
            # one call site per severity: rclpy keeps one severity per call site of a logger
            if level >= logging.CRITICAL:
                log.fatal(msg)
            elif level >= logging.ERROR:
                log.error(msg)
            elif level >= logging.WARNING:
                log.warning(msg)
            elif level >= logging.INFO:
                log.info(msg)
            else:
                log.debug(msg)
        except Exception:  # noqa: BLE001 - logging must never raise into the code that logs
            self.handleError(record)


_current = threading.local()


@contextlib.contextmanager
def sensor(name: str):
    """Within the block, this thread's records are the sensor ``name``'s (:func:`current_sensor`):
    a process of several sensors (``cstomo_sensor_host``) names which one said what."""
    previous = getattr(_current, "name", "")
    _current.name = name
    try:
        yield
    finally:
        _current.name = previous


def current_sensor() -> str:
    """The sensor whose frames or service this thread is handling ('' if none)."""
    return getattr(_current, "name", "")


def attach(ros_logger: RcutilsLogger, context_ok=lambda: True, label=None) -> RosLogHandler:
    """Send the package's records to ``ros_logger`` at its level (not to stderr a second time), each
    prefixed with ``label(record)`` if given; returns the handler for :func:`detach`."""
    handler = RosLogHandler(ros_logger, context_ok, label)
    ROOT.addHandler(handler)
    ROOT.setLevel(max(int(ros_logger.get_effective_level()), logging.DEBUG))
    ROOT.propagate = False
    return handler


def detach(handler: RosLogHandler) -> None:
    """Undo :func:`attach`: once no node's bridge is left, the package's records propagate again (to a
    program's or a command's own handlers), whatever other handlers the package's logger carries (a
    test harness adds its own to every logger that does not propagate)."""
    ROOT.removeHandler(handler)
    if not any(isinstance(h, RosLogHandler) for h in ROOT.handlers):
        ROOT.propagate = True
        ROOT.setLevel(logging.NOTSET)
