"""What the drift tracker (:class:`~.drift.DriftTracker`) learns from rest frames besides their states
(issue 26): the other states' slope against the scale (:class:`FollowSlope`), and whether the frames
before one were quiet (:class:`QuietTest`): a frame counts as rest only then, so that a small load held
still is not taken for the device; and what a rest ends: a held load's own error of its measurement of the
scale (:class:`LoadBias`, :data:`LOAD_BIAS_SIGMA`).

A small load held still passes a frame's own rest tests (1 N straight down: 97 % of its frames at 60 dB;
the best uniform change explains 75 % of its force) and its part along the contacts' and the gradient's
directions went into them, the scale following (a held 1 N read 0.75 N after 10 s). Its step is seen in
two means of the frames' non-uniform force: a fast one over :data:`QUIET_FAST` seconds and a slow one
over :data:`QUIET_SLOW` seconds of the frames that pass the tests (0.25 N apart against their noise of
0.05 N). Quiet: within :data:`QUIET_N` newtons of each other, or :data:`QUIET_SIGMAS` times the fast
mean's noise where that is more (40 dB). A load the frame tests see (the means apart by more than
:data:`QUIET_BIG` times the rest force) moves the slow mean with it, during it and :data:`QUIET_POST`
seconds after it: the rests after a task re-acquire the states the task left stale (else the 1.5 %/K
warm-up locks); so does, in a restart's first QUIET_POST seconds, a frame that reads no load by the joint fit
(:meth:`~.drift.DriftTracker.widen`: the states stale for hours). A small load held longer (1 N: from
about 15 s; 0.80 N at 21 s, 0.72 N at 45 s), or put on within QUIET_POST after a larger one, is taken
for the device as before. The verdict used is the previous frame's, not this one's: chosen by its own
noise, the frames that count as rest would bias the scale (a held 2 N: -1.3e-4 on them, +5e-5 on the
others). docs/node.md, *The zero over time*.
"""
from __future__ import annotations

import math

import numpy as np

#: The other states (the contacts', the gradient's) move with the temperature, so with the scale; under
#: load only the scale is measured (the joint fit), so there they follow it: by ``v ds``, ``ds`` the
#: scale's change in the frame and ``v`` the slope of each state against the scale, fitted on the rest
#: frames (least squares, their weight fading over :data:`FOLLOW_MEMORY` seconds of rest; 0 until the
#: scale spanned :data:`FOLLOW_SPAN` there). Without it they stood still during a task and the tracking locked at
#: 1.5 %/K (docs/node.md, *The zero over time*). All of the slope: half of it reads the 30-minute warm-up at
#: 0.8 %/K better (cstomo bench --drift: 1.03 deg against 1.08), but the states are then half stale after a
#: long task and the rests after it are refused (test_drift: the tracker locks).
FOLLOW_MEMORY = 300.0
FOLLOW_SPAN = 1e-3
QUIET_FAST, QUIET_SLOW = 0.2, 30.0
QUIET_N, QUIET_SIGMAS = 0.12, 2.5
QUIET_BIG, QUIET_POST = 1.0, 2.0
#: A held load's own measurement of the scale (the joint fit, force/estimators/scale_fit.py) is off by the model's mismatch
#: with the device for that load, along the uniform change: an error that stays while the load is held, not
#: noise that its frames average away. :class:`LoadBias` carries it as a state of its own, 1-sigma
#: LOAD_BIAS_SIGMA for each new load: a load is new after a rest, or when the force moved by more than
#: LOAD_MOVE_N newtons or LOAD_MOVE_REL of itself since its bias began. So a held load after a rest measures
#: the device's change during it, not its own mismatch (cstomo bench --drift's device, no drift, tracking on:
#: the scale had followed each task's mismatch by up to 1.2e-3, the median angle 0.99 deg against 0.82
#: untracked, now 0.81); loads without a rest between them still find the scale, each to LOAD_BIAS_SIGMA
#: (a restart under load, back-to-back loads). The 30-minute warm-up reads 1.03-1.04 deg for 1.5e-4 to 3e-3;
#: above 2e-4 back-to-back loads' sigma_n overstates their error beyond 2x (3e-4: 2.2x; 1e-3: 3.5x; these
#: with LOADED_WEIGHT per frame, before it became per 10 ms: docs/benchmark.md, issue 26's warm-up).
LOAD_BIAS_SIGMA = 1.5e-4
LOAD_MOVE_N, LOAD_MOVE_REL = 2.0, 0.1


