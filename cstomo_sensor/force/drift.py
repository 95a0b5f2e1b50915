"""The zero that holds: tracking the device's slow change after its tare (docs/physics.md#device-changes).

After a tare the device keeps changing: the rubber warms (its resistivity rises by 0.2..1.5 % per K,
the same sign everywhere, more on the side nearer the motor), its contacts' impedance falls with
temperature and drifts, the board's current source drifts. The mean change and the drive scale every
voltage of a frame (nearly) alike, ``V = s (V_ref + dV_load)``: a change of ``s`` by 1 % reads as 18 N
at zero load when the change is normalised by the tare alone. A gradient of the change across the
block reads as a lateral load (10 K with 30 % across: 12 N). :class:`DriftTracker` estimates ``s``,
its rate of change, and the states of a few more directions over time (the stream gives them: the
contacts' impedance changing alike and linearly along x, y, z, from the model; the resistivity's
gradient along x, y, z, :func:`gradient_directions`); the pipeline removes them all:
``y = (V / s - V_ref) / y_scale - g . d``.

What separates these slow changes from a load (one frame alone only in part: the normalised change
of a uniform scaling, ``r = V_ref / y_scale``, has a cosine of 0.4..0.7 with a socket load's):

- **shape at rest**: a frame that ``delta r`` alone explains (the whitened residual of the best
  ``delta`` below :data:`REST_BOUND` per channel, the other states' current part taken out first),
  and that reads no force once that ``delta`` is taken out (below :data:`REST_FORCE_SIGMAS` times the
  force's noise), is a frame without load; it measures every state with its full direction (a noise
  of about 1e-5 per frame at 60 dB). A lateral load looks like a gradient: it is never taken for rest.
- **every frame, loaded or not** (issue 26), with the ``model`` estimator: the frame's force and the
  scale fitted jointly (:class:`JointScale`: the load's own uncertainty marginalised, a controller's
  expected load as a measurement of the force), the tracker's mean and covariance the scale's prior: a
  tight prior (a recent rest) leaves the force as it was, a wide one (minutes of load, a restart from an
  old tare: :meth:`DriftTracker.widen`) lets the frame's shape separate them. A loaded frame counts as
  :data:`LOADED_WEIGHT` of a measurement, a rest frame as :data:`REST_WEIGHT`; the other states are
  measured at rest only (a lateral load looks like a gradient). With ``linear`` (no joint fit) a
  loaded frame measures nothing: the scale goes on at its tracked rate, and the rest frames measure the
  scale with its full direction as before.
- **time**: the states are random walks of :data:`RATE` per square-root second, the scale's rate one
  of :data:`ACCEL`; a Kalman filter weighs each rest frame's measurement against them. Loads move in
  tenths of seconds, the device in minutes: a load the shape takes for rest moves the scale little.

What it cannot separate, said plainly:

- a change that none of the directions describe: single electrodes' contacts (20 % drift: 0.13 N), a
  gradient that is not linear, the model's contact response against a real device's (a uniform 10 %
  resistivity change with the contacts unchanged, a scaling plus a contact change: 0.17 N remain).
  That remainder stays in the change, reads as a small force and raises the consistency statistic;
- a load held still whose change the estimator's model misfits along the uniform direction (1-2 N
  straight down, below the calibration's smallest load: about 30 % of it goes into the scale within
  10 s); with ``linear``, a load held still below the rest bounds (about 0.7 N at 60 dB, 5 N at 40 dB)
  is taken for rest and goes slowly into the states;
- a change of rate during a long load (the warming slows while the joint is loaded: followed at the
  next rest), and a change much faster than the rates above (a step of the drive current is followed
  over a second or so at 60 dB).
"""
from __future__ import annotations

import math

