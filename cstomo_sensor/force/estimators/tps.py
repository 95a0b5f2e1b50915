"""A thin-plate-spline interpolant with its analytic Jacobian, evaluated in one small product.

The same interpolant as ``scipy.interpolate.RBFInterpolator(points, values,
kernel="thin_plate_spline", degree=1)`` (no smoothing): ``s(x) = sum_i c_i phi(|x - p_i|) + d_0 +
d^T x`` with ``phi(r) = r^2 log r`` (0 at r = 0) and the coefficients solving

    [K  P] [c]   [values]
    [P' 0] [d] = [0     ],   K_ij = phi(|p_i - p_j|),  P = [1, p].

Its gradient is ``sum_i c_i (2 log r_i + 1) (x - p_i) + d`` (0 at r = 0, where phi is C^1). One
evaluation of the value and the 3 derivatives at one point is a single ``(m, n + 4) @ (n + 4, 4)``
product, where scipy's general evaluator takes about 25 us per call (and the finite-difference
Jacobian four calls): the ``model`` force estimator's Gauss-Newton steps use this.
"""
from __future__ import annotations

import numpy as np

from ...errors import ConfigError


class ThinPlateSpline:
    """Interpolant of ``values`` (n, m) at ``points`` (n, d) through a thin-plate spline of degree 1.

    Parameters
    ----------
    points : (n, d) ndarray
        Distinct nodes (n >= d + 1, not all on one hyperplane).
    values : (n, m) ndarray
        Values at the nodes.
    """

    def __init__(self, points: np.ndarray, values: np.ndarray) -> None:
        p = np.asarray(points, dtype=float)
        v = np.asarray(values, dtype=float)
        if p.ndim != 2 or v.ndim != 2 or len(p) != len(v) or len(p) < p.shape[1] + 1:
            raise ConfigError(f"points.shape={p.shape}, values.shape={v.shape}: expected (n, d) and (n, m) "
                              "with n >= d + 1")
        n, d = p.shape
        K = _phi(np.linalg.norm(p[:, None, :] - p[None, :, :], axis=-1))
        P = np.hstack([np.ones((n, 1)), p])
        A = np.block([[K, P], [P.T, np.zeros((d + 1, d + 1))]])
        rhs = np.vstack([v, np.zeros((d + 1, v.shape[1]))])
        try:
            coef = np.linalg.solve(A, rhs)  # (n + d + 1, m)
        except np.linalg.LinAlgError as err:
            raise ConfigError("thin-plate spline: singular system (repeated or coplanar points)") from err
        self.points = p
        self._A = A
        self.M = np.ascontiguousarray(coef.T)  # (m, n + 1 + d): [c | d_0 | d]
        # basis_rows' work arrays: the rows (1 + d, n + 1 + d) of basis values (row 0) and gradients (rows
        # 1..d), whose constant and linear parts are set once, x written into row 0's last d columns
        self._Bt = np.zeros((1 + d, n + 1 + d))
        self._Bt[0, n] = 1.0
        self._Bt[1:, n + 1:] = np.eye(d)
        self._basis_part, self._x_row = self._Bt[:, :n], self._Bt[0, n + 1:]
        self._d3 = d == 3
        # x - p_i as one product of the rows' own [x; I] block (transposed: [x | I]) and [1; -p^T] (exact:
        # the other terms are zeros); from the table of their squares and 1 (below), one product gives [r^2, r^2 / 2]
        # beside them: W = [r^2, r^2 / 2, x - p_i (d rows)]; then log r^2 in place, and the basis rows are W's last
        # d + 1 rows times log r^2 (one broadcast product): r^2 log r = (r^2 / 2) log r^2, and (log r^2) (x - p_i)
        # for the gradient's (2 log r + 1)(x - p_i) = (log r^2 + 1)(x - p_i): the coefficients c of the spline's
        # basis functions sum to zero with every node's coordinates as weights too (P^T c = 0, the system's last
        # rows), so the terms 1 (x - p_i) add nothing to the Jacobian (on the model estimator's spline they sum
        # to 2e-13 against coefficients of 300)
        self._xI = self._Bt[:, n + 1:].T
        self._P1 = np.vstack([np.ones(n), -p.T])
        self._sq = np.ones((d + 1, n))
        self._sq_d = self._sq[:d]
        # r^2 + 1e-300 (at a node, r^2 < 1e-284, it keeps the log finite: phi is 1e-300 log(1e-300)
        # there instead of 0, and x - p_i = 0)
        self._sums = np.array([[1.0] * d + [1e-300], [0.5] * d + [0.5e-300]])
        self._W = W = np.empty((d + 2, n))
        self._diff, self._factors, self._r2, self._sums_out = W[2:], W[1:], W[0], W[:2]
        self._Mt = np.ascontiguousarray(coef)  # (n + 1 + d, m)

    def __call__(self, x: np.ndarray) -> np.ndarray:
        """Values (k, m) at points ``x`` (k, d) (or (m,) at one point (d,))."""
        x = np.asarray(x, dtype=float)
        one = x.ndim == 1
        x2 = np.atleast_2d(x)
        r = np.linalg.norm(x2[:, None, :] - self.points[None], axis=-1)
        basis = np.hstack([_phi(r), np.ones((len(x2), 1)), x2])
        out = basis @ self.M.T
        return out[0] if one else out

    def basis_rows(self, x: np.ndarray) -> np.ndarray:
        """The (1 + d, n + 1 + d) rows whose product with the coefficients (:attr:`coefficients`,
        (n + 1 + d, m)) is the value (row 0) and the Jacobian's transpose (rows 1..d) at one point
        ``x`` (d floats): ``[phi(r_i) | 1 | x]`` and ``[2 log r_i (x - p_i) | 0 | I]`` (the gradient's
        ``(2 log r_i + 1)(x - p_i)`` without its ``x - p_i``, which the coefficients of this spline, and of
        any values at its nodes (:meth:`coefficients_of`), take to zero). A work array, overwritten by the
        next call."""
        xr = self._x_row
        if self._d3:  # (3 item assignments: half the cost of a slice's from a tuple)
            xr[0], xr[1], xr[2] = x
        else:
            xr[:] = x
        diff, r2 = self._diff, self._r2
        self._xI.dot(self._P1, out=diff)  # (d, n): x - p_i
        np.multiply(diff, diff, out=self._sq_d)
        self._sums.dot(self._sq, out=self._sums_out)
        np.log(r2, out=r2)
        np.multiply(self._factors, r2, out=self._basis_part)
        return self._Bt

    @property
    def coefficients(self) -> np.ndarray:
        """(n + 1 + d, m): ``[c; d_0; d]``, the right factor of :meth:`basis_rows`."""
        return self._Mt

    def coefficients_of(self, values: np.ndarray) -> np.ndarray:
        """(n + 1 + d, m): the coefficients of the spline of other ``values`` (n, m) at the same nodes
        (they are linear in the values: the derivative of :attr:`coefficients` along a change of them)."""
        v = np.asarray(values, dtype=float)
        if v.ndim != 2 or len(v) != len(self.points):
            raise ConfigError(f"values.shape={v.shape}: expected ({len(self.points)}, m), one row per node")
        return np.linalg.solve(self._A, np.vstack([v, np.zeros((self._A.shape[0] - len(v), v.shape[1]))]))

    def value_and_jacobian(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(value (m,), Jacobian (m, d)) at one point ``x`` (d,); the arrays are new."""
        out = self.basis_rows(x) @ self._Mt  # (1 + d, m)
        return out[0], out[1:].T


def _phi(r: np.ndarray) -> np.ndarray:
    """r^2 log r, 0 at r = 0."""
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(r > 0, r**2 * np.log(np.where(r > 0, r, 1.0)), 0.0)
