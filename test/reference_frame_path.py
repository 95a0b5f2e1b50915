"""The per-frame formulations the fast path replaced, kept plain for the tests to hold the library
against (test_frame_path.py): the ``model`` estimator's Gauss-Newton fit through the spline's value
and Jacobian with ``numpy`` normal equations. The package uses none of them."""
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