import numpy as np
from scipy.linalg import lapack

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
#: A loaded frame's own measurement of the scale (:class:`JointScale`, the load marginalised) counts
#: as this fraction of one independent measurement: the frames of one held load share the model's
#: mismatch with the device (not white noise), so their measurements do not average like noise.
LOADED_WEIGHT = 0.005
#: ... and a rest frame's (the rest test's frame: no load the shape shows; a small load held still
#: passes it at 60 dB, 1-2 N straight down, and its misfit by the model along the uniform change would
#: go into the scale as fast as the rest frames' weight lets it).
REST_WEIGHT = 0.1
#: A restart from a saved tare (:meth:`DriftTracker.widen`): the scale's 1-sigma grows with the tare's
#: age as ``RESTART_SIGMA * sqrt(age / 1 h)``, between :data:`RESTART_MIN` and :data:`RESTART_MAX`
#: (section 9: a morning 5 K colder than the tare is about -4 %); its rate's as :data:`RESTART_RATE`
#: (a joint warming at 0.8 %/K by 15 K in 30 min: 7e-5/s); each other state's (the contacts', the
#: gradient's: measured at rest only) by what reads as :data:`RESTART_OTHER_N` newtons of force (a
#: contact's 1 % reads as 0.02-0.05 N, a gradient's 1 % as 4 N: after hours off the block is near
#: its equilibrium, without a gradient).
RESTART_SIGMA, RESTART_MIN, RESTART_MAX = 0.015, 0.003, 0.05
RESTART_RATE = 1e-4
RESTART_OTHER_N = 0.15
#: A controller's expected load (``FrameStream.expect_load``) holds for frames up to this many seconds
#: after its stamp (a dynamics model's output at its own rate, tens of Hz or more).
EXPECTED_HOLD = 0.5
#: Seconds between frames without stamps (``cstomo estimate`` without ``--rate``).
DEFAULT_PERIOD = 0.01
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
#: The tracked change (``|s - 1|``) beyond which a re-tare is advised, and beyond which the tracker
#: is outside what it was validated for (``cstomo bench --drift``: uniform changes up to 10 %).
RETARE_ADVISED = 0.05
VALIDATED = 0.10
#: The rubber's stated resistivity coefficient, per kelvin (docs/physics.md#device-changes: 0.2..1.5 %),
#: to express the tracked change in kelvin.
RESISTIVITY_PER_K = 0.008


def _solve(A: np.ndarray, B: np.ndarray) -> np.ndarray:
    """X with A X = B for a small square ``A`` (LAPACK's gesv without numpy.linalg's checks: 2 us
    instead of 7); raises ``LinAlgError`` if ``A`` is singular, as ``np.linalg.inv`` did."""
    _, _, X, info = lapack.dgesv(A, B)
    if info != 0:
        raise np.linalg.LinAlgError(f"singular matrix (gesv info {info})")
    return X


def gradient_directions(model) -> np.ndarray:
    """(3, n_meas): the normalised change of a resistivity rising linearly across the block along x,
    y and z, by 1 (relative) per half of the block's extent from its middle, through the model's
    sensitivity (``S`` is per relative conductivity change of its basis voxels: ``-S`` per relative
    resistivity change; ``-S @ 1`` is the uniform scaling's ``r`` to 5e-4)."""
    c = np.asarray(model.basis_centers, float)
    lo, hi = c.min(axis=0), c.max(axis=0)
    xi = (c - 0.5 * (lo + hi)) / np.maximum(0.5 * (hi - lo), 1e-12)
    return -(model.S @ xi).T


