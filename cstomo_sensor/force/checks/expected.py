"""A controller's expected load (``~/expected_wrench``): an input to check, never to trust (issue 34,
item 5). No ROS, no serial.

A controller's dynamics model says what load the joint carries now (:meth:`FrameStream.expect_load`);
the slow states (force/slow_states/coordinator.py) use it as a measurement of the force in the joint fit of the device's
change (force/estimators/scale_fit.py
:class:`~cstomo_sensor.force.estimators.scale_fit.JointScale`). Before it is used it must be a load the sensor
can carry and the frames can have: :class:`ExpectedLoad` refuses one

- whose force is not finite (``not_finite``), or beyond the sensor's range ``max_force`` (``beyond_range``);
- in another frame than the wrench's ``frame_id`` (``other_frame``);
- stamped more than ``expected_wrench_tolerance`` before the frames (``stale``) or after them
  (``future``): checked when it arrives (against the latest frame) and again for each frame it is
  used for (it is used for frames up to the tolerance after its stamp, never after);
- far from what the frame says (``far``): its force against the frame's own estimate, each axis to
  the frame's 1-sigma and the message's, a chi-square of 3 degrees beyond :data:`FAR_CHI2`.

Each refusal is counted; the first of each kind is logged (naming the input), every kind is said in
the diagnostics of the period it happened in, and the figures count them all. An accepted message
replaces the previous one (only the newest counts): a flood costs a few microseconds per message
and never reaches the frame path's lock. Used, it moves the device's states by at most the frame's
own 1-sigma of the scale (:func:`bounded`), and never the published force: the force is the frame's,
given the states.
"""
from __future__ import annotations

import logging
import math
import threading

import numpy as np

from ...errors import ConfigError

log = logging.getLogger(__name__)

#: The kinds of refusal, in words.
KINDS = {
    "not_finite": "a force that is not finite",
    "beyond_range": "a force beyond the sensor's range (max_force)",
    "other_frame": "a force in another frame than the wrench's (frame_id)",
    "stale": "a stamp older than the frames by more than expected_wrench_tolerance",
    "future": "a stamp ahead of the frames by more than expected_wrench_tolerance",
    "far": "a force far from what the frames say (beyond their sigma and its own)",
}
#: The consistency test's bound: the chi-square of 3 degrees of freedom of the expected force against the
#: frame's estimate (each axis to the frame's 1-sigma and the message's), exceeded by chance with a
#: probability of 1e-5 per frame (a true expectation, used for 50 frames, is refused once in 2000).
FAR_CHI2 = 25.9


