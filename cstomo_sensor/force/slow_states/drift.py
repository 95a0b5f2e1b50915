"""The zero that holds: tracking the device's slow change after its tare (docs/physics.md#device-changes).

After a tare the device keeps changing (it warms, its contacts and drive drift): the mean change and the
drive scale every voltage alike, ``V = s (V_ref + dV_load)`` (1 % reads as 18 N at zero load), a
gradient across the block reads as a lateral load. :class:`DriftTracker` estimates ``s``, its rate,
and the states of a few more directions (the contacts' impedance changing alike and linearly along x,
y, z; the resistivity's gradient, :func:`~cstomo_sensor.force.estimators.scale_fit.gradient_directions`); the pipeline removes them all:
``y = (V / s - V_ref) / y_scale - g . d``.

What separates these slow changes from a load (one frame alone only in part: the normalised change
of a uniform scaling, ``r = V_ref / y_scale``, has a cosine of 0.4..0.7 with a socket load's): the
frame's **shape at rest** (:data:`REST_BOUND`, :data:`REST_FORCE_SIGMAS`, after quiet frames,
:mod:`.drift_parts`; a rest frame measures every state), **every frame** with the ``model`` estimator
(the force and the scale fitted jointly, :class:`~cstomo_sensor.force.estimators.scale_fit.JointScale`,
the tracker's mean and covariance the scale's prior; the other states follow the scale under load by
their slope at rest, :class:`~.drift_parts.FollowSlope`), and **time** (random
walks of :data:`RATE`, the scale's rate one of :data:`ACCEL`: loads move in tenths of seconds, the
device in minutes). docs/node.md, *The zero over time* and *Following the device under load*, says
how, what it measures and what it cannot separate: a change none of the directions describe (single
contacts, a non-linear gradient: it stays in the change and raises the consistency statistic), a
held load whose model misfit lies along the uniform change, a change of rate during a long load.
"""
from __future__ import annotations

import math

import numpy as np

from ..estimators.linalg import solve_small
from .creep import DEFAULT_PERIOD
from .drift_parts import (  # noqa: F401 (the constants: drift's words)
    FOLLOW_MEMORY,
    FOLLOW_SPAN,
    LOAD_BIAS_SIGMA,
    QUIET_POST,
    FollowSlope,
    Interval,
    LoadBias,
    QuietTest,
    moved,
)

