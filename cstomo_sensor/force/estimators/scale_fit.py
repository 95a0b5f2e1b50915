"""One frame's own measurement of the device's uniform scale, its load marginalised (issue 26): the joint
fit of the force and the scale that lets every frame, loaded or not, inform the drift tracker
(:mod:`cstomo_sensor.force.slow_states.drift`), and the directions the tracker follows besides the scale. docs/node.md, *Following the
device under load*."""
from __future__ import annotations

import numpy as np

from .linalg import inverse3, solve_small


def gradient_coordinates(model, points: np.ndarray) -> np.ndarray:
    """(n, 3): the relative resistivity change at ``points`` (n, 3) m of the gradients along x, y and z:
    rising linearly by 1 per half of the block's extent (its basis voxels' centres) from its middle."""
    c = np.asarray(model.basis_centers, float)
    lo, hi = c.min(axis=0), c.max(axis=0)
    return (np.asarray(points, float) - 0.5 * (lo + hi)) / np.maximum(0.5 * (hi - lo), 1e-12)


def gradient_directions(model) -> np.ndarray:
    """(3, n_meas): the normalised change of the resistivity gradients along x, y and z
    (:func:`gradient_coordinates`) through the model's sensitivity (``S`` is per relative conductivity
    change of its basis voxels: ``-S`` per relative resistivity change; ``-S @ 1`` is the uniform
    scaling's ``r`` to 5e-4). The ``model`` estimator's response follows their states
    (force/estimators/training.py :func:`~.training.response_set`)."""
    return -(model.S @ gradient_coordinates(model, model.basis_centers)).T


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

    With the tracker's other directions ``D_o`` (``others``: the contacts', the gradients'), the same least
    squares over ``(dx, d, d_o)`` profiled over ``dx`` and then ``d`` gives their information
    (:meth:`others_part`): its inverse is their Cramer-Rao bound for the frame. On device_a at 60 dB, as the
    1-sigma of the force each reads at zero load: contacts 0.09 / 0.13 / 0.06 / 0.04 N under a load (0.07 /
    0.12 / 0.04 / 0.03 at rest), gradients along x, y, z 0.28 / 0.28 / 0.02 N (0.07 / 0.08 / 0.02 at
    rest): a lateral load takes 15/16 of the x and y gradients' information (docs/physics.md#device-changes).
    """

    def __init__(self, estimator, r: np.ndarray, others: np.ndarray | None = None) -> None:
        self.est = estimator
        rw = np.asarray(r, float)[estimator.keep] * estimator.w
        self.rw, self.Brw, self.rr = rw, estimator.basis @ rw, float(rw.dot(rw))
        self.dof = max(len(rw) - 4, 1)
        # measure's work arrays: the rows [rho, B w r, B y] (its inner products and the Jacobian's with them, one
        # product each) and the fit's last step
        self._V = np.empty((3, len(self.Brw)))
        self._V[1] = self.Brw
        self._VT = self._V.T
        self._s = np.empty(3)
        self.n_others = 0
        if others is not None and len(others):  # the tracker's other states' directions (whitened, in use)
            Dw = np.ascontiguousarray(np.atleast_2d(np.asarray(others, float))[:, estimator.keep] * estimator.w)
            self.n_others = k = len(Dw)
            self._Dw, self._BD = Dw, np.ascontiguousarray(estimator.basis @ Dw.T)  # (k, n_keep), (kb, k)
            self._Dr, self._DD = Dw @ rw, Dw @ Dw.T
            self._Mx = np.empty((len(self.Brw), 2 + k))
            self._Mx[:, 2:] = self._BD  # the others' columns: fixed (measure sets the first two per frame)
            self._Q = np.empty((1 + k, 1 + k))
            self._Q[1:, 1:] = self._DD

    def measure(self, expected: tuple | None = None, others: bool = False) -> tuple | None:
        """(d, its variance, u, v, the frame's force, the others' part) of the estimator's latest frame (class
        docstring); ``expected``: (force (3,) N, 1-sigma N) a controller expects now. None when the fit gives
        nothing. ``others`` (and the tracker's other directions given): the others' part is (``H``, ``b``,
        ``V``): their information and information vector with the load and the scale profiled out
        (:meth:`others_part`), and the force's step per unit of each (``dF = u - v d - V d_o``); else None."""
        est = self.est
        fit = est.last_fit
        if fit is None:
            return None
        yw, By, step, x_hat, out = fit.yw, fit.by, fit.step, fit.x, fit.out
        k = est.scale
        Jt = out[1:]  # (3, k): the Jacobian's transpose at the last iterate, before its step
        # the residual at the final force, By - s(x + step) = -(out[0] + J step) to first order (before: out[0]'s
        # negative plus J step, the residual at x - step: the force's step u then carried twice the fit's last step,
        # 2e-5 N at the 1e-4 N tolerance, 0.02 N at a 0.01 N one; the scale's measurement, its load profiled out, is
        # the same either way), into the first of V = [rho, B w r, B y]
        V = self._V
        s = self._s  # the fit's last step into a work array (3 item assignments: no new array)
        s[0], s[1], s[2] = step
        rho = s.dot(Jt, out=V[0])
        rho += out[0]
        np.negative(rho, out=rho)
        V[2] = By
        ext = others and self.n_others > 0
        # (ndarray.dot, not np.dot: its dispatch costs more than these small products)
        ry, yy = float(self.rw.dot(yw)), float(yw.dot(yw))
        (pp, pr, py), (_, _, ry_b), (_, _, yy_b) = V.dot(self._VT).tolist()  # the inner products of rho, B w r, B y
        dd = self.rr + 2.0 * ry + yy       # |d_w|^2, d_w = w (r + y)
        dy_perp = ry + yy - ry_b - yy_b  # d_w . y_w outside the basis (B d_w = B w r + B y)
        # A = J^T J (+ L) and its inverse on Python floats: a 3 x 3 system, where a LAPACK call and numpy's
        # small-array calls around it cost more than its arithmetic; J^T J is the fit's last normal matrix
        (_, a0, a1, a2), (_, a3, a4, a5), (_, a6, a7, a8) = fit.normal.tolist()
        if ext:  # the others' columns too: J^T [rho, d_w, D_o] as one array (others_part)
            M = self._Mx
            M[:, 0] = rho
            np.add(self.Brw, By, out=M[:, 1])
            rhs = Jt.dot(M)  # (3, 2 + n_o)
            (r0, g0, *_), (r1, g1, *_), (r2, g2, *_) = rhs.tolist()
        else:  # J^T [rho, B w r, B y]: J^T rho and g = J^T d_w
            (r0, gr0, gy0), (r1, gr1, gy1), (r2, gr2, gy2) = Jt.dot(self._VT).tolist()
            g0, g1, g2 = gr0 + gy0, gr1 + gy1, gr2 + gy2
        if expected is not None:
            f, sig = expected
            lam = (k / sig) ** 2
            a0, a4, a8 = a0 + lam, a4 + lam, a8 + lam
            f0, f1, f2 = (float(v) / k for v in f)
            r0, r1, r2 = r0 + lam * (f0 - x_hat[0]), r1 + lam * (f1 - x_hat[1]), r2 + lam * (f2 - x_hat[2])
            if ext:
                rhs[0, 0], rhs[1, 0], rhs[2, 0] = r0, r1, r2
        inv = inverse3(a0, a1, a2, a3, a4, a5, a6, a7, a8)
        if inv is None:  # singular
            return None
        i0, i1, i2, i3, i4, i5, i6, i7, i8 = inv
        if ext:  # the others' columns too: their solution as an array (others_part)
            sol = np.array(inv).reshape(3, 3).dot(rhs)
            (s0, t0, *_), (s1, t1, *_), (s2, t2, *_) = sol.tolist()
        else:
            s0, s1, s2 = i0 * r0 + i1 * r1 + i2 * r2, i3 * r0 + i4 * r1 + i5 * r2, i6 * r0 + i7 * r1 + i8 * r2
            t0, t1, t2 = i0 * g0 + i1 * g1 + i2 * g2, i3 * g0 + i4 * g1 + i5 * g2, i6 * g0 + i7 * g1 + i8 * g2
        H = dd - (g0 * t0 + g1 * t1 + g2 * t2)
        b = pr + py + dy_perp - (g0 * s0 + g1 * s1 + g2 * s2)  # (B d_w) . rho = (B w r + B y) . rho
        if not H > 0:
            return None
        chi2 = pp + yy - yy_b - b * b / H
        inflate = max(1.0, chi2 / self.dof)  # the model's mismatch with the device, beyond the noise
        part = self.others_part(yw, By, rho, rhs, sol, dd, H, b, chi2, k) if ext else None
        return (b / H, inflate / H, np.array((k * s0, k * s1, k * s2)), np.array((k * t0, k * t1, k * t2)),
                np.array((x_hat[0] * k, x_hat[1] * k, x_hat[2] * k)), part)

    def others_part(self, yw, By, rho, rhs, sol, dd, H00, b0, chi2, k) -> tuple | None:
        """The other states' measurement by the frame, the load's force and the scale profiled out (the
        Schur complements of the joint least squares over force, scale and others): their information ``H``
        (n_o, n_o), its vector ``b`` (``H^-1 b`` their estimate), inflated by the frame's misfit beyond the
        noise; and the force's step per unit of each, the scale held (3, n_o)."""
        Dy = self._Dw.dot(yw)
        BD = self._BD
        G = rhs[:, 1:]  # (3, 1 + n_o): J^T [d_w, D_o]
        Q = self._Q
        Q[0, 0] = dd
        Q[0, 1:] = Q[1:, 0] = self._Dr + Dy
        Hf = Q - G.T.dot(sol[:, 1:])  # (1 + n_o)^2: the states' information, the force profiled
        c = rho.dot(BD) + Dy - By.dot(BD) - G[:, 1:].T.dot(sol[:, 0])  # the others' vector
        h0 = Hf[1:, 0]
        Ho = Hf[1:, 1:] - h0[:, None] * h0 / H00  # ... and the scale profiled
        bo = c - h0 * (b0 / H00)
        try:
            est = solve_small(Ho, bo)
        except np.linalg.LinAlgError:
            return None
        inflate = max(1.0, (chi2 - float(bo.dot(est))) / self.dof)
        return Ho / inflate, bo / inflate, k * sol[:, 2:]
