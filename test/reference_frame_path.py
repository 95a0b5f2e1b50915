"""The per-frame formulations the fast path replaced, kept plain for the tests to hold the library
against (test_frame_path.py): the ``model`` estimator's Gauss-Newton fit through the spline's value
and Jacobian with ``numpy`` normal equations, and the drift tracker's update through a matrix
inverse. The package uses none of them."""
from __future__ import annotations

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


class PlainDriftTracker:
    """``DriftTracker``'s state update as it was: one gain ``P (I + info P)^-1`` through a matrix
    inverse for both kinds of frame (under load an information matrix and vector that are zero but
    for the scale's entry)."""

    def __init__(self, r, gradients, y, noise, keep) -> None:
        from cstomo_sensor.force.drift import LOAD_INFLATION, LOAD_RANK, REST_BOUND

        w = np.where(keep, 1.0 / np.asarray(noise, float), 0.0)
        D = np.atleast_2d(np.asarray(r, float))
        if gradients is not None:
            D = np.vstack([D, gradients])
        D = D * keep
        Dw = D * w
        U = np.linalg.svd(np.asarray(y) * w, full_matrices=False)[2][:LOAD_RANK]
        Du = Dw - (Dw @ U.T) @ U
        self.m, self._w, self._Dw = len(D), w, Dw
        self._N = Dw @ Dw.T
        self._Nu = np.zeros_like(self._N)
        self._Nu[0, 0] = Du[0] @ Du[0] / LOAD_INFLATION
        self._Du = np.zeros_like(Du)
        self._Du[0] = Du[0]
        self._inflation = LOAD_INFLATION
        self._rest = REST_BOUND * float(np.count_nonzero(keep))
        self._eye = np.eye(self.m)
        self.scale, self.gradient, self.P = 1.0, np.zeros(self.m - 1), np.zeros((self.m, self.m))

    def observe(self, y: np.ndarray, dt: float) -> bool:
        from cstomo_sensor.force.drift import RATE

        P = self.P + (RATE * RATE * dt) * self._eye
        yw = y * self._w
        b = self._Dw @ yw
        rest = float(yw @ yw) - b[0] * b[0] / self._N[0, 0] < self._rest
        info, vec = (self._N, b) if rest else (self._Nu, (self._Du @ yw) / self._inflation)
        gain = P @ np.linalg.inv(self._eye + info @ P)
        delta = gain @ vec
        if np.isfinite(delta).all():
            self.scale *= 1.0 + float(delta[0])
            self.gradient = self.gradient + delta[1:]
            P = gain
        self.P = 0.5 * (P + P.T)
        return rest