class ExpectedLoad:
    """The checks of a controller's expected load for a sensor of range ``max_force`` (N), its wrench in
    ``frame_id``, the messages' stamps within ``tolerance`` s of the frames'; ``name``: the input, as
    the log and the diagnostics name it."""

    def __init__(self, max_force: float, tolerance: float, frame_id: str, name: str = "expected load") -> None:
        self.max_force, self.tolerance, self.frame_id, self.name = float(max_force), float(tolerance), frame_id, name
        self.lock = threading.Lock()
        self._pending: tuple | None = None  # (force (3,), sigma, t s or None: from the next frame, stamp checked)
        self.t_frame: float | None = None  # the latest frame's time (s), for the arrival's stamp check
        self.accepted = 0
        self.used_frames = 0
        self.refused = dict.fromkeys(KINDS, 0)
        self._mark = dict(self.refused)  # the counts when the diagnostics' period began
        self._said: set[str] = set()

    @property
    def pending(self) -> tuple | None:
        """The accepted message in effect: (force, sigma, t s or None, its stamp checked), or None."""
        return self._pending

    def offer(self, force, sigma: float, stamp_ns: int | None = None, frame_id: str | None = None,
              source: str | None = None) -> str:
        """A message: ``force`` (3,) N in ``frame_id`` (None: the wrench's), 1-sigma ``sigma`` N per axis,
        stamped ``stamp_ns`` (the frames' clock; None: from the next frame on), from the input ``source``
        (None: :attr:`name` as it is; else it becomes the name said). Returns '' if it is
        accepted (it replaces the one before), else the kind of its refusal (:data:`KINDS`: counted, and
        said once). A force of the wrong shape or a sigma that is no 1-sigma is the caller's error:
        :class:`ConfigError`."""
        if source is not None:
            self.name = source
        f = np.asarray(force, float).reshape(-1)
        if f.shape != (3,):
            raise ConfigError.bad_value("expected load", force, "3 force components in newtons")
        if not (math.isfinite(sigma) and sigma > 0):
            raise ConfigError.bad_value("expected load sigma", sigma, "a 1-sigma > 0 in newtons")
        t = None if stamp_ns is None else stamp_ns * 1e-9
        kind, why = "", ""
        if not np.isfinite(f).all():
            kind, why = "not_finite", f"force {tuple(f.tolist())}"
        elif float(np.linalg.norm(f)) > self.max_force:
            kind, why = "beyond_range", f"|force| {np.linalg.norm(f):.4g} N > max_force {self.max_force:g} N"
        elif frame_id is not None and frame_id != self.frame_id:
            kind, why = "other_frame", f"frame_id {frame_id!r}, the wrench's is {self.frame_id!r}"
        else:
            kind, why = self._when(t, self.t_frame)
        if kind:
            self.refuse(kind, why)
            return kind
        with self.lock:
            self._pending = (f, float(sigma), t, t is None or self.t_frame is not None)
            self.accepted += 1
        return ""

    def _when(self, t: float | None, t_frame: float | None) -> tuple[str, str]:
        """('stale' or 'future', why) for a message at ``t`` against a frame at ``t_frame`` (either None:
        nothing to check), else ('', '')."""
        if t is None or t_frame is None:
            return "", ""
        if t < t_frame - self.tolerance:
            return "stale", f"stamp {t:.9g} s, {t_frame - t:.4g} s before the frames"
        if t > t_frame + self.tolerance:
            return "future", f"stamp {t:.9g} s, {t - t_frame:.4g} s after the frames"
        return "", ""

    def refuse(self, kind: str, why: str) -> None:
        """Count a refusal of ``kind``; the first of each kind is logged."""
        with self.lock:
            self.refused[kind] += 1
            first = kind not in self._said
            self._said.add(kind)
        if first:
            log.warning("%s refused, not used: %s: %s. Said once per kind; every refusal is counted in the "
                        "diagnostics (expected_refused)", self.name, KINDS[kind], why)

    def for_frame(self, t: float | None, force: np.ndarray, sigma) -> tuple | None:
        """The expected load (force, sigma) to use for a frame at ``t`` s (None: no time) whose own estimate
        is ``force`` (3,) N of per-axis 1-sigma ``sigma`` (None: not known yet, the load is not used for
        it); None when there is none, it is not yet or no longer in effect (its stamp within the tolerance
        of the frame's), or it is refused now (``far``; ``stale``, ``future`` when no frame had come to
        check its stamp against when it arrived)."""
        e = self._pending
        if e is None or sigma is None:
            return None
        f, s, te, checked = e
        if t is not None:
            if te is None:  # from the next frame on: its time is the frame's
                te = t
                with self.lock:
                    if self._pending is e:
                        self._pending = e = (f, s, t, True)
            kind, why = self._when(te, t)
            if kind == "stale" and checked:
                self._drop(e)  # its time is over
                return None
            if kind == "future" and checked:
                return None  # the frames have not reached it yet
            if kind:
                return self._refused_now(e, kind, why)
        d = f - force
        chi2 = float(np.sum(d * d / (np.square(sigma) + s * s)))
        if not chi2 <= FAR_CHI2:
            return self._refused_now(e, "far", f"force {np.round(f, 3).tolist()} N against the frame's "
                                               f"{np.round(force, 3).tolist()} N: chi-square {chi2:.4g} > {FAR_CHI2:g}")
        self.used_frames += 1
        return f, s

    def _drop(self, e: tuple) -> None:
        with self.lock:
            if self._pending is e:
                self._pending = None

    def _refused_now(self, e: tuple, kind: str, why: str) -> None:
        self._drop(e)
        self.refuse(kind, why)
        return None

    def status(self) -> tuple[int, list[str], dict]:
        """(level: 1 WARN when messages were refused this period, problems, figures)."""
        with self.lock:
            counts, mark = dict(self.refused), self._mark
        new = {k: n - mark[k] for k, n in counts.items() if n > mark[k]}
        total = ", ".join(f"{k} {n}" for k, n in counts.items() if n) or "none"
        kv = {"expected_accepted": self.accepted, "expected_refused": total}
        if not new:
            return 0, [], kv
        kinds = "; ".join(f"{n} with {KINDS[k]} ({k})" for k, n in new.items())
        return 1, [f"{self.name}: {sum(new.values())} messages refused, not used: {kinds}"], kv

    def end_period(self) -> None:
        """The diagnostics' period ends: the next :meth:`status` says the refusals from here."""
        with self.lock:
            self._mark = dict(self.refused)


def bounded(with_load: tuple, without: tuple | None) -> tuple:
    """A frame's joint measurement of the scale (:meth:`~cstomo_sensor.force.estimators.scale_fit.JointScale.measure`: (d, var, u, v,
    force, the others' part)) with an expected load, bounded by the one ``without`` it: its ``d`` within
    the frame's own 1-sigma of ``d`` (one message moves the states by no more than one frame's noise
    may), and the force's step and the other states' measurement the frame's own (the published force
    is what the frames say, given the states)."""
    if without is None:
        return with_load
    d0, var0, u0, v0, force0, *others0 = without
    step = math.sqrt(var0)
    d = d0 + min(max(with_load[0] - d0, -step), step)
    return (d, with_load[1], u0, v0, force0, *others0)
