"""Creep: a held load reads constant (docs/physics.md#device-changes).

Under a constant load the rubber's strain keeps growing, by a fraction ``c`` (2..6 %) of its initial
value per decade of time after the load is applied, from 0.1 s on, and recovers the same way after
the load is removed; the resistivity, and so the voltages' change, follow the strain. For any load
history (Boltzmann superposition of each change of load, ``phi(tau) = log10(max(tau, 0.1) / 0.1)``)
the change measured is

    y_meas(t) = y(t) + c * integral phi(t - t') dy(t')

with ``y`` the change of the load as it is now. :class:`CreepCompensator` removes the integral. The
law is flat for 0.1 s and then rises as ``log10(1 + u / 0.1)``, ``u`` the time since 0.1 s after the
change: a smooth function that a sum of exponentials follows closely (:func:`creep_modes`: 11 time
constants, 0.03 s to 1.5 days, weights fitted once, non-negative: within 0.002 of a decade from 0.1 s
to 1e5 s, 0.01 % of a load at 4 % per decade). So the compensator keeps the last 0.1 s of changes
(a few frames) and low-passes each change once it is 0.1 s old: ``c sum_k w_k s_k(t)``, each ``s_k``
the change delayed by 0.1 s and low-passed with time constant ``tau_k``, a few vectors updated per
frame whatever the history's length. As the creep of the next frame depends only on changes 0.1 s
older, the offset it gets is the creep at its own time (its time taken one frame period ahead).
(Before, without the delay, the kink at 0.1 s made the fitted kernel run up to 0.17 of a decade ahead
within 0.2 s of a change, 0.03 beyond 1 s.)

It acts on the normalised change (what the estimator, the stress field and the drift tracker see),
before them all: a held load's force and field read constant, and the rest after a long load reads
zero while the rubber recovers, so the drift tracker is not fooled by the recovery into taking it for
a change of the device. The change is taken as proportional to the strain: true to first order (the
material law and the conductivity bend at large compressions). Measured on the honest simulation
(noise-free, a 20 N load held 10 minutes, the law itself applied to the change against it applied to
the estimated force): 0.07 % of the load off after 10 minutes on the change, 0.2 % on the force (the
estimator's own non-linearity in the magnitude), and 0.03 N against 0.13 N at rest after the load's
removal: the change is the better space.

What it cannot do, said plainly: the coefficient is the rubber's (``cstomo calibrate`` fits it from
the calibration's held loads, or from a held load given apart; a calibration file carries it; else the
documented middle, 4 % per decade, is assumed: up to 2 % per decade of a held load off on a rubber at
2 or 6 %); loads before the reference (a tare taken while a previous load still recovers) are not
known to it.
"""
from __future__ import annotations

from collections import deque
from functools import cache

import numpy as np

from ...model.material import CREEP_T0
from ...settings import MAX_CREEP, TYPICAL_CREEP_PER_DECADE

#: The coefficient assumed without a calibration: the middle of the documented 2..6 % per decade,
#: the simulated board's default rubber too (one declaration: settings.py; model/material.py's CREEP_T0:
#: creep counts from this many seconds after a change of load).
DEFAULT_CREEP = TYPICAL_CREEP_PER_DECADE
#: Seconds between frames without stamps (`cstomo estimate` without `--rate`): the creep compensation
#: and the drift tracker (force/slow_states/drift.py) take it.
DEFAULT_PERIOD = 0.01
#: Time steps are rounded to this many seconds to look up their decay factors (board stamps jitter
#: by microseconds: 10 us changes a factor of the fastest mode by 3e-4 of itself, far below noise).
STEP_ROUND = 1e-5
#: Longest time step taken between two frames, in frame periods: a stamp that jumps (a stepped clock)
#: does not age the history by more; an outage ages it by that much only (a load held through it is a
#: little younger to the compensation than it is).
MAX_STEPS = 10.0
#: The frame period is the median of this many last steps (positive ones, as stamped): a change of the
#: frame rate is followed from the second frame at the new rate (one step of it clipped), a single late
#: frame or jumped stamp is not taken for one. (A running mean of 100 steps, before, took 50 s to follow
#: 100 -> 1 frames/s, clipping each step meanwhile: a held load read 0.5 % high 40 s later.)
PERIOD_STEPS = 3


def creep_problem(c) -> str:
    """Why ``c`` is no creep coefficient ('' if it is one)."""
    if isinstance(c, bool) or not isinstance(c, (int, float)) or not 0 <= c <= MAX_CREEP:
        return f"a fraction per decade, 0 <= c <= {MAX_CREEP:g} (rubbers: 0.02..0.06; 0 = off)"
    return ""


#: Modes offered to the kernel's fit: every 2/3 of a decade from 0.03 s to 1.5 days (kept: those with a
#: weight; 11 of them, as many as the former kernel's): the fit is within 0.002 of a decade of the law
#: from 0.1 s to 1e5 s, where the former one was up to 0.17 of a decade ahead within 0.2 s of a change
#: (the kink at 0.1 s cannot be made by exponentials: it is now the delay).
MODE_DECADES = 2.0 / 3.0


