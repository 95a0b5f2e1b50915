"""The board's noise estimated from its own frames, for a reference that measured none (issue 20). No
ROS, no serial.

A tare of N >= 2 frames measures the per-channel noise (force/reference/files.py); a one-frame reference (a
one-frame tare, a one-row reference file without its ``.noise.csv``) does not, and the estimators
then assumed :data:`~.files.DEFAULT_NOISE_DB`. A 40 dB board is 10 x noisier than that: its frames
all trip the foreign-load flag and the estimators weigh the channels as if they were quiet. The
frames themselves tell the noise:

- **model** (docs/physics.md#noise): white noise of one standard deviation ``sigma`` on every channel,
  constant over a session. The estimate is that one level; a board whose channels differ is measured
  per channel by a tare of several frames.
- **one pair**: the difference of two consecutive frames, ``d = V_k - V_(k-1)``, has noise of std
  ``sqrt(2) sigma`` on every channel; a load that moves over tenths of a second changes little from
  one frame to the next at 100 frames/s, and the drift of the device (minutes) nothing. The pair's
  level is ``median_i |d_i| / (sqrt(2) * 0.6745)`` over the channels in use (0.6745: the median of
  ``|N(0, 1)|``): a fast load moves some channels much more than others, and the median ignores up to
  half of them. Over 208 channels one pair's level has a spread of about 8 % (1 sigma).
- **over pairs**: the median of the latest :data:`WINDOW` pairs' levels, so a step of the load, a
  reconnect or a glitch is one pair among many. The estimate is used only when at least
  :data:`AGREE_FRACTION` of those pairs lie within :data:`AGREE` of it (pure noise: all of them); frames
  of distinct loads one after the other (a file of one frame per load, not a time series) fail that
  and keep the assumed noise rather than take the loads' changes for noise.

The frame stream (frame_path/stream.py) runs one :class:`NoiseEstimate` over the frames it processes while
the noise in use is not measured, and hands the level to the pipeline after :data:`MIN_PAIRS` pairs,
then measures one pair in :data:`SAMPLE_EVERY` frames and hands it over again, every
:data:`UPDATE_EVERY` pairs, when it moved by more than :data:`RETUNE` (the estimators are rebuilt then:
7-13 ms, at most every 20 s at 100 frames/s). Per measured pair: one subtraction and one partial sort
of 208 values, 5-7 us (docs/node.md). ``cstomo estimate`` runs the same estimate over its whole
frames file first (:func:`noise_level`), so every frame gets it.
"""
from __future__ import annotations

import math

import numpy as np

from ...errors import ConfigError

#: The median of |N(0, 1)|: ``median |d| / MAD_NORMAL`` is the std of a Gaussian d.
MAD_NORMAL = 0.6744897501960817
#: Pairs of consecutive frames before an estimate is used (0.1 s at 100 frames/s): the median of 10
#: pairs' levels has a spread of about 3 % (1 sigma).
MIN_PAIRS = 10
#: Once an estimate is in use, one pair in this many frames is measured (the others only keep their
#: frame for the next pair): a quarter of the cost, the window four times as long.
SAMPLE_EVERY = 4
#: The latest pairs the estimate is the median of (40 s at 100 frames/s, one pair in 4 frames).
WINDOW = 1000
#: Pairs between two evaluations of an estimate in use (20 s at 100 frames/s).
UPDATE_EVERY = 500
#: A new estimate replaces the one in use when it differs by more than this fraction of it.
RETUNE = 0.1
#: A pair agrees with the estimate when its level is within this fraction of it (noise alone: 3
#: sigma of one pair's level) ...
AGREE = 0.25
#: ... and the estimate stands when at least this fraction of the pairs agree.
AGREE_FRACTION = 0.5


def pair_level(d_abs: np.ndarray) -> float:
    """The noise level (std of one frame, volts) of one pair from ``d_abs``, the absolute differences
    of two consecutive frames over the channels in use (partially sorted in place)."""
    m = len(d_abs)
    if m == 0:
        return math.nan
    h = m // 2
    if m % 2:
        d_abs.partition(h)
        med = d_abs[h]
    else:
        d_abs.partition((h - 1, h))
        med = 0.5 * (d_abs[h - 1] + d_abs[h])
    return float(med) / (math.sqrt(2.0) * MAD_NORMAL)


