"""The per-frame formulations the fast path replaced, kept plain for the tests to hold the library
against (test_frame_path.py): the ``model`` estimator's Gauss-Newton fit through the spline's value
and Jacobian with ``numpy`` normal equations. The package uses none of them."""
from __future__ import annotations

import math

import numpy as np


def _solve3(A: np.ndarray, b: np.ndarray) -> np.ndarray | None:
    try:
        return np.linalg.solve(A, b)
    except np.linalg.LinAlgError:
        return None


def model_estimate(est, y: np.ndarray) -> np.ndarray:
    """``ModelEstimator.estimate`` as it was: value and Jacobian, then J^T J and J^T r apart."""
    x = est.linear.estimate(y) / est.scale
    target = est.basis @ (y[est.keep] * est.w)
    for _ in range(est.iterations):
        pred, J = est.surrogate.value_and_jacobian(x)
        step = _solve3(J.T @ J, J.T @ (target - pred))
        if step is None:
            step = np.linalg.lstsq(J, target - pred, rcond=None)[0]
        x = x + step
        if not step @ step >= (1e-4 / est.scale) ** 2:
            break
    return x * est.scale



def drift_observe(tracker, y: np.ndarray, t: float | None = None) -> bool:
    """``DriftTracker.observe`` as it was (issue 20's tracker with the rate): the prediction by row and
    column operations and the rest frame's gain through a matrix inverse, on ``tracker``'s state; with
    issue 26's follow under load: the other states' slope against the scale by a weighted polynomial
    fit of every rest frame kept (``np.polyfit``), and their variance's growth since the last rest."""
    from cstomo_sensor.force.slow_states.creep import DEFAULT_PERIOD
    from cstomo_sensor.force.slow_states.drift import (
        FOLLOW_MEMORY,
        FOLLOW_SIGMA,
        FOLLOW_SPAN,
        RATE_MEMORY,
        RESTART_CONTACT,
        RESTART_GRADIENT,
    )

    self = tracker
    dt = DEFAULT_PERIOD if t is None or self._t is None else min(max(t - self._t, 0.0), 1.0)
    if t is not None:
        self._t = t
    m = self.m
    k = m + 1  # the measured states and the rate (the tracker's arrays go on with the slopes' states)
    a = math.exp(-dt / RATE_MEMORY)
    P = self.P.copy()
    P[0] += dt * P[m]
    P[m] *= a
    P[:, 0] += dt * P[:, m]
    P[:, m] *= a
    P[np.diag_indices_from(P)] += self._q[:k] * dt
    yw = y * self._w
    b = np.append(self._Dwm @ yw, 0.0)  # the measured states' rows, the rate's 0
    best = b[0] / self._N[0, 0]
    rest = float(yw @ yw) - b[0] * best < self._rest
    if rest and self._W is not None:
        f = self._W @ y - self._Wr * best
        rest = math.sqrt(float(f @ f)) < self.rest_force
    step = self.rate * dt
    self.rate *= a
    if not rest:
        s0 = self.scale
        self.scale *= 1.0 + step
        if m > 1:
            a0 = self._unmeasured
            self._unmeasured = a0 + abs(step)
            others = np.arange(1, m)
            # the slope's 1-sigma: FOLLOW_SIGMA once rests spanned FOLLOW_SPAN of the scale, else section 9's
            # range (issue 34): RESTART_CONTACT for the contacts' states (the first), RESTART_GRADIENT for the rest
            if getattr(self, "_ref_fitted", False):
                slope2 = np.full(m - 1, FOLLOW_SIGMA ** 2)
            else:
                slope2 = np.array([(RESTART_CONTACT if k < self.contacts else RESTART_GRADIENT) ** 2 for k in range(m - 1)])
            P[others, others] += slope2 * (self._unmeasured ** 2 - a0 ** 2)
            self.gradient = self.gradient + self.follow * (self.scale - s0)
            np.dot(self.gradient, self._D[1:], out=self.offset)
        self.P = P
        return False
    self.rest_frames += 1
    self._unmeasured, self._t_rest = 0.0, self._t
    info = self._N[:k, :k]
    gain = P @ np.linalg.inv(np.eye(k) + info @ P)
    delta = gain @ (b - info[:, 0] * step)
    if np.isfinite(delta).all():
        self.scale *= (1.0 + step) * (1.0 + float(delta[0]))
        self.rate += float(delta[m])
        if m > 1:
            self.gradient = self.gradient + delta[1:m]
            np.dot(self.gradient, self._D[1:], out=self.offset)
        P = gain
    if m > 1:  # every rest frame's (scale, states), weighted by the rest time since it
        clock = getattr(self, "_rest_clock", 0.0) + dt
        hist = getattr(self, "_rest_hist", []) + [(clock, self.scale - 1.0, self.gradient.copy())]
        self._rest_clock, self._rest_hist = clock, hist
        c, s, g = (np.array([h[i] for h in hist]) for i in range(3))
        w = np.exp(-(clock - c) / FOLLOW_MEMORY)
        if len(hist) > 1 and np.sum(w * (s - np.sum(w * s) / np.sum(w)) ** 2) > np.sum(w) * FOLLOW_SPAN ** 2:
            self.follow = np.array([np.polyfit(s, g[:, i], 1, w=np.sqrt(w))[0] for i in range(m - 1)])
            self._ref_fitted = True
    self.P = 0.5 * (P + P.T)
    return True


