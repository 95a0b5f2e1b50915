"""Creep: a held load reads constant (docs/physics.md#device-changes).

Under a constant load the rubber's strain keeps growing, by a fraction ``c`` (2..6 %) of its initial
value per decade of time after the load is applied, from 0.1 s on, and recovers the same way after
the load is removed; the resistivity, and so the voltages' change, follow the strain. For any load
history (Boltzmann superposition of each change of load, ``phi(tau) = log10(max(tau, 0.1) / 0.1)``)
the change measured is

    y_meas(t) = y(t) + c * integral phi(t - t') dy(t')

with ``y`` the change of the load as it is now. :class:`CreepCompensator` removes the integral. The
kernel is written as a sum of exponentials (:func:`creep_modes`: 15 time constants from 0.01 s to
a day offered, weights fitted once with non-negative weights, which keeps 11, from 0.32 s; the kernel
to 0.07 of a decade beyond 0.3 s, i.e. 0.3 % of a load at 4 % per decade, 0.03 of a decade beyond 1 s
and 0.005 at 20 s; within the first 0.2 s after a change, where the law is flat until 0.1 s and then
kinks, it runs up to 0.17 of a decade ahead: 0.7 % of the change at 4 %, for a few frames), so the
integral is ``c sum_k w_k s_k(t)``, each ``s_k`` the change low-passed with time constant ``tau_k``: a few
vectors updated per frame, whatever the history's length.

It acts on the normalised change (what the estimator, the stress field and the drift tracker see),
before them all: a held load's force and field read constant, and the rest after a long load reads
zero while the rubber recovers, so the drift tracker is not fooled by the recovery into taking it for
a change of the device. The change is taken as proportional to the strain: true to first order (the
material law bends at large compressions; the creep is a few % of the load's change, the error of
this a few % of that).

What it cannot do, said plainly: the coefficient is the rubber's (``cstomo calibrate`` fits it from a
held load; a calibration file carries it; else the documented middle, 4 % per decade, is assumed:
up to 2 % per decade of a held load off on a rubber at 2 or 6 %); loads before the reference (a tare
taken while a previous load still recovers) are not known to it.
"""
from __future__ import annotations

from functools import cache

import numpy as np

from ..model.material import CREEP_T0, TYPICAL_CREEP_PER_DECADE

#: The coefficient assumed without a calibration: the middle of the documented 2..6 % per decade,
#: the simulated board's default rubber too (model/material.py declares both; CREEP_T0: creep counts
#: from this many seconds after a change of load).
DEFAULT_CREEP = TYPICAL_CREEP_PER_DECADE
#: Seconds between frames without stamps (as the drift tracker's).
DEFAULT_PERIOD = 0.01
#: The largest coefficient taken (rubbers: 0.02..0.06); the compensation feeds back its own output,
#: stable to about 0.3 per decade.
MAX_CREEP = 0.2
#: Longest time step taken between two frames, in frame periods (the running mean of the steps): a
#: stamp that jumps (a stepped clock) does not age the history by more; an outage ages it by that
#: much only (a load held through it is a little younger to the compensation than it is).
MAX_STEPS = 10.0


def creep_problem(c) -> str:
    """Why ``c`` is no creep coefficient ('' if it is one)."""
    if isinstance(c, bool) or not isinstance(c, (int, float)) or not 0 <= c <= MAX_CREEP:
        return f"a fraction per decade, 0 <= c <= {MAX_CREEP:g} (rubbers: 0.02..0.06; 0 = off)"
    return ""


@cache
def creep_modes() -> tuple[np.ndarray, np.ndarray]:
    """(tau (k,) s, w (k,)): ``log10(max(tau, 0.1) / 0.1) ~ sum_k w_k (1 - exp(-tau / tau_k))`` (module
    docstring), fitted with non-negative weights on 0.01 s .. 1e5 s, log-spaced."""
    from scipy.optimize import nnls

    taus = CREEP_T0 * 10.0 ** np.arange(-1.0, 6.01, 0.5)
    grid = np.logspace(-2, 5, 1400)
    target = np.log10(np.maximum(grid, CREEP_T0) / CREEP_T0)
    w, _ = nnls(1.0 - np.exp(-grid[:, None] / taus[None, :]), target)
    keep = w > 0
    return taus[keep], w[keep]