#: Random walk of the scale (and of the gradient and contact states), per square-root second: what
#: the device does beyond a steady rate (the drive current's drift, a contact's). Small, so that a
#: load a frame takes for rest is not taken for a change of the device: at 40 dB a 10 N load pressing
#: straight down looks like a 0.5 % uniform change within the noise; at 2e-4 the scale took it
#: within a tenth of a second (held-out loads at 40 dB: 16.6 deg with tracking, 4.7 without; now 4.7).
RATE = 2e-5
#: Random walk of the scale's rate of change (per second), per square-root second: the device warms
#: and cools over minutes (15 K in 30 minutes at 0.8 %/K: a rate of 2e-4/s falling to 1e-5/s), so
#: during a load, when nothing is measured, the scale goes on changing at the rate of the rests
#: (cstomo bench --drift: the warm-up's angle error 2.77 -> 2.03 deg; a rate of the gradient too gains
#: nothing). 1e-5 follows a ramp's end more slowly (+-10 % in 5 minutes: 0.2 N), 3e-5 costs the
#: warm-up's angle (2.09 deg).
ACCEL = 2e-5
#: The scale's rate is remembered this many seconds without a measurement (it returns to 0 with this
#: time constant): a task keeps much of it, a load held 10 minutes does not extrapolate a rate known
#: from a few rest frames (a 20 N load held from 1 s after the tare: 8 % off after 10 minutes without
#: it, 0.9 % at 60 s, 0.5 % at 30 s; the warm-up's errors are the same at 30 and 60 s).
RATE_MEMORY = 30.0
#: ... and that slope is known only so well: while no rest measures them, each other state moves on by
#: ``e a``, ``a`` the scale's change at its tracked rate since the last rest frame and ``e`` the slope's own
#: error, a state of the tracker of 1-sigma FOLLOW_SIGMA from each rest frame on (a slope anywhere in section
#: 9's 0..30 % has a 1-sigma of 0.09 about its middle): unmeasured, each state's variance grows by
#: ``(FOLLOW_SIGMA a)^2``, so the forces' sigma says what a long task leaves unmeasured (the diagnostics warn
#: when that reads more than :data:`~.coordinator.UNMEASURED_N` newtons, 1-sigma, at zero load); measured by loaded
#: frames (:data:`LOADED_OTHER_N`), the slope is what they learn over the task, not a state free to move
#: with each frame: as a random walk of the same variance the gradients followed each dozen frames' noise and
#: each load's mismatch (device_b's uniform 2 % loaded warm-up, last minute: 1.66 deg / 2.09 %, now 1.21 /
#: 1.32, against 1.03 / 1.15 unwarmed). A restart's jump of the scale is not counted (:meth:`widen` covers
#: it: a block off for hours has no gradient). Before a rest measured the slope (:class:`~.drift_parts.FollowSlope`,
#: 0 until then), its 1-sigma is section 9's range: :data:`RESTART_GRADIENT` and :data:`RESTART_CONTACT` (a
#: loaded warm-up from the tare, no rest: the loaded frames then measure them).
FOLLOW_SIGMA = 0.1
#: A loaded frame's own measurement of the scale
# (:class:`~cstomo_sensor.force.estimators.scale_fit.JointScale`, the load marginalised) counts
#: as this fraction of one independent measurement: the frames of one held load share the model's
#: mismatch with the device (not white noise), so their measurements do not average like noise.
LOADED_WEIGHT = 0.005
#: ... and a rest frame's (the rest test's frame: no load the shape shows; a small load held still
#: passes it at 60 dB, 1-2 N straight down, and its misfit by the model along the uniform change would
#: go into the scale as fast as the rest frames' weight lets it).
REST_WEIGHT = 0.1
#: A restart from a saved tare (:meth:`DriftTracker.widen`): the scale's 1-sigma grows with the tare's
#: age as ``RESTART_SIGMA * sqrt(age / 1 h)`` within [RESTART_MIN, RESTART_MAX] (a morning 5 K colder
#: than the tare: about -4 %); its rate's as RESTART_RATE (0.8 %/K by 15 K in 30 min: 7e-5/s); each
#: other state's by what reads as RESTART_OTHER_N newtons (after hours off, no gradient).
RESTART_SIGMA, RESTART_MIN, RESTART_MAX = 0.015, 0.003, 0.05
RESTART_RATE = 1e-4
RESTART_OTHER_N = 0.15
#: ... and at least what section 9's hours off can do to the other states (docs/physics.md#device-changes):
#: each resistivity gradient RESTART_GRADIENT of the scale's 1-sigma (a gradient of up to 30 % across the
#: block: +-0.75 % from its middle at a 2.5 % change); each contact state RESTART_CONTACT of it (contacts
#: -0.5..-1.5 %/K against the rubber's 0.8 %/K: 1.9 x the scale's change), and, in quadrature, their own
#: drift of up to RESTART_CONTACT_DRIFT over RESTART_CONTACT_DAYS days, growing as the square root of the
#: tare's age. Before (0.15 N each): a restart after warming with a 30 % gradient read a phantom lateral
#: force of 3-11 N for ever (issue 34).
#: Whatever the age: the scale's change they follow is taken as at least RESTART_CHANGE (a tare saved minutes
#: before a restart may follow a fast warm-up; the scale itself is measured by every frame, loaded or not,
#: the others under load only weakly, docs/physics.md#device-changes).
RESTART_GRADIENT = 0.3
RESTART_CHANGE = 0.025
RESTART_CONTACT = 1.9
RESTART_CONTACT_DRIFT, RESTART_CONTACT_DAYS = 0.2, 3.0
#: A loaded frame measures the other states too (:meth:`~cstomo_sensor.force.estimators.scale_fit.JointScale.others_part`: the load and the
#: scale profiled out; their Cramer-Rao bound in docs/physics.md#device-changes), counted as a loaded frame's
#: scale (:data:`LOADED_WEIGHT` per 10 ms). The model's mismatch with the device for a load reaches into
#: them as an error that stays while the load is held (device_a, no change: the x and y gradients read
#: -0.15 and -0.6 N at zero load under 12-30 N loads, against a Cramer-Rao bound of 0.28 N per frame): it
#: is a state of its own for each load (another load than its own, :func:`~.drift_parts.moved`: a frame counted as
#: rest within a held load does not end it; before, it did, and a 2 N load held from a restart read 0.53 N off
#: at 1-3 s against 0.45), 1-sigma what reads as
#: LOADED_BIAS_N + LOADED_OTHER_REL |F| newtons at zero load (under 4-12 N: 0.04-0.08 N), so a held load
#: counts as one measurement at most and loads with different mismatches average it; a frame without load
#: (a phantom of the states themselves) has next to none. Only while a state is less certain than
#: LOADED_OTHER_N (a restart, a long task): else the rests measure them, as before.
LOADED_OTHER_N, LOADED_BIAS_N, LOADED_OTHER_REL = 0.3, 0.05, 0.05
#: ... and, while they are certain, every CHECK_EVERY-th unrested frame checks them: the frame's measurement
#: of the other states against their estimate, in units of its own noise, the held load's mismatch and their
#: covariance (chi-square per state, averaged over CHECK_S seconds). Beyond CHECK_BOUND the states are wider
#: than their covariance says (a restart from a recent tare after a fast change; a change none of the rests
#: saw): each widens by its innovation and the loaded frames measure it again. Before: the phantom lateral
#: force of a gradient unmeasured at a restart kept every frame from counting as rest, for ever (issue 34).
CHECK_EVERY, CHECK_S, CHECK_BOUND = 8, 1.0, 1.4
#: A loaded frame's measurement of the other states counts as OTHERS_WEIGHT of one per 10 ms: the part its
#: frames share (the held load's mismatch) is their bias state, so the rest of it is the frame's noise
#: (0.1: the restart loaded from the first frame 0.98 deg / 1.71 % from 5 s; 1: 0.95 / 1.67).
OTHERS_WEIGHT = 1.0
#: Bound of a rest frame's whitened residual, per channel in use: the noise gives 1 (its chi-square
#: spread over 208 channels is 0.1); a change beyond the directions' reach (the voltages' noise grows
#: as the scale falls, a device's change is not exactly the model's) takes the rest. A 1 N socket
#: load gives several times the bound.
REST_BOUND = 1.5
#: A rest frame also reads no force once the best uniform change is taken out: below this many times
#: the rms of the force's per-frame noise (60 dB: 0.29 N; 40 dB: 1.9 N), and below :data:`REST_FORCE_MIN`
#: whatever the noise. The residual bound alone is in units of the noise: on a 40 dB board a 5-10 N
#: load passes it, and its sideways part went into the gradient (angle errors of 50 deg).
REST_FORCE_SIGMAS = 2.5
REST_FORCE_MIN = 0.5
#: The states' prediction and updates run once per UPDATE_S seconds of frames (by their stamps: every 4th frame at
#: 100 frames/s, every 40th at 1000, every frame at 25 frames/s and fewer), with every frame's measurements summed
#: (issue 36: the slow states move over seconds). Every frame: the rest and quiet tests, the scale's step at its rate
#: (the next frame is formed with it), the joint fit's measurement of the scale (its information and its
#: information-weighted innovation summed), a rest frame's information vector, a loaded frame's measurement of the
#: other states (their information and vector summed), and its force corrected with the states as they are and the
#: scale its interval's measurements so far make (:meth:`DriftTracker._peek`). An update: the prediction over the
#: interval, then one update with the sums: for states that do not move within it (the scale by ``RATE
#: sqrt(UPDATE_S)``, 4e-6 in 40 ms) and a held load's bias shared by its frames, the updates the frames would have
#: made one by one (a linear-Gaussian measurement: the information adds). The frames summed are of one kind (all at
#: rest, or all loaded with one held load): another kind updates with them first. Every frame as before: without a
#: joint fit (the linear estimator), in a restart's first seconds (:meth:`DriftTracker.widen`), with a controller's
#: expected load (``now``), a loaded frame that measures the other states (its own measurement corrects its own
#: force) and, by default, every loaded frame (:data:`LOADED_EVERY_FRAME`). docs/node.md, *The zero over time*.
UPDATE_S = 0.04
#: ... and the loaded frames every frame as before (True): summed per interval (False: the scale's measurements with
#: the held load's bias summed, the mechanism of :class:`~.drift_parts.Interval`), the robot bench's loaded warm-up on
#: device_b read worse over 12 noise seeds, paired (1.29 deg / 1.68 % against 1.23 / 1.47; its unwarmed one and
#: device_a's within their paired standard error): docs/benchmark.md, *The slow states once per interval*.
LOADED_EVERY_FRAME = True