@cache
def creep_modes() -> tuple[np.ndarray, np.ndarray]:
    """(tau (k,) s, w (k,)): ``log10(1 + u / 0.1) ~ sum_k w_k (1 - exp(-u / tau_k))`` for ``u`` >= 0 s
    since the change's delayed copy arrived (the law at ``u + 0.1`` s after the change; module
    docstring), fitted with non-negative weights on 0 .. 1e5 s. Smooth from its start (a Bernstein
    function: a mixture of exactly such exponentials), so the sum follows it closely."""
    from scipy.optimize import nnls

    taus = CREEP_T0 * 10.0 ** np.arange(-0.5, 6.5 + 1e-9, MODE_DECADES)
    u = np.concatenate([[0.0], np.logspace(-4, 5, 2000)])
    target = np.log10(1.0 + u / CREEP_T0)
    w, _ = nnls(1.0 - np.exp(-u[:, None] / taus[None, :]), target)
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


#: A load of a calibration recording counts for the creep's fit when held this long after it was
#: applied (s): from 1 s (settled) to 5 s the strain creeps by 0.7 of a decade, 2.8 % of the load's change
#: at 4 % per decade.
HELD_FOR = 5.0
#: ... and the fit takes this many such loads at least.
MIN_HELD = 3


def fit_creep_loads(times, readings, load, starts, min_time: float = 1.0) -> tuple[float, int]:
    """(creep coefficient, loads it was fitted on) of a recording of loads held in turn.

    ``readings`` (n, 3): the uncompensated forces of frames at ``times`` (s, in time order), each on
    held load ``load`` (n,) (0, 1, ... in the order they were applied; -1: none, the load changing),
    load j applied at ``starts[j]`` (s; before the first, the tare's zero). By the law (module
    docstring, superposed in the force: the strain, and so the estimate, is positively homogeneous in
    it), the reading of a frame of load j is ``b_j + c sum_(k <= j) phi(t - starts[k]) (b_k - b_(k-1))``
    with ``b`` the loads' readings without creep (b_-1 = 0); ``c`` is fitted by least squares on the
    frames from ``min_time`` after their load was applied, ``b`` the loads' means without the fitted
    creep (three rounds: ``b`` starts at the readings' medians). Raises ValueError, the reason in one
    line, when fewer than :data:`MIN_HELD` loads are held :data:`HELD_FOR` s."""
    t, m = np.asarray(times, float), np.asarray(readings, float)
    lab, st = np.asarray(load, int), np.asarray(starts, float)
    ok = (lab >= 0) & np.isfinite(m).all(axis=1)
    last = np.full(len(st), -np.inf)
    np.maximum.at(last, lab[ok], t[ok])
    held = last - st >= HELD_FOR
    if held.sum() < MIN_HELD:
        raise ValueError(f"{int(held.sum())} of its {len(st)} loads and rests held {HELD_FOR:g} s or more "
                         f"({MIN_HELD} needed)")
    use = ok & (t - st[np.maximum(lab, 0)] >= min_time)
    t, m, lab = t[use], m[use], lab[use]
    b = np.array([np.median(m[lab == j], axis=0) if np.any(lab == j) else np.zeros(3) for j in range(len(st))])
    phi = np.log10(np.maximum(t[:, None] - st[None, :], CREEP_T0) / CREEP_T0) * (np.arange(len(st))[None, :] <= lab[:, None])
    n = np.bincount(lab, minlength=len(st))[:, None]
    c = 0.0
    for _ in range(3):
        x = phi @ np.diff(np.vstack([np.zeros((1, 3)), b]), axis=0)  # (n, 3) the creep per unit of c
        dm, dx = m - _means(m, lab, n)[lab], x - _means(x, lab, n)[lab]  # each load's own mean out (b_j)
        c = float(np.sum(dm * dx) / max(np.sum(dx * dx), 1e-300))
        b = np.where(n > 0, _means(m - c * x, lab, n), b)
    if creep_problem(c):
        raise ValueError(f"fitted creep {c:.3g} per decade: expected {creep_problem(c)}; were the loads held still?")
    return c, int(held.sum())


def _means(v: np.ndarray, lab: np.ndarray, n: np.ndarray) -> np.ndarray:
    """(loads, 3) the mean of the rows of ``v`` by load (0 for a load without rows)."""
    out = np.zeros((len(n), v.shape[1]))
    np.add.at(out, lab, v)
    return out / np.maximum(n, 1)


def creep_kernel(tau) -> np.ndarray:
    """The kernel at ``tau`` (s since a change): what :class:`CreepCompensator` removes per unit of
    change, 0 for 0.1 s, then the fitted sum (:func:`creep_modes`)."""
    taus, w = creep_modes()
    u = np.maximum(np.atleast_1d(np.asarray(tau, float)) - CREEP_T0, 0.0)
    return (1.0 - np.exp(-u[:, None] / taus)) @ w


