"""The slow, plainly correct Landweber solvers the tests hold the library's closed form against
(cstomo_sensor/inverse/landweber.py): the iteration itself (plain, weighted, the paper's adaptive
step), ``g_k = R_k y`` through a :class:`LandweberSVD` without forming ``R_k``, and the choice of
the damping by generalised cross-validation. The package uses none of them; their input checks are
the library's own, so the tests of its validation hold for them too.
"""
from __future__ import annotations

import logging
import math
from collections.abc import Callable

import numpy as np
import scipy.linalg
import scipy.optimize

from cstomo_sensor.errors import ConfigError
from cstomo_sensor.inverse.landweber import (
    LandweberSVD,
    _check_damping,
    _check_data,
    _check_matrix,
    _check_n_iter,
    _check_weight,
    _resolve_step,
)

log = logging.getLogger(__name__)


def landweber(
    J: np.ndarray,
    y: np.ndarray,
    n_iter: int,
    step: float | None = None,
    damping: float = 0.0,
    adaptive: bool = False,
    callback: Callable[[int, np.ndarray], None] | None = None,
    weight: np.ndarray | None = None,
) -> np.ndarray:
    """Run the (damped, optionally weighted) Landweber iteration from ``g = 0``.

    Fixed step::

        g_{k+1} = g_k + step * (W J^T (y - J g_k) - damping * g_k)

    with ``W = diag(weight)`` (identity without a weight), stable for
    ``0 < step <= 2 / (s_max^2 + damping)`` (bounded; convergent for strict ``<``), ``s_max`` being
    the largest singular value of ``J W^(1/2)``. ``step=None`` means ``1 / (s_max^2 + damping)``.
    ``k`` fixed-step iterations equal :func:`apply` (the library's closed form, built with the same
    weight).

    Adaptive step (``adaptive=True``, the paper's equation (24)): with ``Q_k = y - J g_k``,
    ``alpha_k = ||J^T Q_k||^2 / ||J J^T Q_k||^2`` and ``g_{k+1} = g_k + alpha_k J^T Q_k``, i.e.
    steepest descent with exact line search on ``||y - J g||^2 / 2`` (the residual never grows).
    With ``damping > 0`` this module uses the damped analogue: ``r_k = J^T Q_k - damping g_k`` and
    ``alpha_k = ||r_k||^2 / (||J r_k||^2 + damping ||r_k||^2)``, exact line search on
    ``(||y - J g||^2 + damping ||g||^2) / 2``; it reduces to equation (24) for ``damping = 0``.
    The iteration stops early (returning the current ``g``) when ``r_k`` is exactly zero, i.e. a zero
    residual or ``J^T Q_k = 0`` for ``damping = 0``, where ``alpha_k`` would be 0/0.

    Parameters
    ----------
    J : (n_meas, n_cells) ndarray
        Jacobian (sensitivity matrix), finite.
    y : (n_meas,) ndarray, or (n_meas, m) ndarray for the fixed step
        Data; several columns are iterated at once (``y = I`` gives the matrix ``R_k``).
    n_iter : int
        Number of iterations, ``>= 0``.
    step : float, optional
        Fixed step; must be ``None`` with ``adaptive=True``.
    damping : float
        Tikhonov damping ``lam >= 0``.
    adaptive : bool
        Use the paper's adaptive step (see above).
    callback : callable ``(k, g) -> None``, optional
        Called after iteration ``k = 1 .. n_iter`` with a read-only view of ``g``.
    weight : (n_cells,) ndarray, optional
        Positive finite weight per unknown (fixed step only), e.g. :func:`column_weight`.

    Returns
    -------
    g : (n_cells,) or (n_cells, m) float64 ndarray

    Raises
    ------
    ConfigError
        Bad shapes, non-finite ``J``, negative ``damping``/``n_iter``, or a step outside the bound.
    FrameError
        ``y`` has the wrong length or contains NaN/Inf.
    """
    J = _check_matrix(J)
    n_meas, n_cells = J.shape
    y = _check_data(y, n_meas, allow_2d=not adaptive)
    n_iter = _check_n_iter(n_iter, allow_inf=False)
    damping = _check_damping(damping)
    g = np.zeros((n_cells,) + y.shape[1:])
    view = g.view()
    view.flags.writeable = False

    if adaptive:
        if weight is not None:
            raise ConfigError("weight with adaptive=True: the weighted iteration has a fixed step")
        if step is not None:
            raise ConfigError(f"step={step!r} with adaptive=True: the adaptive step is computed, pass step=None")
        for k in range(1, n_iter + 1):
            r = J.T @ (y - J @ g) - damping * g
            num = float(r @ r)
            if num == 0.0:
                log.debug("adaptive Landweber stopped at k=%d: zero gradient (0/0 step)", k - 1)
                break
            Jr = J @ r
            den = float(Jr @ Jr) + damping * num
            if den == 0.0:  # pragma: no cover - r in range(J^T) makes J r = 0 imply r = 0
                break
            g += (num / den) * r
            if callback is not None:
                callback(k, view)
        return g

    w = np.ones(n_cells) if weight is None else _check_weight(weight, n_cells)
    w = w.reshape((-1,) + (1,) * (y.ndim - 1))
    if n_iter > 0 or step is not None:
        step = _resolve_step(step, float(scipy.linalg.norm(J * np.sqrt(w.ravel()), 2)), damping)
    for k in range(1, n_iter + 1):
        g += step * (w * (J.T @ (y - J @ g)) - damping * g)
        if callback is not None:
            callback(k, view)
    return g