class DriftTracker:
    """The device's slow change since its tare (module docstring): the uniform scale ``s`` of its
    voltages, its ``rate`` (per second), and the states of the other directions (``gradient``, (k,):
    the stream gives the contacts' four and the resistivity gradient's three, relative change per
    half extent). ``r`` (n_meas,): the normalised change of a uniform scaling by 1 + 1 (``V_ref /
    y_scale``); ``gradients`` (k, n_meas) or None: the other directions (the model's contact
    directions, :func:`~cstomo_sensor.force.estimators.scale_fit.gradient_directions`; None: the scale alone); ``noise`` (n_meas,): the
    per-channel noise std of a change (y units); ``keep`` (n_meas,) bool: the channels in use;
    ``force_map`` (3, n_meas) or None: the estimator's linear map from a change to a force (N), for
    the rest frames' force bound (None: the residual bound alone)."""

    def __init__(self, r: np.ndarray, gradients: np.ndarray | None, noise: np.ndarray, keep: np.ndarray,
                 force_map: np.ndarray | None = None, contacts: int = 0) -> None:
        self._args = (r, gradients, noise, keep, force_map)
        self.contacts = int(contacts)  # the first this many other states are the contacts' (widen)
        # the last this many other states are learned (force/slow_states/learned.py): each one's restart per scale
        self.learned = np.zeros(0)
        # each other state's slope against the scale before a rest measured it: section 9's range (FOLLOW_SIGMA)
        self._unfitted2 = np.full(0 if gradients is None else len(gradients), RESTART_GRADIENT ** 2)
        w = np.where(keep, 1.0 / np.asarray(noise, float), 0.0)
        D = np.atleast_2d(np.asarray(r, float))
        if gradients is not None:
            D = np.vstack([D, gradients])
        D = D * keep
        Dw = D * w
        self.m = m = len(D)  # measured states: the scale, the gradient; then the scale's rate
        # ... then each other state's slope against the scale since the latest rest (FOLLOW_SIGMA): not measured
        # by a frame, it carries what they follow unmeasured, so that loaded frames measure it over time
        self.n = n = m + 1 + (m - 1 if m > 1 else 0)
        self._D, self._w, self._Dw = D, w, Dw
        self._N = np.zeros((n, n))
        self._N[:m, :m] = Dw @ Dw.T
        self._Dwm = np.ascontiguousarray(Dw)  # observe's product: the measured states' rows only (the rest of b stays 0)
        self._rest = REST_BOUND * float(np.count_nonzero(keep))
        self._W = None
        if force_map is not None:  # the force of a change, of a uniform change, and its noise
            W = np.asarray(force_map, float) * keep
            sigma = math.sqrt(float(np.sum((W * np.where(keep, noise, 0.0)) ** 2)))
            self._W, self._Wr = W, W @ D[0]
            self._Wrl = self._Wr.tolist()  # observe's rest force on Python floats
            self._Wo = W @ D[1:].T  # (3, m - 1): the force of each other state (unmeasured_n)
            self._other_n = np.maximum(np.linalg.norm(self._Wo, axis=0), 1e-12)  # its norm: N per unit
            self._floor2 = (LOADED_OTHER_N / self._other_n) ** 2  # the loaded frames' floor (LOADED_OTHER_N)
            self._floor2l = self._floor2.tolist()
            self.rest_force = max(REST_FORCE_MIN, REST_FORCE_SIGMAS * sigma)
            self._quiet = QuietTest(sigma, self.rest_force)
        self._N00, self._N0 = float(self._N[0, 0]), np.ascontiguousarray(self._N[:, 0])
        self._N_others = self._N.copy()  # the information of the states other than the scale
        self._N_others[0, :] = self._N_others[:, 0] = 0.0
        self._tot = np.zeros(n)
        self._Dg = np.ascontiguousarray(D[1:])  # the gradient's directions: its offset
        self._yw = np.empty_like(w)
        self._b = np.zeros(n)
        self._bm, self._tot_o = self._b[:m], self._tot[1:m]  # views of observe's work arrays
        self._eye = np.eye(n)
        self._q = np.array([RATE * RATE] * m + [ACCEL * ACCEL] + [0.0] * (n - m - 1))
        self._dt, self._a = -1.0, 1.0  # observe()'s frame period and the rate's fading over it
        # the prediction's factors of the latest update (UPDATE_S): the scale's step per unit rate, the rate's fading,
        # the interval and its random walks
        self._Ftr, self._Ffade, self._dt_q, self._qdt = -1.0, -1.0, -1.0, self._q
        self._F = np.eye(n)  # the prediction: the scale by its rate; unrested, the other states by their slope
        self._FT = self._F.T
        self._FP = np.empty((n, n))  # observe's work arrays: F Pa, then the prediction F Pa F^T (P within a frame)
        self._Ppred = np.empty((n, n))
        self._Ppred_diag = self._Ppred.reshape(-1)[::n + 1]
        self._unfitted2[self.contacts_block] = RESTART_CONTACT ** 2
        # ... its entries of the slopes (their step each frame): F[i, m + i], i = 1..m-1, as one strided view
        self._Fs = self._F.reshape(-1)[m + n + 1::n + 1][:m - 1]
        self._Fda = 0.0  # ... their value now
        self.scale = 1.0
        self.rate = 0.0  # the scale's relative change per second
        self.gradient = np.zeros(m - 1)
        self.offset = np.zeros_like(w)  # the gradient's change: subtracted from the frame's change
        self._Pa = np.zeros((n, n))  # the covariance of every state (P: the measured ones and the rate)
        self.rest_frames = 0  # frames measured as at rest (all time)
        self.force_step: np.ndarray | None = None  # observe()'s joint force step (N) of the latest frame
        self._follow = FollowSlope(m)
        self.follow = self._follow.slope  # each other state's slope against the scale (force/slow_states/drift_parts.py)
        self._slope = np.zeros(n - m - 1)  # the slopes' estimate beyond follow's
        self._reset_slopes()
        self._bias = LoadBias(n)  # the held load's error of its measurement of the scale (force/slow_states/drift_parts.py)
        self._obias: list | None = None  # ... and of the other states (_loaded_others)
        self._check, self._frames, self._wanted = 0.0, 0, False  # the other states' check (CHECK_EVERY)
        self._unmeasured = 0.0  # the scale's change at its rate since the latest rest frame (FOLLOW_SIGMA)
        self._t_rest: float | None = None  # the latest rest frame's time (since_rest)
        self._t: float | None = None
        self._restarted = 0.0  # seconds left of a restart's re-acquisition at rest (widen)
        self._acc = Interval(n, m)  # the frames since the latest update, summed (UPDATE_S)
        self._scale_upd = 1.0  # the scale after the latest update (the other states follow it from there)
        self._wanted_for: np.ndarray | None = None  # the covariance others_wanted judged

    def rebuilt(self, *, keep: np.ndarray | None = None, noise: np.ndarray | None = None,
                force_map: np.ndarray | None = None) -> DriftTracker:
        """The same tracker, its state kept, over the channels ``keep`` or for a change's per-channel
        noise ``noise`` (y units), with the estimator's ``force_map`` (None: each as it was). The frames summed
        since the latest update update this tracker first (their information is in its weights)."""
        self.flush()
        r, gradients, noise0, keep0, map0 = self._args
        new = DriftTracker(r, gradients, noise0 if noise is None else noise, keep0 if keep is None else keep,
                           map0 if force_map is None else force_map, self.contacts)
        new.learned = self.learned
        new.scale, new.rate, new.rest_frames, new._t = self.scale, self.rate, self.rest_frames, self._t
        new._scale_upd = self.scale
        new._Pa, new._slope = self._Pa.copy(), self._slope.copy()
        new._set_gradient(self.gradient)
        new._follow = self._follow.copy()
        new.follow = new._follow.slope
        new._bias = self._bias.copy()
        new._obias = None if self._obias is None else [a.copy() for a in self._obias]
        new._unmeasured, new._t_rest, new._restarted = self._unmeasured, self._t_rest, self._restarted
        if self._W is not None and new._W is not None:  # the quiet test's means and verdict (its noise the new one's)
            q, o = new._quiet, self._quiet
            q.fast, q.slow, q.quiet, q.post = list(o.fast), list(o.slow), o.quiet, o.post
        return new

    def with_directions(self, rows: np.ndarray, per_scale: np.ndarray, sigma: float) -> DriftTracker:
        """The same tracker, its state kept, with ``rows`` (k, n_meas) more directions (the device's own,
        force/slow_states/learned.py; ``per_scale``: each one's restart 1-sigma per unit of the scale's, :meth:`widen`),
        their states 0 of 1-sigma ``sigma`` (the next rest frames measure them); the frames summed since the latest
        update update this tracker first."""
        self.flush()
        r, gradients, noise, keep, fmap = self._args
        rows = np.atleast_2d(np.asarray(rows, float))
        k = len(rows)
        new = DriftTracker(r, rows if gradients is None else np.vstack([gradients, rows]), noise, keep, fmap,
                           self.contacts)
        new.learned = np.append(self.learned, np.asarray(per_scale, float))
        m, m1 = self.m, new.m

        def pad(a, axis):  # zeros for the new states, inserted before the rate (the last state)
            return np.insert(a, [m] * k, 0.0, axis=axis)

        P = pad(pad(self.P, 0), 1)
        P[m:m1, m:m1] = np.eye(k) * sigma * sigma
        new.P, new.scale, new.rate, new.rest_frames, new._t = P, self.scale, self.rate, self.rest_frames, self._t
        new._scale_upd = self.scale
        new._set_gradient(np.append(self.gradient, np.zeros(k)))
        new._follow._fit[:, :m] = self._follow._fit
        new._follow.slope[:m - 1] = self._follow.slope
        new._follow.fitted = self._follow.fitted
        new.follow = new._follow.slope
        new._reset_slopes()  # (a rest frame's, as the learner's frames are) by the copied fit's 1-sigma
        new._bias = self._bias.copy()
        new._bias.c = np.zeros(new.n)  # the states' (padded as P), then the rate's; the slopes' 0 as after a rest
        new._bias.c[:m1] = np.append(self._bias.c[:m], np.zeros(k))
        new._bias.c[m1] = self._bias.c[m]
        new._unmeasured, new._t_rest, new._restarted = self._unmeasured, self._t_rest, self._restarted
        if self._W is not None and new._W is not None:
            q, o = new._quiet, self._quiet
            q.fast, q.slow, q.quiet, q.post = list(o.fast), list(o.slow), o.quiet, o.post
        return new

    # the named blocks of the states (positions counted here only): the other states (:attr:`gradient`, the
    # directions after the scale) are the model's contacts', then the resistivity's gradients, then the device's
    # own (force/slow_states/learned.py); the full state vector is the scale, the other states, the scale's rate, then the
    # other states' slopes against the scale

    @property
    def contacts_block(self) -> slice:
        """The contacts' states: a slice of :attr:`gradient` (the other states)."""
        return slice(0, min(self.contacts, self.m - 1))

    @property
    def gradients_block(self) -> slice:
        """The resistivity gradients' states: a slice of :attr:`gradient` (the other states)."""
        return slice(self.contacts_block.stop, self.learned_block.start)

    @property
    def learned_block(self) -> slice:
        """The device's own directions' states (force/slow_states/learned.py): a slice of :attr:`gradient` (the other
        states)."""
        k = self.m - 1
        return slice(k - min(len(self.learned), k - self.contacts_block.stop), k)

    @property
    def slopes_block(self) -> slice:
        """The other states' slopes against the scale since the latest rest (:data:`FOLLOW_SIGMA`): a slice of
        the full state vector (its covariance :attr:`_Pa`; empty without other states)."""
        return slice(self.m + 1, self.n)

    @property
    def state_directions(self) -> np.ndarray:
        """(m, n_meas): each measured state's direction in the voltages (the masked channels' entries zero)."""
        return self._D

    @property
    def weights(self) -> np.ndarray:
        """(n_meas,): each channel's weight, 1 / its noise (0: masked)."""
        return self._w

    @property
    def whitened_directions(self) -> np.ndarray:
        """(m, n_meas): :attr:`state_directions` times :attr:`weights`."""
        return self._Dw

    @property
    def force_noise(self) -> float | None:
        """The force's per-frame noise at zero load (N) the rest test judges by; None without a force map."""
        return None if self._W is None else self._quiet.sigma

    @property
    def frame_period(self) -> float:
        """The frame period (s) of the latest :meth:`observe` (-1 before the first)."""
        return self._dt

    @property
    def P(self) -> np.ndarray:
        """(m + 1, m + 1): the covariance of the measured states (the scale, the other states) and the scale's
        rate (the slopes' own: not here)."""
        return self._Pa[:self.m + 1, :self.m + 1]

    @P.setter
    def P(self, value: np.ndarray) -> None:
        self._Pa = self._Pa.copy()
        self._Pa[:self.m + 1, :self.m + 1] = value

    def _reset_slopes(self) -> None:
        """A rest measured the other states: what they follow from here is their slope against the scale, known
        to FOLLOW_SIGMA once rests fitted it (force/slow_states/drift_parts.py FollowSlope), else to section 9's range
        (RESTART_GRADIENT, RESTART_CONTACT), and uncorrelated with the rest."""
        sl = self.slopes_block
        if sl.start == sl.stop:
            return
        P = self._Pa
        P[sl, :] = 0.0
        P[:, sl] = 0.0
        P.reshape(-1)[sl.start * (self.n + 1)::self.n + 1] = (FOLLOW_SIGMA * FOLLOW_SIGMA if self._follow.fitted
                                                            else self._unfitted2)
        self._slope[:] = 0.0

    @property
    def change(self) -> float:
        """The tracked relative change of the voltages since the tare (``s - 1``)."""
        return self.scale - 1.0

    def _set_gradient(self, g: np.ndarray) -> None:
        self.gradient = np.asarray(g, float)
        if self.m > 1:
            self.gradient.dot(self._Dg, out=self.offset)

    def observe(self, y: np.ndarray, t: float | None = None, joint: tuple | None = None, now: bool = False) -> bool:
        """Update the state with the normalised change ``y`` (n_meas,) of a frame at time ``t`` (s; None:
        :data:`DEFAULT_PERIOD` after the previous frame), formed with the current state; returns True
        if the frame was taken as at rest. ``joint``: the frame's
        :meth:`~cstomo_sensor.force.estimators.scale_fit.JointScale.measure` (None: the
        linear estimator, no joint fit: a loaded frame measures nothing); then :attr:`force_step` is
        the frame's force step (N) for the scale as updated (None without it). The states' prediction and
        updates run once per :data:`UPDATE_S` of frames, with every frame's measurements summed; ``now``: on
        this frame (a controller's expected load), as without a joint fit and in a restart's first seconds."""
        dt = DEFAULT_PERIOD if t is None or self._t is None else min(max(t - self._t, 0.0), 1.0)
        if t is not None:  # a stepped clock: one frame's step is clipped, the next ones count from it
            self._t = t
        m = self.m
        if dt != self._dt:  # frames come at one rate: the rate's fading once
            self._dt, self._a = dt, math.exp(-dt / RATE_MEMORY)
        # (the per-frame path below uses ndarray.dot, work arrays and Python floats for 3-vectors: numpy's
        # dispatch of np.dot and np.multiply.outer costs more than their arithmetic)
        yw = np.multiply(y, self._w, out=self._yw)
        b = self._b  # its rows of the measured states; the slopes' stay 0
        self._Dwm.dot(yw, out=self._bm)
        # at rest when the scale alone explains the frame (the gradient's current part is already
        # taken out): a lateral load looks like a gradient and must never be taken for one
        b0 = float(b[0])
        best = b0 / self._N00  # the uniform change that explains the most of the frame
        rest = float(yw.dot(yw)) - b0 * best < self._rest
        if self._W is not None:
            (f0, f1, f2), (r0, r1, r2) = self._W.dot(y).tolist(), self._Wrl
            f = [f0 - r0 * best, f1 - r1 * best, f2 - r2 * best]  # 3 Python floats: the quiet test's too
            rest = rest and math.hypot(*f) < self.rest_force
            # ... and, with the joint fit, after quiet frames (force/slow_states/drift_parts.py); the linear estimator
            # measures the scale at rest only: not quieted
            quiet = self._quiet.step(f, rest, dt)
            if self._restarted > 0.0:  # a restart's first seconds: a frame that reads no load re-anchors the quiet test
                self._restarted -= dt
                now = True
                if rest and joint is not None and math.hypot(*joint[4]) < self.rest_force:
                    q = self._quiet
                    q.slow = list(q.fast)
                    q.quiet = quiet = True
            rest = rest and (quiet or joint is None)
        acc = self._acc
        part = joint[5] if joint is not None and len(joint) > 5 else None
        # a loaded frame that measures the other states (they are wanted, or checked) updates them at once: its own
        # measurement corrects its own force (V, the force's step per unit of each), as a joint fit of the force and
        # the states (summed for an interval, the frames between updates went without it: the robot bench's loaded
        # warm-up on the unwarmed device_a and device_b read 0.09 / 0.06 deg worse over 6 noise seeds)
        now = now or joint is None or UPDATE_S <= 0.0 or (not rest and (part is not None or LOADED_EVERY_FRAME))
        s_form = self.scale  # the scale the frame was formed with
        # the frames summed are of one kind (Interval): a frame of another kind (rest or loaded, another held
        # load, no joint fit) has them update the states first, as they would have one by one before it; this
        # frame's measurements then count from the state it was formed with (shift: the other states' change)
        shift = None
        if acc.n and (now or rest != acc.rest or not acc.joint
                      or (not rest and acc.force is not None and moved(joint[4].tolist(), acc.force))):
            shift = np.array(self._update()[1:m])
            if rest and m > 1:
                b -= self._N[:, 1:m].dot(shift)
        step = self.rate * dt
        self.rate *= self._a
        self.scale *= 1.0 + step  # predicted: the scale moves on at its rate (the prediction's mean, every frame)
        o = self.scale / s_form - 1.0  # the frame's prediction over the scale it was formed with
        acc.n += 1
        acc.dt += dt
        acc.tr += dt * acc.fade
        acc.fade *= self._a
        acc.rest, acc.joint = rest, joint is not None
        if rest:
            self.rest_frames += 1
            self._unmeasured, self._t_rest = 0.0, self._t
            acc.b += b  # at rest the other states are measured with their full directions: the information vectors summed
            acc.n_b = True
            acc.o += o
        elif m > 1:  # unmeasured, the other states follow the scale by their slope (FOLLOW_SIGMA)
            da = abs(step)
            self._unmeasured += da
            acc.da += da
        if joint is not None:
            # every frame, at rest or loaded: the scale measured with the frame's load marginalised
            # (JointScale, force/estimators/scale_fit.py), so that a load is never taken for the device; a loaded frame counts as
            # LOADED_WEIGHT of a measurement per DEFAULT_PERIOD (the model's mismatch with a load is not white noise: the
            # same held load reads the same at 10 and 100 frames/s), a rest frame as REST_WEIGHT
            z, var = joint[0], joint[1]
            w = REST_WEIGHT if rest else LOADED_WEIGHT * max(dt, 1e-4) / DEFAULT_PERIOD
            nu = z - o
            if var > 0.0 and math.isfinite(nu) and math.isfinite(var):
                acc.info += w / var
                acc.vec += w * nu / var
            if not rest:
                if acc.force is None:  # the held load's bias: the one in effect if this is its load, else a new one's
                    f, bf = joint[4].tolist(), self._bias.force
                    acc.force = bf if bf is not None and not moved(f, bf) else f
                if part is not None and m > 1 and math.isfinite(sum(part[1].tolist())):
                    Ho, bo = part[0], part[1]
                    acc.H += Ho
                    acc.hb += bo if shift is None else bo - Ho.dot(shift)
                    if acc.da:
                        acc.Hda += Ho * acc.da
                    acc.k += 1
                    acc.k_h = True
                    acc.w += OTHERS_WEIGHT * max(dt, 1e-4) / DEFAULT_PERIOD
                    acc.kdt += CHECK_EVERY * dt
        if now or acc.dt >= UPDATE_S - 0.5 * dt:
            d = self._update()
            if joint is not None:  # the force given the scale (and the others, when measured) now known
                self._force_step(joint, part, o + d[0], d[1:m] if shift is None else shift + d[1:m])
        elif joint is not None:  # between updates: the frame's own step and the scale its interval's frames measured
            self._force_step(joint, part, o + self._peek(), shift)
        else:
            self.force_step = None
        return rest

    def flush(self) -> None:
        """The frames summed since the latest update (:data:`UPDATE_S`), if any, update the states now."""
        if self._acc.n:
            self._update()

    def _peek(self) -> float:
        """The scale's change that the joint fit's measurements of the interval's frames so far (this one's included)
        make, as its update would (the scale alone, on Python floats): a frame between updates is corrected with
        its own measurement and its interval's, as frame by frame (the update makes them the states)."""
        acc = self._acc
        if not acc.info > 0.0:
            return 0.0
        m, Pa, tr = self.m, self._Pa, acc.tr
        P00 = float(Pa[0, 0]) + 2.0 * tr * float(Pa[0, m]) + tr * tr * float(Pa[m, m]) + float(self._q[0]) * acc.dt
        nu = acc.vec / acc.info
        if acc.rest:
            return P00 / (P00 + 1.0 / acc.info) * nu
        bias = self._bias  # the held load's bias: the one in effect, or a new one's (observe's acc.force)
        c0, p, b = (float(bias.c[0]), bias.p, bias.b) if acc.force is bias.force else (0.0, LOAD_BIAS_SIGMA ** 2, 0.0)
        h0 = P00 + c0
        return h0 / (h0 + c0 + p + 1.0 / acc.info) * (nu - b)

    def _force_step(self, joint: tuple, part, d0: float, do) -> None:
        """:attr:`force_step`: the frame's force for the scale's change ``d0`` since the frame was formed and the
        other states' ``do`` (None: none), with the joint fit's ``part`` (its step per unit of each: None, not measured)."""
        (u0, u1, u2), (v0, v1, v2) = joint[2].tolist(), joint[3].tolist()
        if part is not None and do is not None:
            s0, s1, s2 = part[2].dot(do).tolist()
            self.force_step = np.array(((u0 - v0 * d0) - s0, (u1 - v1 * d0) - s1, (u2 - v2 * d0) - s2))
        else:
            self.force_step = np.array((u0 - v0 * d0, u1 - v1 * d0, u2 - v2 * d0))

    def _update(self) -> list:
        """The states' prediction over the frames summed since the latest update (:class:`~.drift_parts.Interval`)
        and their measurements' updates; returns the states' change (a list: the scale's relative change beyond
        the frames' steps, the other states', the rate's, ...)."""
        acc, m = self._acc, self.m
        rest, use_joint, dt = acc.rest, acc.joint, acc.dt
        if acc.tr != self._Ftr or acc.fade != self._Ffade:  # the same every interval at one frame rate
            self._Ftr, self._Ffade = acc.tr, acc.fade
            self._F[0, m], self._F[m, m] = acc.tr, acc.fade
        if dt != self._dt_q:
            self._dt_q, self._qdt = dt, self._q * dt
        tot = self._tot  # the states' change beyond the frames' steps: the follow, then the updates
        tot.fill(0.0)
        da = acc.da
        if da:
            np.multiply(self._slope, da, out=self._tot_o)
        if da != self._Fda:  # the slopes' entries of the prediction (unchanged over a run of rest frames)
            self._Fs[:] = self._Fda = da
        # predicted: the scale moves on at its rate, which fades; unrested, the other states by their slope:
        # F P F^T + Q dt with F = I + tr e_0 e_m^T + da E_os, F_mm = fade (two small products: half the cost of row
        # and column updates), into a work array: P lives within this update (its end makes _Pa anew)
        P = self._Ppred
        self._F.dot(self._Pa, out=self._FP).dot(self._FT, out=P)
        self._Ppred_diag += self._qdt  # the diagonal
        if use_joint and acc.info > 0.0:
            # the joint fit's measurements of the scale: their information-weighted mean, of their summed information
            nu, var = acc.vec / acc.info, 1.0 / acc.info
            if rest:
                self._bias.rest()
                Pc = P[:, 0].copy()
                gain = Pc / (float(Pc[0]) + var)
                delta = gain * nu
                if math.isfinite(sum(delta.tolist())):
                    tot += delta
                    P -= gain[:, None] * Pc  # the outer product
            else:
                ob = self._obias
                if ob is not None:  # the others' bias: its covariance with the states predicted as they are
                    ob[2] = self._F.dot(ob[2])
                delta = self._bias.update(P, self._F, acc.force, nu, var)
                if self._bias.new and ob is not None and moved(self._bias.force, ob[3]):
                    self._obias = ob = None  # another load: its own mismatch (_loaded_others)
                if delta is not None:
                    tot += delta
                    if ob is not None:  # ... and updated with them (the scale's measurement)
                        ob2 = ob[2]
                        ob2 -= self._bias.kx[:, None] * ob2[0]  # the outer product
        elif use_joint and rest:
            self._bias.rest()
        if use_joint and not rest and acc.k and self._bias.force is not None:
            # the other states' measurements, in information form (summed); each frame's as at the interval's end:
            # the other states' follow after it added (the slope times the loaded frames' da after it)
            hb = acc.hb
            if da:
                hb = hb + (acc.H * da - acc.Hda).dot(self._slope)
            self._loaded_others(P, tot, acc.H, hb, acc.w / acc.k, acc.kdt)
        if rest:
            # at rest the other states (the contacts', the gradient's) are measured with their full
            # directions; the scale too without a joint fit (the linear estimator). The information
            # matrix N (times the frames) and vector of the frames: the gain (P^-1 + nN)^-1 = P (I + nN P)^-1
            # without inverting P, its transpose solving (I + P nN) G' = P (A = I + nN P in C order is I + P nN
            # in Fortran's, as LAPACK takes it; P is symmetric)
            n = acc.n
            N = self._N if not use_joint else self._N_others
            A = N.dot(P)
            if n > 1:
                A *= n
            A += self._eye
            gain = solve_small(A.T, P.T).T
            # what the steps and the joint update leave: each frame's innovation over the state it was formed with
            innov = acc.b - self._N.dot(tot) * n
            innov -= self._N0 * acc.o
            if use_joint:
                innov[0] = 0.0
            delta = gain.dot(innov)
            if math.isfinite(sum(delta.tolist())):
                tot += delta
                P = gain
        d = tot.tolist()
        self.scale *= 1.0 + d[0]
        self.rate += d[m]
        if m > 1:
            g = self.gradient + self._tot_o
            if rest:
                self._follow.add(dt, self.scale - 1.0, g, acc.n)
            else:  # unmeasured: the other states follow the scale's change (FOLLOW_MEMORY)
                g += self.follow * (self.scale - self._scale_upd)
            self._set_gradient(g)
        self._scale_upd = self.scale
        Pa = P + P.T
        Pa *= 0.5
        self._Pa = Pa
        if rest:
            self._reset_slopes()
        elif self.n > m + 1:
            self._slope += tot[m + 1:]
        acc.clear()
        return d

    def _loaded_others(self, P: np.ndarray, tot: np.ndarray, Ho: np.ndarray, bo: np.ndarray, w: float,
                       check_s: float) -> None:
        """The loaded frames' measurement of the other states (:meth:`~cstomo_sensor.force.estimators.scale_fit.JointScale.others_part`'s
        information ``Ho`` and vector ``bo``, summed over the interval's frames), weighted ``w``, with
        :data:`LOADED_OTHER_N`'s floor: a Kalman update of every state through their covariance ``P`` (in place)
        into ``tot``; ``check_s``: the check's time they stand for (:data:`CHECK_EVERY` frame periods each)."""
        m = self.m
        try:
            Hinv = solve_small(Ho, self._eye[1:m, 1:m].copy())
        except np.linalg.LinAlgError:
            return
        z = Hinv.dot(bo)
        ob = self._obias  # the held load's own error of the measurement (beta, its variance, covariance c, its force)
        if ob is None:  # (observe drops it for another load)
            k = LOADED_BIAS_N + LOADED_OTHER_REL * math.hypot(*self._bias.force)
            ob = self._obias = [np.zeros(m - 1), np.diag(k * k / self._other_n ** 2), np.zeros((self.n, m - 1)),
                                list(self._bias.force)]
        beta, pb, c = ob[:3]
        if not self._wanted:  # a check (CHECK_EVERY, others_wanted): widen the states the frame finds wider than their covariance
            nu = z - tot[1:m]  # the held load's mismatch by its prior, not by what it took in
            k = LOADED_BIAS_N + LOADED_OTHER_REL * math.hypot(*self._bias.force)
            try:
                d2 = float(nu.dot(solve_small(P[1:m, 1:m] + np.diag(k * k / self._other_n ** 2) + Hinv, nu))) / (m - 1)
            except np.linalg.LinAlgError:
                return
            if not math.isfinite(d2):
                return
            a = 1.0 - math.exp(-check_s / CHECK_S)
            self._check += a * (d2 - self._check)
            if self._check < CHECK_BOUND:
                return
            P.reshape(-1)[self.n + 1:m * (self.n + 1):self.n + 1] += nu * nu
            self._check = 0.0
        Cxy = P[:, 1:m] + c  # cov(states, measured), measured = others + beta + noise
        Cby = c[1:m].T + pb
        S = Cxy[1:m] + c[1:m].T + pb + Hinv / w
        try:
            sol = solve_small(0.5 * (S + S.T), np.hstack([Cxy.T, Cby.T]))  # S^-1 [Cxy^T, Cby^T]
        except np.linalg.LinAlgError:
            return
        Kx, Kb = sol[:, :self.n].T, sol[:, self.n:].T
        nu = z - tot[1:m] - beta
        delta = Kx.dot(nu)
        if math.isfinite(sum(delta.tolist())):
            tot += delta
            P -= Kx.dot(Cxy.T)
            bc = self._bias.c  # the scale's bias: its covariance with the states updated with them
            bc -= Kx.dot(bc[1:m])
            ob[0] = beta + Kb.dot(nu)
            ob[2] = c - Kx.dot(Cby.T)
            ob[1] = pb - Kb.dot(Cby.T)

    def others_wanted(self) -> bool:
        """Whether the next frame, if unrested, should measure the other states (:data:`LOADED_OTHER_N`): one
        of them is less certain than the loaded frames' floor; or check them (:data:`CHECK_EVERY`). Called once
        per frame, before :meth:`observe`: it counts the frame towards the check and tells :meth:`observe`
        which of the two the frame's measurement is for."""
        if self._W is None or self.m < 2:
            return False
        if self._wanted_for is not self._Pa:  # P changes at an update only (UPDATE_S)
            self._wanted_for = self._Pa
            self._wanted = any(p > f for p, f in zip(self._Pa.diagonal()[1:self.m].tolist(), self._floor2l))
        if self._wanted:
            return True
        self._frames += 1  # a check after unrested frames only (a rest measures them all)
        return self._frames % CHECK_EVERY == 0 and self._t_rest != self._t

    def widen(self, age_s: float) -> None:
        """A restart from a tare saved ``age_s`` seconds ago: the device moved meanwhile by an unknown
        amount (module constants :data:`RESTART_SIGMA` ...): the states' covariance widened, so that the
        first frames, loaded or not, measure them (their own shape) and their forces say how unsure. In the first
        :data:`~.drift_parts.QUIET_POST` seconds a frame that passes its own rest tests and that the joint fit reads
        below the rest force re-anchors the quiet test (force/slow_states/drift_parts.py), as after a task: the states the first
        rest frames fit move the frames' non-uniform force, a step of the tracker's own, not a load put on (a
        small load held from the first frame, which passes the frame's own tests, is read by the joint fit).
        Before: the first rest frames left a 0.4-0.7 N lateral phantom, the quiet test took it for a load
        and refused every rest frame until the loaded frames' sparse measurements of the states happened to
        bring it under its bound, after 4-9 s by the frames' noise (device_b at -2 %, 16
        noise seeds: 0.96-1.04 x the unchanged device's zero p99 from 1 s, 3 of them 1.11-1.27 x, main
        included; now 0.96-0.99 x)."""
        if not (age_s >= 0 and math.isfinite(age_s)):
            raise ValueError(f"tare age {age_s!r}: expected seconds >= 0")
        self.flush()
        s = min(RESTART_MAX, max(RESTART_MIN, RESTART_SIGMA * math.sqrt(age_s / 3600.0)))
        m = self.m
        add = np.zeros(m + 1)
        if m > 1:
            so = max(s, RESTART_CHANGE)
            other = np.full(m - 1, RESTART_GRADIENT * so)
            other[self.contacts_block] = math.hypot(RESTART_CONTACT * so, RESTART_CONTACT_DRIFT
                                                    * min(1.0, math.sqrt(age_s / (86400.0 * RESTART_CONTACT_DAYS))))
            bl = self.learned_block
            if bl.stop > bl.start:  # the device's own directions (force/slow_states/learned.py): by their slope against the scale
                other[bl] = np.maximum(self.learned[len(self.learned) - (bl.stop - bl.start):], RESTART_GRADIENT) * so
            add[1:m] = other ** 2
            if self._W is not None:
                add[1:m] = np.maximum(add[1:m], (RESTART_OTHER_N / self._other_n) ** 2)
        add[0], add[m] = s * s, RESTART_RATE ** 2
        self.P = self.P + np.diag(add)
        self._restarted = QUIET_POST  # the states left stale for hours: the rests re-acquire them (observe)

    @property
    def unmeasured_n(self) -> float:
        """The 1-sigma (N) at zero load of the states only a rest measures (the contacts', the gradient's)."""
        if self._W is None or self.m < 2:
            return 0.0
        Wo, P = self._Wo, self.P[1:self.m, 1:self.m]
        return math.sqrt(max(float(np.sum((Wo @ P) * Wo)), 0.0))

    def since_rest(self) -> tuple[float | None, float]:
        """(seconds since the latest rest frame, None: unknown; the scale's change at its tracked rate
        since then): what the states only a rest measures have followed unmeasured."""
        ago = None if self._t is None or self._t_rest is None else max(self._t - self._t_rest, 0.0)
        return ago, self._unmeasured