class JointScale:
    """One frame's own measurement of the device's uniform scale with its load marginalised (issue 26,
    item 2): the model estimator's last fit (``ModelEstimator.last_fit``: the surrogate's residual and
    Jacobian at the force it found, in its whitened basis) extended by the scale's direction.

    A scale error ``d`` of the frame's change ``y`` adds ``d (r + y)`` (``r = V_ref / y_scale``); with
    ``J`` the load's Jacobian, ``rho`` the fit's residual and a controller's expected load ``e`` of
    information ``L`` (None: none), the joint least squares over the force step ``dx`` and ``d``::

        |rho - J dx - d_w d|^2 + (dx - e)^T L (dx - e)

    profiled over ``dx`` gives ``d``'s information ``H = |d_w|^2 - g^T A^-1 g`` and its estimate
    ``b / H`` (``A = J^T J + L``, ``g = J^T d_w``): the part of the frame's change along ``r`` that no
    load explains. The part of ``d_w`` outside the estimator's basis (no load makes it) is taken from
    dot products over the full change. :meth:`measure` returns it with the force's step for a given
    ``d``: ``dF = u - v d`` (N).
    """

    def __init__(self, estimator, r: np.ndarray) -> None:
        self.est = estimator
        rw = np.asarray(r, float)[estimator.keep] * estimator.w
        self.rw, self.Brw, self.rr = rw, estimator.basis @ rw, float(rw.dot(rw))
        self.dof = max(len(rw) - 4, 1)
        self._M = np.empty((len(self.Brw), 2))

    def measure(self, expected: tuple | None = None) -> tuple | None:
        """(d, its variance, u, v, the frame's force) of the estimator's latest frame (class docstring); ``expected``:
        (force (3,) N, 1-sigma N) a controller expects now. None when the fit gives nothing."""
        est = self.est
        if est.last_fit is None:
            return None
        yw, step, x_hat = est.last_fit
        out, k = est._out, est.scale
        Jt = out[1:]  # (3, k): the Jacobian's transpose at the last iterate, before its step
        rho = np.dot(np.asarray(step, float), Jt)  # the residual at the final force: By - s(x) to first order
        rho -= out[0]
        By = est._d0 - est._d0_target
        Bd = self.Brw + By
        ry, yy = float(self.rw.dot(yw)), float(yw.dot(yw))
        dd = self.rr + 2.0 * ry + yy       # |d_w|^2, d_w = w (r + y)
        dy_perp = ry + yy - float(Bd.dot(By))  # d_w . y_w outside the basis
        A = np.dot(Jt, Jt.T)
        M = self._M
        M[:, 0] = rho
        M[:, 1] = Bd
        rhs = np.dot(Jt, M)  # (3, 2): J^T rho, g = J^T d_w
        if expected is not None:
            f, sig = expected
            lam = (k / sig) ** 2
            A[np.diag_indices(3)] += lam
            rhs[:, 0] += lam * (np.asarray(f, float) / k - np.asarray(x_hat))
        try:
            sol = _solve(A, rhs)
        except np.linalg.LinAlgError:
            return None
        g = rhs[:, 1]
        H = dd - float(g.dot(sol[:, 1]))
        b = float(Bd.dot(rho)) + dy_perp - float(g.dot(sol[:, 0]))
        if not H > 0:
            return None
        chi2 = float(rho.dot(rho)) + yy - float(By.dot(By)) - b * b / H
        inflate = max(1.0, chi2 / self.dof)  # the model's mismatch with the device, beyond the noise
        return b / H, inflate / H, k * sol[:, 0], k * sol[:, 1], np.multiply(x_hat, k)