def moved(force: list, held: list) -> bool:
    """Whether ``force`` (3 floats, N) is another load than ``held`` (its force when its bias began): further
    from it than LOAD_MOVE_N newtons or LOAD_MOVE_REL of it."""
    return math.dist(force, held) > max(LOAD_MOVE_N, LOAD_MOVE_REL * math.hypot(*held))


class QuietTest:
    """The fast and slow means of the non-uniform force and the previous frame's verdict (module docstring).
    Its means are 3 Python floats each (a step in 2 us, where numpy's small-array calls took 10)."""

    def __init__(self, sigma: float, rest_force: float) -> None:
        self.sigma, self.big = sigma, QUIET_BIG * rest_force  # the force's per-frame noise (N), a load the tests see
        self.fast, self.slow, self.quiet, self.post = [0.0] * 3, [0.0] * 3, True, 0.0
        self._dt, self._k = None, None

    def step(self, f, rest: bool, dt: float) -> bool:
        """The previous frames' verdict (True: quiet); then the non-uniform force ``f`` (3,) N of this frame
        into the means. ``rest``: the frame passes its own tests (only those move the slow mean)."""
        if dt != self._dt:  # frames come at one rate: the factors once
            af = 1.0 - math.exp(-dt / QUIET_FAST)
            bound = max(QUIET_N, QUIET_SIGMAS * self.sigma * math.sqrt(af / (2.0 - af)))
            self._dt, self._k = dt, (af, 1.0 - math.exp(-dt / QUIET_SLOW), bound * bound)
        af, aslow, bound2 = self._k
        f0, f1, f2 = f.tolist() if isinstance(f, np.ndarray) else f
        a0, a1, a2 = self.fast
        a0, a1, a2 = a0 + af * (f0 - a0), a1 + af * (f1 - a1), a2 + af * (f2 - a2)
        self.fast = [a0, a1, a2]
        s0, s1, s2 = self.slow
        d0, d1, d2 = a0 - s0, a1 - s1, a2 - s2
        verdict = self.quiet
        if d0 * d0 + d1 * d1 + d2 * d2 > self.big * self.big:  # a load the frame tests see: the slow mean follows it and its end
            self.post = QUIET_POST
        if self.post > 0.0:
            self.post -= dt
            self.slow = [a0, a1, a2]
            self.quiet = True
            return verdict
        if rest:
            s0, s1, s2 = s0 + aslow * d0, s1 + aslow * d1, s2 + aslow * d2
            self.slow = [s0, s1, s2]
            d0, d1, d2 = a0 - s0, a1 - s1, a2 - s2
        self.quiet = d0 * d0 + d1 * d1 + d2 * d2 < bound2
        return verdict


class FollowSlope:
    """Each other state's slope against the scale (:attr:`slope`, updated in place), a weighted least
    squares over the rest frames fading over :data:`FOLLOW_MEMORY` seconds; 0 until the scale spanned
    :data:`FOLLOW_SPAN`."""

    def __init__(self, m: int) -> None:
        self.slope = np.zeros(m - 1)
        self.fitted = False  # the scale spanned FOLLOW_SPAN at rest: the slope is measured
        self._fit = np.zeros((3, m))  # the weighted sums: (1, s, s^2) x (1, x_o)

    def copy(self) -> FollowSlope:
        new = FollowSlope(len(self.slope) + 1)
        new.slope[:], new._fit[:], new.fitted = self.slope, self._fit, self.fitted
        return new

    def add(self, dt: float, s: float, g: np.ndarray, count: int = 1) -> None:
        """A rest frame's other states ``g`` at the scale's change ``s``, ``dt`` s after the previous frame;
        ``count``: as many rest frames over ``dt`` (the drift tracker's update of an interval's, UPDATE_S)."""
        F = self._fit
        F *= math.exp(-dt / FOLLOW_MEMORY)
        n, s1, s2 = F[:, 0].tolist()  # the scale's sums on Python floats
        n, s1, s2 = n + count, s1 + count * s, s2 + count * s * s
        F[:, 0] = n, s1, s2
        F[0, 1:] += count * g  # (count 1: exactly the one frame's g)
        F[1, 1:] += (count * s) * g
        ss = s2 - s1 * s1 / n  # the scale's weighted spread, times n
        if ss > n * FOLLOW_SPAN ** 2:
            self.slope[:] = (F[1, 1:] - s1 * F[0, 1:] / n) / ss
            self.fitted = True