def model_sigma(sig, D: np.ndarray | None, force: np.ndarray, P: np.ndarray | None, offset: np.ndarray | None, change: float,
                misfit: float = 1.0):
    """``ForceSigma``'s ((sigma fx, fy, fz), sigma_n) with the ``model`` estimator's own map, plainly:
    the map ``k (J^T J)^-1 J^T B w`` of the estimator's latest fit through ``np.linalg.solve``, the
    covariance of the module docstring as one 3 x 3 matrix (``D``: the tracker's directions) (issue 26: the per-frame form solved the
    normal equations by LAPACK with the states' directions as right-hand sides; issue 34: the frame's
    ``misfit`` times the noise's and the states' terms, the calibration residual by the load's elevation)."""
    from cstomo_sensor.force.slow_states.sigma import UNDESCRIBED

    est = sig.est
    k, fit = est.scale, est.last_fit
    Jt = fit.out[1:]
    A = Jt @ Jt.T
    local = k * np.linalg.solve(A, Jt @ sig._Bw)  # (3, n_keep): a change's force near the frame's load
    cov = k * k * sig._noise_w2 * np.linalg.inv(A)
    if P is not None:
        kept = np.asarray(est.keep, bool)
        D = D[:, kept]  # the states' directions on the kept channels
        Dy = D.copy()
        Dy[0] += fit.yw / est.w  # a scale error scales the load's change too
        WD = np.hstack([local @ Dy.T, np.zeros((3, 1))])  # the rate: no direction of its own
        cov += WD @ P @ WD.T
        wr = local @ D[0]
        cov += (UNDESCRIBED * change) ** 2 * float(wr @ wr) / 3.0 * np.eye(3)
    cov *= max(misfit, 1.0)
    # k^2 = k_v^2 + k_l^2 cos^2(el): per axis a third of k_v^2 |F|^2 + k_l^2 |F_lateral|^2 (k2, kl2: the thirds)
    cov += (sig.k2 * float(force @ force) + sig.kl2 * float(force[:2] @ force[:2])) * np.eye(3)
    if offset is not None:
        c = sig.creep_rel * local @ offset[np.asarray(est.keep, bool)]
        cov += np.outer(c, c)
    return np.sqrt(np.diag(cov)), float(np.sqrt(np.trace(cov)))