def apply(svd: LandweberSVD, y: np.ndarray, n_iter: int | float, step: float | None = None,
          damping: float = 0.0) -> np.ndarray:
    """``g_k = R_k y`` of the library's closed form (``svd``'s filter factors) in float64 without
    forming ``R_k``.

    Parameters
    ----------
    svd : LandweberSVD
    y : (n_meas,) or (n_meas, m) ndarray
        Data; entries at dropped measurements are ignored (they may be NaN), the others must be finite.
    n_iter, step, damping
        As in :meth:`LandweberSVD.matrix`.

    Returns
    -------
    g : (n_cells,) or (n_cells, m) float64 ndarray
    """
    y = _check_data(y, svd.n_meas, mask=svd.keep)
    f = svd.factors(n_iter, step, damping)
    c = svd.U.T @ y
    return svd.Vt.T @ (f.reshape((-1,) + (1,) * (c.ndim - 1)) * c)


def choose_by_gcv(
    svd: LandweberSVD,
    y: np.ndarray,
    lam_min: float | None = None,
    lam_max: float | None = None,
    n_grid: int = 200,
) -> float:
    """Damping ``lam`` (with ``k = inf``, i.e. Tikhonov) by generalised cross-validation.

    Rule: minimise ``GCV(lam) = ||y - J g_lam||^2 / (m - sum_i s_i^2 / (s_i^2 + lam))^2`` with
    ``g_lam = V diag(s / (s^2 + lam)) U^T y`` and ``m`` the number of kept measurements, first on
    a logarithmic grid of ``n_grid`` values in ``[lam_min, lam_max]`` (default
    ``[(s_min/10)^2, (10 s_max)^2]``), then by a bounded scalar minimisation of ``GCV`` in
    ``log lam`` between the neighbours of the best grid point. Deterministic.

    Parameters
    ----------
    svd : LandweberSVD
    y : (n_meas,) ndarray
    lam_min, lam_max : float, optional
        Search interval, ``0 < lam_min < lam_max``.
    n_grid : int
        Grid size, ``>= 3``.

    Returns
    -------
    lam : float
    """
    c, perp2 = svd._coefficients(y)
    s2 = svd.s * svd.s
    lo = float(lam_min) if lam_min is not None else float(s2[-1]) / 100.0
    hi = float(lam_max) if lam_max is not None else float(s2[0]) * 100.0
    if not (math.isfinite(lo) and math.isfinite(hi) and 0.0 < lo < hi):
        raise ConfigError(f"lam_min={lo!r}, lam_max={hi!r}: expected 0 < lam_min < lam_max, finite")
    if int(n_grid) != n_grid or n_grid < 3:
        raise ConfigError(f"n_grid={n_grid!r}: expected an integer >= 3")
    m = int(np.count_nonzero(svd.keep))

    def gcv(log_lam: float) -> float:
        lam = math.exp(log_lam)
        shrink = lam / (s2 + lam)  # 1 - s f for k = inf
        res2 = float(np.sum((shrink * c) ** 2)) + perp2
        dof = m - float(np.sum(s2 / (s2 + lam)))
        return res2 / (dof * dof)

    logs = np.linspace(math.log(lo), math.log(hi), int(n_grid))
    values = np.array([gcv(t) for t in logs])
    i = int(np.argmin(values))
    a, b = logs[max(i - 1, 0)], logs[min(i + 1, len(logs) - 1)]
    best = scipy.optimize.minimize_scalar(gcv, bounds=(a, b), method="bounded",
                                          options={"xatol": 1e-6})
    t = float(best.x) if best.fun <= values[i] else float(logs[i])
    return math.exp(t)