class LoadBias:
    """The held load's own error of its measurement of the scale (the model's mismatch with the device for
    that load: constant while the load is held), a state beside the tracker's: its estimate ``b``, variance
    ``p`` and covariance ``c`` with the tracker's states; a new load (the force moved by more than
    LOAD_MOVE_N or LOAD_MOVE_REL) starts a new bias of 1-sigma LOAD_BIAS_SIGMA."""

    def __init__(self, n: int) -> None:
        self.c, self.p, self.b, self.force = np.zeros(n), 0.0, 0.0, None
        self.new = False  # the latest update began a new load
        self.kx: np.ndarray | None = None  # its latest gain of the states

    def copy(self) -> LoadBias:
        new = LoadBias(len(self.c))
        new.c[:], new.p, new.b, new.force = self.c, self.p, self.b, self.force
        return new

    def rest(self) -> None:
        self.force = None

    def update(self, P: np.ndarray, F: np.ndarray, force: np.ndarray, nu: float, var: float) -> np.ndarray | None:
        """A loaded frame's measurement ``nu`` (its innovation, the bias not taken out) of the scale (state 0) of
        white variance ``var``; ``P`` the states' predicted covariance (updated in place), ``F`` the
        prediction's transition; returns the states' update (None: not finite, nothing changed)."""
        f = np.asarray(force, float).tolist()  # on Python floats: a norm of 3 numbers in 0.1 us, not 3
        self.new = self.force is None or moved(f, self.force)
        if self.new:
            self.force, self.p, self.b = f, LOAD_BIAS_SIGMA ** 2, 0.0
            self.c[:] = 0.0
        else:
            self.c = F.dot(self.c)
        h = P[:, 0] + self.c
        hb = float(self.c[0]) + self.p
        S = float(h[0]) + hb + var
        nu = nu - self.b
        kx, kb = h / S, hb / S
        delta = kx * nu
        if not (math.isfinite(sum(delta.tolist())) and math.isfinite(kb * nu)):
            return None
        P -= kx[:, None] * h  # the outer product (np.multiply.outer's dispatch costs more than it)
        self.c -= kx * hb
        self.p -= kb * hb
        self.kx = kx  # the states' gain (the tracker's other biases' covariance with them follows it)
        self.b += kb * nu
        return delta


class Interval:
    """The frames since the drift tracker's latest update (:data:`~.drift.UPDATE_S`), summed: one kind of frame
    each (all at rest or all loaded with one held load, :meth:`~.drift.DriftTracker.observe`), so that one update
    with their sums is the updates they would have made one by one of states that do not move between them (a
    linear-Gaussian measurement of static states, a held load's bias shared: the information adds).

    ``n`` frames over ``dt`` seconds; the prediction's factors over them: ``tr`` the scale's step per unit of the
    rate (each frame's period times the rate's fading before it), ``fade`` the rate's fading, ``da`` the scale's
    change at its rate over the loaded frames (the other states follow it, :data:`~.drift.FOLLOW_SIGMA`). The
    joint fit's scale measurements: ``info`` (sum of weight / variance) and ``vec`` (sum of weight x innovation /
    variance). At rest: ``b`` the frames' information vectors summed, ``o`` their formation offsets of the scale
    summed (each frame's prediction over the scale it was formed with). Loaded: ``force`` the held load's (its
    bias's reference), the other states' parts (:meth:`~cstomo_sensor.force.estimators.scale_fit.JointScale.others_part`)
    summed unweighted (``H``, ``hb``; ``Hda`` the information times each frame's ``da`` so far: the follow within
    the interval), their count ``k``, their weights ``w`` and the check's time ``kdt`` summed."""

    def __init__(self, n_states: int, m: int) -> None:
        self.b = np.zeros(n_states)
        self.H = np.zeros((m - 1, m - 1))
        self.hb = np.zeros(m - 1)
        self.Hda = np.zeros((m - 1, m - 1))
        self.n_b = self.k_h = True  # the arrays hold sums (clear zeroes them only then)
        self.clear()

    def clear(self) -> None:
        self.n, self.dt, self.tr, self.fade, self.da = 0, 0.0, 0.0, 1.0, 0.0
        self.rest, self.joint, self.force = False, True, None
        self.info = self.vec = self.o = 0.0
        self.k, self.w, self.kdt = 0, 0.0, 0.0
        if self.n_b:
            self.b.fill(0.0)
            self.n_b = False
        if self.k_h:
            self.H.fill(0.0)
            self.hb.fill(0.0)
            self.Hda.fill(0.0)
            self.k_h = False