def level_of(levels: np.ndarray) -> tuple[float, float]:
    """(the estimate: the median of the pairs' ``levels``, the fraction of them within :data:`AGREE`
    of it); (NaN, 0.0) without pairs."""
    lv = np.asarray(levels, float)
    lv = lv[np.isfinite(lv)]
    if not lv.size:
        return math.nan, 0.0
    med = float(np.median(lv))
    return med, float(np.mean(np.abs(lv - med) <= AGREE * med))


class NoiseEstimate:
    """The running estimate of the board's noise level from consecutive frames (module docstring).

    Parameters
    ----------
    n_meas : int
        Values per frame.
    window : int
        The latest pairs the estimate is the median of.
    """

    def __init__(self, n_meas: int, window: int = WINDOW) -> None:
        if isinstance(window, bool) or not isinstance(window, (int, np.integer)) or window < 1:
            raise ConfigError.bad_value("window", window, "a count of frame pairs >= 1")
        self._prev = np.zeros(n_meas)
        self._prev_keep: np.ndarray | None = None  # the channels in use in _prev (None: all)
        self._follows = False  # the next frame follows the one in _prev
        self._d = np.empty(n_meas)
        self._levels = np.full(int(window), np.nan)
        self.pairs = 0  # pairs observed (all time)

    @property
    def count(self) -> int:
        """Pairs the estimate is the median of (at most ``window``)."""
        return min(self.pairs, len(self._levels))

    def observe(self, frame: np.ndarray, keep: np.ndarray | None = None, pair: bool = True) -> None:
        """The next frame (n_meas,) volts, finite on the channels ``keep`` (None: all), measured right
        after the previous one observed: its difference to that one is a pair (``pair`` False: the
        frame is only kept for the next pair, which costs one copy)."""
        if pair and self._follows:
            d = np.subtract(frame, self._prev, out=self._d)
            np.abs(d, out=d)
            if keep is not None or self._prev_keep is not None:
                both = keep if self._prev_keep is None else self._prev_keep if keep is None else keep & self._prev_keep
                d = d[both]
            level = pair_level(d)
            if math.isfinite(level):
                self._levels[self.pairs % len(self._levels)] = level
                self.pairs += 1
        self._prev[:] = frame
        self._prev_keep = None if keep is None else np.array(keep, bool)
        self._follows = True

    def restart(self) -> None:
        """The next frame does not follow the latest one observed (no pair across a gap)."""
        self._follows = False

    def level(self) -> tuple[float, float]:
        """(the estimate in volts, the fraction of the pairs that agree with it): :func:`level_of`
        over the latest ``window`` pairs."""
        return level_of(self._levels[: self.count])


def noise_level(frames: np.ndarray, keep: np.ndarray | None = None) -> tuple[float, int, float]:
    """(level in volts, pairs, agreeing fraction) of the consecutive frames ``frames`` (n, n_meas) of a
    file, in their order, over the channels ``keep`` (None: those finite in both frames of a pair).
    The level is NaN with fewer than two frames."""
    f = np.atleast_2d(np.asarray(frames, float))
    est = NoiseEstimate(f.shape[1], window=max(len(f) - 1, 1))
    for row in f:
        ok = np.isfinite(row) if keep is None else np.asarray(keep, bool) & np.isfinite(row)
        est.observe(np.where(ok, row, 0.0), None if ok.all() else ok)
    level, agree = est.level()
    return level, est.count, agree


def is_time_series(pairs: int, agree: float) -> bool:
    """Whether ``pairs`` consecutive frame pairs, the fraction ``agree`` of them differing by noise alone
    (:func:`noise_level`, :meth:`NoiseEstimate.level`), are a time series of one device: at least
    :data:`MIN_PAIRS` pairs, at least :data:`AGREE_FRACTION` of them agreeing. The one rule of the
    stream's noise estimate (frame_path/noise_in_use.py), ``cstomo calibrate``'s recorded noise and ``cstomo
    estimate``'s creep (which acts on a history in time)."""
    return pairs >= MIN_PAIRS and agree >= AGREE_FRACTION


def snr_db(level: float, reference: np.ndarray) -> float:
    """The SNR (dB) of a noise ``level`` (volts) against the reference's rms (docs/physics.md#noise)."""
    rms = float(np.sqrt(np.mean(np.asarray(reference, float) ** 2)))
    return 20.0 * math.log10(rms / level) if level > 0 else math.inf
