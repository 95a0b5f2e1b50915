"""The one frame loop: a source's stamped frames through a sensor's frame stream to its sinks. No ROS.

``run(source, stream, sinks)`` is the node (the serial board or a topic in, ROS publishers out),
``cstomo replay`` (a bag in, a bag writer and a forces file out), ``cstomo estimate`` (a frames file
in, a forces file out), ``cstomo calibrate`` and the benchmarks: the same loop with other sources and
sinks, so they cannot disagree (docs/node.md, "One frame stream").

A sink is a callable ``sink(frame, output)`` given every frame the source yields with what the stream
made of it (:class:`~cstomo_sensor.frame_path.outputs.FrameOutput`, or None: a tare frame, a late or dropped
one, no reference yet); a sink builds only what it is asked for (the node's publishers only the
topics someone subscribes to). ``close()`` is called on the sinks that have it when the source is
exhausted.
"""
from __future__ import annotations

import threading
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np

from ..frames_io import write_forces
from .pipeline import FrameResult
from .sources import FrameSource, StampedFrame


def connect(source: FrameSource, stream) -> None:
    """Route the source's events to the stream: a reconnect restarts its filter and ends a pending tare
    (:meth:`~cstomo_sensor.frame_path.stream.FrameStream.reconnected`), an input that is no frame is counted
    as corrupt."""
    source.on_reconnect = stream.reconnected
    source.on_corrupt = stream.corrupt


def step(stream, sinks: Sequence[Callable], frame: StampedFrame, process: bool = True):
    """One frame through ``stream`` (``process`` False: only counted) and to every sink; returns its output.
    The body of :func:`run`'s loop, and the loop of a caller whose source pushes its frames (the node's topic
    input, ros/node.py) or who acts between frames (a benchmark's controller, tools/bench/robot.py)."""
    out = stream.push(frame.values, frame.saturated, frame.contact_ok, frame.stamp_ns, frame.age_ns, process)
    for sink in sinks:
        sink(frame, out)
    return out


def run(source: FrameSource, stream, sinks: Sequence[Callable] = (), *, stop: threading.Event | None = None,
        process: Callable[[], bool] | None = None, timeout: float = 0.1) -> int:
    """Push every frame of ``source`` through ``stream`` to ``sinks`` until the source is exhausted or
    ``stop`` is set; ``process()`` False: frames are only counted (an inactive node that is not
    taring). Returns the frames taken. Closes the sinks (not the source) when the source is exhausted."""
    connect(source, stream)
    n = 0
    while not (stop is not None and stop.is_set()):
        frame = source.recv(timeout)
        if frame is None:
            if source.exhausted:
                break
            continue
        n += 1
        step(stream, sinks, frame, True if process is None else process())
    if source.exhausted:
        for sink in sinks:
            close = getattr(sink, "close", None)
            if close is not None:
                close()
    return n


class Results:
    """A sink keeping one :class:`~cstomo_sensor.frame_path.pipeline.FrameResult` per frame: with
    ``every_frame`` a frame without an output gets an implausible result naming why it was dropped
    (``cstomo estimate``: one row per input frame), else only the frames with an output are kept
    (``cstomo replay``: tare frames give no row). ``path``: written as a forces file on close
    (docs/formats.md#forces-file; the ``valid`` column always, or, with ``valid_column='auto'``, only
    when a frame was implausible)."""

    def __init__(self, stream=None, every_frame: bool = False, path: str | Path | None = None,
                 valid_column: bool | str = True) -> None:
        self.stream = stream
        self.every_frame = every_frame
        self.path = path
        self.valid_column = valid_column
        self.results: list[FrameResult] = []
        self.index: list[int] = []  # each result's frame index in the input (the forces file's `frame`)
        self._seen = 0

    def __call__(self, frame: StampedFrame, out) -> None:
        if out is not None:
            self.results.append(out.result)
        elif self.every_frame:
            self.results.append(FrameResult.implausible(self.stream.counter.counts.reject_reason))
        else:
            self._seen += 1
            return
        self.index.append(self._seen)
        self._seen += 1

    @property
    def forces(self) -> np.ndarray:
        return np.array([r.force for r in self.results], float).reshape(-1, 3)

    @property
    def valid(self) -> np.ndarray:
        return np.array([r.valid for r in self.results], bool)

    def close(self) -> None:
        if self.path is None:
            return
        r, valid = self.results, self.valid
        write_forces(self.path, self.forces, valid=None if self.valid_column == "auto" and valid.all() else valid,
                     consistency=np.array([x.consistency for x in r], float),
                     foreign_load=np.array([x.foreign_load for x in r], bool),
                     sigma_n=np.array([x.sigma_n for x in r], float), index=np.array(self.index, int))


class Trace:
    """A sink for the benchmarks: per frame, the force read (NaN when none: a tare frame, a dropped or
    an implausible one), its ``sigma_n``, the seconds since the previous frame's (the stream's time
    per frame, the source's few microseconds included) and ``probe()`` after it (e.g. the
    pipeline's tracked scale)."""

    def __init__(self, probe: Callable[[], float] | None = None) -> None:
        import time

        self._clock = time.perf_counter
        self._t = self._clock()
        self.probe = probe
        self.forces: list = []
        self.sigma_n: list[float] = []
        self.seconds: list[float] = []
        self.probed: list[float] = []

    def __call__(self, frame: StampedFrame, out) -> None:
        t = self._clock()
        self.seconds.append(t - self._t)
        self._t = t
        ok = out is not None and out.result.valid
        self.forces.append(out.result.force if ok else (np.nan,) * 3)
        self.sigma_n.append(out.result.sigma_n if ok else np.nan)
        if self.probe is not None:
            self.probed.append(self.probe())
