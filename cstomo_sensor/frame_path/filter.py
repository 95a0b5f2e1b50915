"""The low-pass of ``~/wrench_filtered``: a first-order filter on the force, driven by the frames' stamps.

Per frame with stamp ``t`` (s) and force ``x`` (3,): ``y += a (x - y)`` with
``a = 1 - exp(-(t - t_prev) / tau)`` and ``tau = 1 / (2 pi cutoff_hz)``. That is the exact response
of the continuous filter ``H(s) = 1 / (1 + s tau)`` to an input held between frames, so the cutoff
means the same at any frame rate and through jitter in the stamps: the gain is -3 dB at
``cutoff_hz``, a step reaches 63.2 % after ``tau`` and 95 % after ``3 tau``, and the delay of a slow
signal (the group delay at low frequency) is ``tau``: 8 ms at 20 Hz. On white noise at ``fs`` frames/s
the standard deviation falls by ``sqrt(a / (2 - a))`` (about ``sqrt(pi cutoff_hz / fs)``; 0.25 at 20 Hz
and 1000 frames/s).

The filter restarts from the next frame (its output is then that frame's force) after :meth:`reset`
(the node calls it on a new reference: a tare; and after a reconnect of the board), after a gap of
more than ``max_gap`` seconds between frames, and when the stamps go backwards (a board that
restarted its clock). ``cutoff_hz`` = 0 is "off": the output is the input.
"""
from __future__ import annotations

import math

import numpy as np

from ..errors import ConfigError


class LowPass:
    """First-order low-pass of a 3-vector over stamped samples (module docstring).

    Parameters
    ----------
    cutoff_hz : float
        -3 dB frequency in Hz; 0 = off (the output is the input).
    max_gap : float
        Seconds between frames beyond which the filter restarts.
    """

    def __init__(self, cutoff_hz: float, max_gap: float = 0.5) -> None:
        if not (math.isfinite(cutoff_hz) and cutoff_hz >= 0):
            raise ConfigError.bad_value("wrench_filter_hz", cutoff_hz, "a cutoff >= 0 in Hz (0 = off)")
        if not max_gap > 0:
            raise ConfigError.bad_value("max_gap", max_gap, "seconds > 0")
        self.cutoff_hz = float(cutoff_hz)
        self.tau = 1.0 / (2 * math.pi * cutoff_hz) if cutoff_hz > 0 else 0.0
        self.max_gap = float(max_gap)
        self.resets = 0  # restarts for any reason (the first frame included)
        self._t: float | None = None
        self._y = (0.0, 0.0, 0.0)

    def reset(self) -> None:
        """Restart from the next frame."""
        self._t = None

    def __call__(self, x, t: float) -> tuple[float, float, float]:
        """The filtered value after the sample ``x`` (3,) at time ``t`` (s)."""
        x0, x1, x2 = np.asarray(x, dtype=float).tolist()
        last, self._t = self._t, t
        dt = -1.0 if last is None else t - last
        y0, y1, y2 = self._y
        if not self.tau or not 0.0 <= dt <= self.max_gap or not math.isfinite(x0 + x1 + x2 + y0 + y1 + y2):
            if self.tau and not 0.0 <= dt <= self.max_gap:
                self.resets += 1
            self._y = (x0, x1, x2)
            return self._y
        a = -math.expm1(-dt / self.tau)
        self._y = (y0 + a * (x0 - y0), y1 + a * (x1 - y1), y2 + a * (x2 - y2))
        return self._y