class PlainCreep:
    """``CreepCompensator.observe`` as it was (issue 26): each low-pass stepped toward the change held,
    ``s += (1 - exp(-dt / tau)) (last - s)``, by broadcast row operations; the same queue and clock."""

    def __init__(self, coefficient: float, n_meas: int) -> None:
        from cstomo_sensor.force.slow_states.creep import creep_modes

        self.tau, w = creep_modes()
        self.cw = coefficient * w
        self.s = np.zeros((len(self.tau), n_meas))
        self.offset = np.zeros(n_meas)
        self.t, self.clock, self.recent, self.queue = None, 0.0, [], []
        self.last, self.t_last, self.f_last = np.zeros(n_meas), 0.1, None

    def observe(self, y: np.ndarray, t: float, frozen: np.ndarray | None = None) -> None:
        from cstomo_sensor.force.slow_states.creep import CREEP_T0, MAX_STEPS, PERIOD_STEPS, STEP_ROUND

        step = None if self.t is None else t - self.t
        self.t = t
        if step is not None and step > 0:
            self.recent = (self.recent + [step])[-PERIOD_STEPS:]
        period = sorted(self.recent)[(len(self.recent) - 1) // 2] if self.recent else 0.01
        self.clock += 0.01 if step is None else min(max(step, 0.0), MAX_STEPS * period)
        self.queue.append((self.clock + CREEP_T0, y.copy(), None if frozen is None else frozen.copy()))
        due = self.clock + period

        def factor(dt):
            return -np.expm1(-(round(dt / STEP_ROUND) * STEP_ROUND) / self.tau)[:, None]

        while self.queue and self.queue[0][0] <= due + 1e-3 * period:
            te, yq, fq = self.queue.pop(0)
            if te - self.t_last > 0:
                d = (self.last - self.s) * factor(te - self.t_last)
                if self.f_last is not None:
                    d[:, self.f_last] = 0.0
                self.s += d
            self.last, self.t_last, self.f_last = yq, te, fq
        self.offset = self.cw @ self.s
        part = due - self.t_last
        if part > max(1e-3 * period, STEP_ROUND / 2):
            d = self.last - self.s
            if self.f_last is not None:
                d[:, self.f_last] = 0.0
            self.offset = self.offset + (self.cw * factor(part)[:, 0]) @ d


class PlainQuietTest:
    """``drift_parts.QuietTest`` as it was: its means as numpy arrays."""

    def __init__(self, sigma: float, rest_force: float) -> None:
        from cstomo_sensor.force.slow_states.drift_parts import QUIET_BIG

        self.sigma, self.big = sigma, QUIET_BIG * rest_force
        self.fast, self.slow, self.quiet, self.post = np.zeros(3), np.zeros(3), True, 0.0

    def step(self, f: np.ndarray, rest: bool, dt: float) -> bool:
        from cstomo_sensor.force.slow_states.drift_parts import QUIET_FAST, QUIET_N, QUIET_POST, QUIET_SIGMAS, QUIET_SLOW

        af = 1.0 - math.exp(-dt / QUIET_FAST)
        bound = max(QUIET_N, QUIET_SIGMAS * self.sigma * math.sqrt(af / (2.0 - af)))
        aslow, bound2 = 1.0 - math.exp(-dt / QUIET_SLOW), bound * bound
        fast, slow = self.fast, self.slow
        fast += af * (f - fast)
        d = fast - slow
        verdict = self.quiet
        if float(d.dot(d)) > self.big * self.big:
            self.post = QUIET_POST
        if self.post > 0.0:
            self.post -= dt
            slow[:] = fast
            self.quiet = True
            return verdict
        if rest:
            slow += aslow * d
            d = fast - slow
        self.quiet = float(d.dot(d)) < bound2
        return verdict


class PlainUnloaded:
    """``learned.Unloaded`` as it was: its means as numpy arrays."""

    def __init__(self) -> None:
        self.fast = self.slow = None
        self.clear = self.broke = False

    def step(self, force, rest: bool, sigma: float, dt: float, known: bool) -> bool:
        from cstomo_sensor.force.slow_states.learned import STEP_FAST, STEP_N, STEP_SIGMAS, STEP_SLOW

        if force is None or not np.isfinite(force).all():
            self.clear, self.broke = False, True
            return rest
        a, b = 1.0 - math.exp(-dt / STEP_FAST), 1.0 - math.exp(-dt / STEP_SLOW)
        sd = math.sqrt(max(a / (2.0 - a) + b / (2.0 - b) - 2.0 * a * b / (1.0 - (1.0 - a) * (1.0 - b)), 0.0))
        if self.fast is None:
            self.fast, self.slow = np.array(force, float), np.array(force, float)
        else:
            self.fast += a * (force - self.fast)
            self.slow += b * (force - self.slow)
        d = self.fast - self.slow
        bound = max(STEP_N, STEP_SIGMAS * sd * sigma)
        self.broke = float(d.dot(d)) > bound * bound or known
        self.clear = (self.clear or rest) and not self.broke
        return self.clear or rest


def follow_add(fit: np.ndarray, slope: np.ndarray, dt: float, s: float, g: np.ndarray) -> bool:
    """``drift_parts.FollowSlope.add`` as it was, on its sums ``fit`` (3, m) and ``slope`` (m - 1,), in place;
    returns whether the slope is fitted by this frame."""
    from cstomo_sensor.force.slow_states.drift_parts import FOLLOW_MEMORY, FOLLOW_SPAN

    F = fit
    F *= math.exp(-dt / FOLLOW_MEMORY)
    F[0, 0] += 1.0
    F[1, 0] += s
    F[2, 0] += s * s
    F[0, 1:] += g
    F[1, 1:] += s * g
    n, ss = F[0, 0], F[2, 0] - F[1, 0] ** 2 / F[0, 0]
    if ss > n * FOLLOW_SPAN ** 2:
        slope[:] = (F[1, 1:] - F[1, 0] * F[0, 1:] / n) / ss
        return True
    return False


def joint_measure(joint, expected=None, others: bool = False):
    """``JointScale.measure`` as it was: the force profiled out through ``np.linalg.solve`` of the 3 x 3 normal
    matrix (every right-hand side at once), the others' part by ``others_part`` on that solution."""
    est = joint.est
    if est.last_fit is None:
        return None
    yw, By, step, x_hat, out, _ = est.last_fit
    k = est.scale
    Jt = out[1:]
    rho = -(out[0] + np.asarray(step, float) @ Jt)
    Bd = joint.Brw + By
    ry, yy = float(joint.rw @ yw), float(yw @ yw)
    dd = joint.rr + 2.0 * ry + yy
    dy_perp = ry + yy - float(Bd @ By)
    A = Jt @ Jt.T
    ext = others and joint.n_others > 0
    M = np.column_stack([rho, Bd] + ([joint._BD] if ext else []))
    rhs = Jt @ M
    if expected is not None:
        f, sig = expected
        lam = (k / sig) ** 2
        A = A + lam * np.eye(3)
        rhs[:, 0] += lam * (np.asarray(f, float) / k - np.asarray(x_hat))
    try:
        sol = np.linalg.solve(A, rhs)
    except np.linalg.LinAlgError:
        return None
    g = rhs[:, 1]
    H = dd - float(g @ sol[:, 1])
    b = float(Bd @ rho) + dy_perp - float(g @ sol[:, 0])
    if not H > 0:
        return None
    chi2 = float(rho @ rho) + yy - float(By @ By) - b * b / H
    inflate = max(1.0, chi2 / joint.dof)
    part = joint.others_part(yw, By, rho, rhs, sol, dd, H, b, chi2, k) if ext else None
    return b / H, inflate / H, k * sol[:, 0], k * sol[:, 1], np.asarray(x_hat) * k, part


# ---- helper est (issue 34's frame cost: the estimator, the joint fit, the sigma) ----------------------------------

def spline_rows(spline, x: np.ndarray) -> np.ndarray:
    """``ThinPlateSpline.basis_rows`` as it was: the value's row ``[phi(r_i) | 1 | x]`` and the gradient's
    ``[(2 log r_i + 1)(x - p_i) | 0 | I]``, the ``x - p_i`` term included, by broadcasting."""
    p = spline.points
    n, d = p.shape
    diff = np.asarray(x, float)[None, :] - p  # (n, d)
    r = np.sqrt(np.sum(diff * diff, axis=1))
    with np.errstate(divide="ignore", invalid="ignore"):
        phi = np.where(r > 0, r * r * np.log(np.where(r > 0, r, 1.0)), 0.0)
        g = np.where(r > 0, 2.0 * np.log(np.where(r > 0, r, 1.0)) + 1.0, 0.0)
    rows = np.zeros((1 + d, n + 1 + d))
    rows[0, :n], rows[0, n], rows[0, n + 1:] = phi, 1.0, x
    rows[1:, :n] = (g[:, None] * diff).T
    rows[1:, n + 1:] = np.eye(d)
    return rows
