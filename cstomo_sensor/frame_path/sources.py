"""Frame sources: where a sensor's stamped frames come from (python-can's ``BusABC`` shape). No ROS.

A source's :meth:`FrameSource.recv` returns the next :class:`StampedFrame` or None (nothing within
the timeout, or the source is :attr:`~FrameSource.exhausted`); what happens between frames arrives
as calls on the source's event hooks, set by whoever consumes it (:func:`cstomo_sensor.frame_path.loop.run`
sets them to the frame stream's): ``on_reconnect()`` when a board came back after an outage,
``on_corrupt(err)`` for an input that is no frame. :meth:`~FrameSource.stats` says what it counted,
:meth:`~FrameSource.close` releases it.

- :class:`SerialSource`: the board on a serial port (any pyserial URL, ``virtual://NAME`` for the
  in-process simulated board): :class:`~cstomo_sensor.board.driver.BoardDriver` read by the thread that calls
  :meth:`~SerialSource.recv` (no reader thread, no hand-over), its clock mapped onto the host's.
- :class:`ArraySource`: recorded frames with their stamps (a frames file at a nominal rate, a
  simulated timeline).
- a ROS topic and a rosbag2 file: :mod:`cstomo_sensor.ros.sources` (they decode ROS messages).
"""
from __future__ import annotations

import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass

import numpy as np

from ..board.clock import ClockMapper
from ..board.wire import ALL_CONTACTS_OK, NO_SATURATION
from ..errors import ConfigError


@dataclass(slots=True)
class StampedFrame:
    """One frame of volts with its stamp.

    Attributes
    ----------
    values : (208,) ndarray
        Volts.
    stamp_ns : int
        When it was measured, ns on the consumer's clock (the node's ROS clock; 0: unknown).
    age_ns : int
        How long ago it was measured, ns on the monotonic clock (0: just now, or unknown).
    saturated, contact_ok : ndarray or None
        The board's flags ((208,) and (16,) bool), or None; a recorded frame's flagged measurements
        (NaN in a raw message) are passed as ``saturated``.
    t_ns : int
        The recording's own time of the frame (a bag's receive time; else the stamp).
    """

    values: np.ndarray
    stamp_ns: int
    age_ns: int = 0
    saturated: np.ndarray | None = None
    contact_ok: np.ndarray | None = None
    t_ns: int = 0


class FrameSource:
    """The base of the sources (module docstring)."""

    on_reconnect: Callable[[], None] | None = None
    on_corrupt: Callable[[BaseException], None] | None = None
    #: True once a finite source gave its last frame (a live one never is).
    exhausted: bool = False

    def recv(self, timeout: float | None = None) -> StampedFrame | None:
        """The next frame, waiting up to ``timeout`` s (None: as long as it takes); None if none came."""
        raise NotImplementedError

    def stats(self) -> dict:
        """What the source counted (frames at least)."""
        return {}

    def close(self) -> None:
        """Release the source; safe to call more than once."""

    def _corrupt(self, err: BaseException) -> None:
        if self.on_corrupt is not None:
            self.on_corrupt(err)

    def __iter__(self) -> Iterator[StampedFrame]:
        while not self.exhausted:
            frame = self.recv()
            if frame is not None:
                yield frame

    def __enter__(self):
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class ArraySource(FrameSource):
    """Recorded frames with their stamps.

    Parameters
    ----------
    frames : (n, 208) array
    stamps_ns : (n,) ints or None
        The frames' stamps; None: ``rate_hz`` frames per second, the first at ``start_s`` s (default:
        one frame period: the frames of a file at its nominal rate, as ``cstomo estimate`` numbers them).
    saturated : (n, 208) bool array or None
        The frames' flagged measurements.
    """

    def __init__(self, frames, stamps_ns=None, *, rate_hz: float | None = None, start_s: float | None = None,
                 saturated=None) -> None:
        self.frames = np.asarray(frames, dtype=float)
        if self.frames.ndim != 2:
            raise ConfigError(f"frames.shape={self.frames.shape}: expected (n_frames, n_values)")
        n = len(self.frames)
        if stamps_ns is None:
            if rate_hz is None or not rate_hz > 0:
                raise ConfigError.bad_value("rate_hz", rate_hz, "frames per second > 0 (or give stamps_ns)")
            start = 1.0 / rate_hz if start_s is None else start_s
            stamps_ns = np.round(1e9 * (start + np.arange(n) / rate_hz))
        self.stamps_ns = [int(s) for s in np.asarray(stamps_ns).reshape(-1)]
        if len(self.stamps_ns) != n:
            raise ConfigError(f"{len(self.stamps_ns)} stamps for {n} frames: expected one per frame")
        self.saturated = saturated
        self._next = 0
        self.exhausted = n == 0

    def recv(self, timeout: float | None = None) -> StampedFrame | None:
        k = self._next
        if k >= len(self.frames):
            self.exhausted = True
            return None
        self._next = k + 1
        self.exhausted = self._next >= len(self.frames)
        s = self.stamps_ns[k]
        return StampedFrame(self.frames[k], s, 0, None if self.saturated is None else self.saturated[k], None, s)

    def stats(self) -> dict:
        return {"frames": self._next}


class SerialSource(FrameSource):
    """The board on a serial port: :class:`~cstomo_sensor.board.driver.BoardDriver` without a reader thread (the
    thread calling :meth:`recv` reads, decodes and goes on with the frame), each frame stamped with
    the consumer's clock ``now_ns()`` (the node's ROS clock) minus its age (flags None when the board
    flagged nothing, as a source without flags gives them): the board clock mapped
    onto the host's monotonic clock (:class:`~cstomo_sensor.board.clock.ClockMapper`, a window of ``clock_window``
    s; it cannot step); a text-mode frame (no board clock) is stamped now. A reconnect of the board
    calls ``on_reconnect`` from :meth:`recv`, before the returning frames.

    The remaining keyword arguments go to the driver (``protocol``, ``baudrate``, ``rate_hz``,
    ``queue_size``, ``stall_timeout``, ...).
    """

    def __init__(self, url: str, *, now_ns: Callable[[], int] = time.time_ns, clock_window: float = 10.0,
                 **driver) -> None:
        from ..board.driver import BoardDriver

        self.clock = ClockMapper(clock_window)
        self._now_ns = now_ns
        self.driver = BoardDriver(url, thread=False, on_reconnect=self._reconnected, **driver)

    def _reconnected(self) -> None:
        if self.on_reconnect is not None:
            self.on_reconnect()

    def recv(self, timeout: float | None = None) -> StampedFrame | None:
        frame = self.driver.get(1e9 if timeout is None else timeout)
        if frame is None:
            return None
        now_ns = self._now_ns()
        age_ns = 0  # text mode: no board clock
        if frame.board_time_us is not None:
            mono_ns = time.monotonic_ns()
            age_ns = mono_ns - self.clock.stamp_ns(frame.board_time_us, mono_ns)
        # a frame without flags (the decoder's shared arrays) carries None: nothing flagged, no per-frame test
        sat, ok = frame.saturated, frame.contact_ok
        return StampedFrame(frame.values, now_ns - age_ns, age_ns, None if sat is NO_SATURATION else sat,
                            None if ok is ALL_CONTACTS_OK else ok, now_ns - age_ns)

    def stats(self) -> dict:
        s = self.driver.stats()
        return {"frames": s.frames, "reconnects": s.reconnects, "connected": s.connected}

    def close(self) -> None:
        self.driver.close()