class CreepCompensator:
    """The creep of the changes seen so far (module docstring): :attr:`offset` (n_meas,) is what
    the rubber's creep adds to the change of the next frame, for the pipeline to subtract.

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
        self._tau, self._cw, self._k = taus, self.coefficient * w, len(taus)
        k = self._k
        self._cw1 = np.append(self._cw, 0.0)  # the offset of the state below
        # the state: the delayed change low-passed by each time constant (rows 0..k-1) and the change that
        # entered last (row k, held until the next one enters), so that one product steps every low-pass
        # (:meth:`_step`); two of them, in turn (the product's output and input)
        self._state, self._next = np.zeros((k + 1, n_meas)), np.zeros((k + 1, n_meas))
        self._d = np.empty((k, n_meas))
        self.offset = np.zeros(n_meas)
        self._t: float | None = None
        self._clock = 0.0  # the frames' time as the history counts it (steps clipped)
        self._period = DEFAULT_PERIOD  # the frames' period (s): the median of the last steps
        self._recent: deque[float] = deque(maxlen=PERIOD_STEPS)
        # the changes of the last 0.1 s: (time they enter the low-passes, the change, its frozen channels)
        self._queue: deque[tuple[float, np.ndarray, np.ndarray | None]] = deque()
        self._free: list[np.ndarray] = []  # the queue's spent buffers, reused
        # when the change that entered last did, and its frozen channels
        self._t_last, self._f_last = CREEP_T0, None
        self._steps: dict[float, np.ndarray] = {}  # _step's matrices by step: frames come at one rate

    def _step(self, dt: float) -> np.ndarray:
        """``[diag(1 - a) | a]`` (k, k + 1), ``a = 1 - exp(-dt / tau)``: its product with the state is the
        low-passes ``dt`` later, ``s + a (last - s)``; dt rounded to :data:`STEP_ROUND` s (stamps
        jitter: the table hits)."""
        dt = round(dt / STEP_ROUND) * STEP_ROUND
        M = self._steps.get(dt)
        if M is None:
            if len(self._steps) > 64:  # stamps that jitter: no unbounded table
                self._steps.clear()
            a = -np.expm1(-dt / self._tau)
            M = self._steps[dt] = np.hstack([np.diag(1.0 - a), a[:, None]])
        return M

    def observe(self, y: np.ndarray, t: float | None = None, frozen: np.ndarray | None = None) -> None:
        """Take the compensated change ``y`` (n_meas,) of a frame at time ``t`` (s; None:
        :data:`DEFAULT_PERIOD` after the previous frame; a stamp that goes back counts 0 s, a jump at
        most :data:`MAX_STEPS` frame periods) into the history, except on the channels ``frozen`` (excluded: their
        history waits); :attr:`offset` becomes the creep one frame period later (for the next frame).

        A frame's change counts from its own time until the next frame's (a change of load is taken
        to happen at the frame that first shows it: never ahead of the rubber), and enters the
        low-passes 0.1 s later (the law is flat until then)."""
        step = DEFAULT_PERIOD if t is None else None if self._t is None else t - self._t
        if t is not None:  # a stepped clock: one frame's step is clipped, the next ones count from it
            self._t = t
        if step is not None and step > 0:
            self._recent.append(step)
            self._period = sorted(self._recent)[(len(self._recent) - 1) // 2]
        dt = DEFAULT_PERIOD if step is None else min(max(step, 0.0), MAX_STEPS * self._period)
        self._clock += dt
        buf = self._free.pop() if self._free else np.empty_like(self.offset)
        np.copyto(buf, y)
        self._queue.append((self._clock + CREEP_T0, buf, None if frozen is None else frozen.copy()))
        due = self._clock + self._period  # the next frame's time: its creep needs the changes until due - 0.1 s
        q, k = self._queue, self._k
        while q and q[0][0] <= due + 1e-3 * self._period:
            te, yq, fq = q.popleft()
            step = te - self._t_last
            state, new = self._state, self._next
            if step > 0:  # the last change held from its time to this one's
                self._step(step).dot(state, out=new[:k])  # (ndarray.dot: without np.dot's dispatch)
                if self._f_last is not None:
                    new[:k, self._f_last] = state[:k, self._f_last]
            else:
                new[:k] = state[:k]
            new[k] = yq
            self._state, self._next = new, state
            self._free.append(yq)
            self._t_last, self._f_last = te, fq
        self._cw1.dot(self._state, out=self.offset)
        part = due - self._t_last
        if part > max(1e-3 * self._period, STEP_ROUND / 2):  # the last change held on until due (a period that does not divide 0.1 s)
            s = self._state
            d = np.subtract(s[k], s[:k], out=self._d)
            if self._f_last is not None:
                d[:, self._f_last] = 0.0
            self.offset += (self._cw * self._step(part)[:, k]).dot(d)