def fit_creep(times, magnitudes, min_time: float = 1.0) -> float:
    """The creep coefficient of a held load: ``|F|(t) = A (1 + c log10(t / 0.1))`` fitted by least squares
    to the (uncompensated) force magnitudes at ``times`` (s since the load was applied), from
    ``min_time`` on (the load settled). Raises ValueError when the hold is too short to tell (less
    than a decade of time from ``min_time``) or the fit is no creep coefficient."""
    t, m = np.asarray(times, float), np.asarray(magnitudes, float)
    t0 = max(min_time, CREEP_T0)
    use = (t >= t0) & np.isfinite(m)
    if use.sum() < 10 or t[use].max() < 10 * t0:
        span = f"{t.min():g}..{t.max():g} s" if t.size else "no frames"
        raise ValueError(f"a held load over {span} with {int(use.sum())} usable frames from {t0:g} s on: expected "
                         f"a decade of time from {t0:g} s (to {10 * t0:g} s or more; a minute is better) and 10 frames")
    phi = np.log10(t[use] / CREEP_T0)
    (a, b), *_ = np.linalg.lstsq(np.stack([np.ones_like(phi), phi], axis=1), m[use], rcond=None)
    c = float(b / a) if a > 0 else float("nan")
    if creep_problem(c):
        raise ValueError(f"fitted creep {c:.3g} per decade: expected {creep_problem(c)}; was the load held still?")
    return c


def creep_kernel(tau) -> np.ndarray:
    """The fitted kernel at ``tau`` (s): what :class:`CreepCompensator` removes per unit of change."""
    taus, w = creep_modes()
    return (1.0 - np.exp(-np.atleast_1d(np.asarray(tau, float))[:, None] / taus)) @ w


class CreepCompensator:
    """The creep of the changes seen so far (module docstring): :attr:`offset` (n_meas,) is what
    the rubber's creep adds to the change now, for the pipeline to subtract.

    Parameters
    ----------
    coefficient : float
        The rubber's creep per decade (0.02..0.06), 0 <= c <= :data:`MAX_CREEP`.
    n_meas : int
        Measurements per frame.
    """

    def __init__(self, coefficient: float, n_meas: int) -> None:
        why = creep_problem(coefficient)
        if why:
            raise ValueError(f"creep coefficient {coefficient!r}: expected {why}")
        self.coefficient = float(coefficient)
        taus, w = creep_modes()
        self._tau, self._cw = taus, self.coefficient * w
        self._s = np.zeros((len(taus), n_meas))  # the change low-passed by each time constant
        self._d = np.empty_like(self._s)
        self.offset = np.zeros(n_meas)
        self._t: float | None = None
        self._period, self._steps = DEFAULT_PERIOD, 0  # the frames' period (s), the steps it is the mean of
        self._dt = -1.0
        self._a = np.zeros((len(taus), 1))

    def observe(self, y: np.ndarray, t: float | None = None, frozen: np.ndarray | None = None) -> None:
        """Take the compensated change ``y`` (n_meas,) of a frame at time ``t`` (s; None:
        :data:`DEFAULT_PERIOD` after the previous frame; a stamp that goes back counts 0 s, a jump at
        most :data:`MAX_STEPS` frame periods) into the history, except on the channels ``frozen`` (excluded: their
        history waits); :attr:`offset` becomes the creep at that time (for the next frame)."""
        dt = DEFAULT_PERIOD if t is None or self._t is None else min(max(t - self._t, 0.0), MAX_STEPS * self._period)
        if t is not None:  # a stepped clock: one frame's step is clipped, the next ones count from it
            self._t = t
        if dt > 0:
            self._period = dt if self._steps == 0 else self._period + (dt - self._period) / min(self._steps + 1, 100)
            self._steps += 1
        if dt != self._dt:  # frames come at one rate: the factors are computed once
            self._dt = dt
            self._a = -np.expm1(-dt / self._tau)[:, None]
        d = np.subtract(y, self._s, out=self._d)
        d *= self._a
        if frozen is not None:
            d[:, frozen] = 0.0
        self._s += d
        np.dot(self._cw, self._s, out=self.offset)