class DriftTracker:
    """The device's slow change since its tare (module docstring): the uniform scale ``s`` of its
    voltages, its ``rate`` (per second), and the states of the other directions (``gradient``, (k,):
    the stream gives the contacts' four and the resistivity gradient's three, relative change per
    half extent).

    Parameters
    ----------
    r : (n_meas,) ndarray
        The normalised change of a uniform scaling by 1 + 1 (``V_ref / y_scale``).
    gradients : (k, n_meas) ndarray or None
        The other directions followed at rest (the model's contact directions, :func:`gradient_directions`;
        None: the scale alone is tracked).
    noise : (n_meas,) ndarray
        Per-channel noise std of a change (y units).
    keep : (n_meas,) bool ndarray
        Channels in use.
    force_map : (3, n_meas) ndarray or None
        The estimator's linear map from a change to a force (N), for the rest frames' force bound
        (None: the residual bound alone).
    """

    def __init__(self, r: np.ndarray, gradients: np.ndarray | None, noise: np.ndarray, keep: np.ndarray,
                 force_map: np.ndarray | None = None) -> None:
        self._args = (r, gradients, noise, keep, force_map)
        w = np.where(keep, 1.0 / np.asarray(noise, float), 0.0)
        D = np.atleast_2d(np.asarray(r, float))
        if gradients is not None:
            D = np.vstack([D, gradients])
        D = D * keep
        Dw = D * w
        self.m = m = len(D)  # measured states: the scale, the gradient; then the scale's rate
        self._D, self._w, self._Dw = D, w, Dw
        self._N = np.zeros((m + 1, m + 1))
        self._N[:m, :m] = Dw @ Dw.T
        self._Dw1 = np.vstack([Dw, np.zeros((1, len(w)))])
        self._rest = REST_BOUND * float(np.count_nonzero(keep))
        self._W = None
        if force_map is not None:  # the force of a change, of a uniform change, and its noise
            W = np.asarray(force_map, float) * keep
            sigma = math.sqrt(float(np.sum((W * np.where(keep, noise, 0.0)) ** 2)))
            self._W, self._Wr = W, W @ D[0]
            self.rest_force = max(REST_FORCE_MIN, REST_FORCE_SIGMAS * sigma)
        self._N00, self._N0 = float(self._N[0, 0]), np.ascontiguousarray(self._N[:, 0])
        self._N_others = self._N.copy()  # the information of the states other than the scale
        self._N_others[0, :] = self._N_others[:, 0] = 0.0
        self._tot = np.zeros(m + 1)
        self._Dg = np.ascontiguousarray(D[1:])  # the gradient's directions: its offset
        self._yw = np.empty_like(w)
        self._b = np.empty(m + 1)
        self._eye = np.eye(m + 1)
        self._q = np.array([RATE * RATE] * m + [ACCEL * ACCEL])
        self._dt, self._a, self._qdt = -1.0, 1.0, self._q  # observe()'s factors of the last period
        self._F = np.eye(m + 1)
        self.scale = 1.0
        self.rate = 0.0  # the scale's relative change per second
        self.gradient = np.zeros(m - 1)
        self.offset = np.zeros_like(w)  # the gradient's change: subtracted from the frame's change
        self.P = np.zeros((m + 1, m + 1))
        self.rest_frames = 0  # frames measured as at rest (all time)
        self.force_step: np.ndarray | None = None  # observe()'s joint force step (N) of the latest frame
        self._t: float | None = None

    def with_mask(self, keep: np.ndarray, new_map: np.ndarray | None = None) -> DriftTracker:
        """The same tracker (its state kept) over the channels ``keep``."""
        r, gradients, noise, _, force_map = self._args
        return self._carried(DriftTracker(r, gradients, noise, keep, force_map if new_map is None else new_map))

    def with_noise(self, noise: np.ndarray, new_map: np.ndarray | None = None) -> DriftTracker:
        """The same tracker (its state kept) for a change of per-channel noise ``noise`` (y units)."""
        r, gradients, _, keep, force_map = self._args
        return self._carried(DriftTracker(r, gradients, noise, keep, force_map if new_map is None else new_map))

    def _carried(self, new: DriftTracker) -> DriftTracker:
        """``new`` with this tracker's state."""
        new.scale, new.rate, new.P, new.rest_frames, new._t = self.scale, self.rate, self.P, self.rest_frames, self._t
        new._set_gradient(self.gradient)
        return new

    @property
    def change(self) -> float:
        """The tracked relative change of the voltages since the tare (``s - 1``)."""
        return self.scale - 1.0

    def _set_gradient(self, g: np.ndarray) -> None:
        self.gradient = np.asarray(g, float)
        if self.m > 1:
            np.dot(self.gradient, self._Dg, out=self.offset)

    def observe(self, y: np.ndarray, t: float | None = None, joint: tuple | None = None) -> bool:
        """Update the state with the normalised change ``y`` (n_meas,) of a frame at time ``t`` (s; None:
        :data:`DEFAULT_PERIOD` after the previous frame), formed with the current state; returns True
        if the frame was taken as at rest. ``joint``: the frame's :meth:`JointScale.measure` (None: the
        linear estimator, no joint fit: a loaded frame measures nothing); then :attr:`force_step` is
        the frame's force step (N) for the scale as updated (None without it)."""
        dt = DEFAULT_PERIOD if t is None or self._t is None else min(max(t - self._t, 0.0), 1.0)
        if t is not None:  # a stepped clock: one frame's step is clipped, the next ones count from it
            self._t = t
        m = self.m
        if dt != self._dt:  # frames come at one rate: the prediction's factors once
            self._dt, self._a, self._qdt = dt, math.exp(-dt / RATE_MEMORY), self._q * dt
            self._F[0, m], self._F[m, m] = dt, self._a
        a = self._a
        # predicted: the scale moves on at its rate, which fades: F P F^T + Q dt with
        # F = I + dt e_0 e_m^T, F_mm = a (two small products: half the cost of row and column updates)
        P = np.dot(np.dot(self._F, self.P), self._F.T)
        P.reshape(-1)[:: m + 2] += self._qdt  # the diagonal
        yw = np.multiply(y, self._w, out=self._yw)
        b = np.dot(self._Dw1, yw, out=self._b)
        # at rest when the scale alone explains the frame (the gradient's current part is already
        # taken out): a lateral load looks like a gradient and must never be taken for one
        b0 = float(b[0])
        best = b0 / self._N00  # the uniform change that explains the most of the frame
        rest = float(yw.dot(yw)) - b0 * best < self._rest
        if rest and self._W is not None:
            f = np.dot(self._W, y) - self._Wr * best
            rest = math.sqrt(float(f.dot(f))) < self.rest_force
        step = self.rate * dt
        self.rate *= a
        self.force_step = None
        tot = self._tot  # the states' change since the frame was formed: the step, then the updates
        tot[:] = 0.0
        tot[0] = step
        use_joint = joint is not None
        if use_joint:
            # every frame, at rest or loaded: the scale measured with the frame's load marginalised
            # (JointScale), so that a load is never taken for the device; a loaded frame counts as
            # LOADED_WEIGHT of a measurement (the model's mismatch with a load is not white noise)
            z, var, u, v, _ = joint
            var = var / (REST_WEIGHT if rest else LOADED_WEIGHT)
            Pc = P[:, 0].copy()
            gain = Pc / (Pc[0] + var)
            delta = gain * (z - step)
            if math.isfinite(float(delta.sum())):
                tot += delta
                P -= np.multiply.outer(gain, Pc)
        if rest:
            # at rest the other states (the contacts', the gradient's) are measured with their full
            # directions; the scale too without a joint fit (the linear estimator). The information
            # matrix N and vector of this frame: the gain (P^-1 + N)^-1 = P (I + N P)^-1 without
            # inverting P, its transpose solving (I + P N) G' = P (A = I + N P in C order is I + P N
            # in Fortran's, as LAPACK takes it; P is symmetric)
            self.rest_frames += 1
            N = self._N if not use_joint else self._N_others
            A = np.dot(N, P)
            A += self._eye
            gain = _solve(A.T, P.T).T
            innov = b - np.dot(self._N, tot)  # what the step and the joint update leave
            if use_joint:
                innov[0] = 0.0
            delta = np.dot(gain, innov)
            if math.isfinite(float(delta.sum())):
                tot += delta
                P = gain
        d = tot.tolist()
        # the frame was formed with the scale before this frame's step: the step and the updates
        self.scale *= (1.0 + step) * (1.0 + d[0] - step)
        self.rate += d[m]
        if m > 1 and (rest or joint is not None):
            self._set_gradient(self.gradient + tot[1:m])
        if joint is not None:
            self.force_step = joint[2] - joint[3] * d[0]  # the force given the scale now known
        self.P = 0.5 * (P + P.T)
        return rest

    def widen(self, age_s: float) -> None:
        """A restart from a tare saved ``age_s`` seconds ago: the device moved meanwhile by an unknown
        amount (module constants :data:`RESTART_SIGMA` ...): the states' covariance widened, so that the
        first frames, loaded or not, measure them (their own shape) and their forces say how unsure."""
        if not (age_s >= 0 and math.isfinite(age_s)):
            raise ValueError(f"tare age {age_s!r}: expected seconds >= 0")
        s = min(RESTART_MAX, max(RESTART_MIN, RESTART_SIGMA * math.sqrt(age_s / 3600.0)))
        m = self.m
        add = np.zeros(m + 1)
        if self._W is not None and m > 1:
            add[1:m] = (RESTART_OTHER_N / np.maximum(np.linalg.norm(self._W @ self._Dg.T, axis=0), 1e-12)) ** 2
        add[0], add[m] = s * s, RESTART_RATE ** 2
        self.P = self.P + np.diag(add)

    @property
    def kelvin_text(self) -> str:
        """The tracked change as a temperature change of the rubber at :data:`RESISTIVITY_PER_K`."""
        kelvin = math.log(self.scale) / math.log1p(RESISTIVITY_PER_K) if self.scale > 0 else math.nan
        return f"{kelvin:+.1f} K at {RESISTIVITY_PER_K:.1%}/K, or a drive drift"

    def status(self) -> tuple[int, str]:
        """(0 OK, 1 WARN; a message) of the tracked change for the diagnostics."""
        c = self.change
        text = f"{c:+.2%} since the tare (about {self.kelvin_text})"
        if abs(c) > VALIDATED:
            return 1, f"device changed {text}: beyond the {VALIDATED:.0%} the zero tracking is validated for; re-tare"
        if abs(c) > RETARE_ADVISED:
            return 0, f"device changed {text}: a re-tare is advised when the joint is free"
        return 0, ""
