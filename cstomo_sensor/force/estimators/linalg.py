"""Small dense linear algebra of the per-frame path: 3 x 3 systems on Python floats (a few us where
``numpy.linalg`` takes ~8 us of checks and dispatch) and LAPACK's solve for the drift tracker's and the
joint fit's few states. No ROS, no serial."""
from __future__ import annotations

import numpy as np
from scipy.linalg import lapack


def solve_small(A: np.ndarray, B: np.ndarray) -> np.ndarray:
    """X with A X = B for a small square ``A`` (LAPACK's gesv without numpy.linalg's checks: 2 us
    instead of 7); raises ``LinAlgError`` if ``A`` is singular, as ``np.linalg.inv`` did."""
    _, _, X, info = lapack.dgesv(A, B)
    if info != 0:
        raise np.linalg.LinAlgError(f"singular matrix (gesv info {info})")
    return X


def cramer3(a, b, c, d, e, f, g, h, i, u, v, w) -> tuple[float, float, float] | None:
    """x with [[a, b, c], [d, e, f], [g, h, i]] x = [u, v, w] by Cramer's rule on Python floats (a
    few us, where ``np.linalg.solve`` takes ~8 us of overhead); None if the matrix is singular."""
    ei_fh, fg_di, dh_eg = e * i - f * h, f * g - d * i, d * h - e * g
    det = a * ei_fh + b * fg_di + c * dh_eg
    if not abs(det) > 0:
        return None
    return ((u * ei_fh + v * (c * h - b * i) + w * (b * f - c * e)) / det,
            (u * fg_di + v * (a * i - c * g) + w * (c * d - a * f)) / det,
            (u * dh_eg + v * (b * g - a * h) + w * (a * e - b * d)) / det)


def inverse3(a, b, c, d, e, f, g, h, i) -> list[float] | None:
    """The inverse of [[a, b, c], [d, e, f], [g, h, i]] as 9 floats by rows (its adjugate over its
    determinant, on Python floats); None if it is singular."""
    ei_fh, fg_di, dh_eg = e * i - f * h, f * g - d * i, d * h - e * g
    det = a * ei_fh + b * fg_di + c * dh_eg
    if not abs(det) > 0:
        return None
    r = 1.0 / det
    return [ei_fh * r, (c * h - b * i) * r, (b * f - c * e) * r,
            fg_di * r, (a * i - c * g) * r, (c * d - a * f) * r,
            dh_eg * r, (b * g - a * h) * r, (a * e - b * d) * r]
