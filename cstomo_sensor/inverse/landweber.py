"""Landweber reconstruction: the iteration's closed form through the SVD, and the choice of k by
the discrepancy principle.

Pure linear algebra (numpy and scipy only); nothing here knows about meshes or electrodes. The
iteration itself (plain, weighted, the paper's adaptive step) runs only in the tests, as the slow,
plainly correct version the closed form is held against (test/reference_landweber.py).

The (damped) Landweber iteration from ``g_0 = 0`` is::

    g_{k+1} = g_k + step * (J^T (y - J g_k) - lam * g_k)

With the thin SVD ``J = U diag(s) V^T`` it has the closed form ``g_k = R_k y`` with::

    R_k = V diag(f_k) U^T,   f_k = s * (1 - (1 - step (s^2 + lam))^k) / (s^2 + lam)

which is stable (bounded in k) for ``0 < step <= 2 / (s_max^2 + lam)`` and converges for
``0 < step < 2 / (s_max^2 + lam)``; as ``k -> inf`` the factors tend to ``s / (s^2 + lam)``
(Tikhonov with parameter ``lam``, or the pseudo-inverse for ``lam = 0``). The factor is computed as
``-expm1(k * log1p(-step (s^2 + lam)))`` so that it is exact for huge ``k`` and tiny steps.
Singular values below ``rtol * s_max`` (the numerical rank of J; at most 104 of the 208 rows are
independent because of reciprocity) get factor 0.

Weighted (preconditioned) Landweber: with a positive weight ``w`` per unknown (``W = diag(w)``),
substitute ``g = W^(1/2) z`` and run the iteration above on ``A = J W^(1/2)`` for ``z``; in ``g`` it is::

    g_{k+1} = g_k + step * (W J^T (y - J g_k) - lam * g_k)

and its closed form is ``R_k = W^(1/2) V_A diag(f_k(s_A)) U_A^T`` through the SVD of ``A`` (step and
stability bound from ``s_max(A)``). The column-normalising weight ``w = diag(J^T J)^(-p)``
(:func:`column_weight`; NOSER and pyEIT's ``kotre`` prior) lifts the cells the data hardly sees
(deep ones) against those next to the electrodes; ``p = 0`` is the plain iteration.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import scipy.linalg

from ..errors import ConfigError, FrameError

__all__ = [
    "column_weight",
    "filter_factors",
    "LandweberSVD",
    "choose_by_discrepancy",
]

#: Steps within this relative distance above ``2 / (s_max^2 + lam)`` count as *at* the bound: the
#: largest singular value is computed by different LAPACK routines in different places and may
#: differ in the last few bits.
BOUND_RTOL = 1e-12


# --------------------------------------------------------------------------------------------------
# validation helpers
# --------------------------------------------------------------------------------------------------
def _check_matrix(J: np.ndarray, name: str = "J") -> np.ndarray:
    J = np.asarray(J, dtype=np.float64)
    if J.ndim != 2 or J.shape[0] == 0 or J.shape[1] == 0:
        raise ConfigError(f"{name}.shape={J.shape}: expected a non-empty 2-D (n_meas, n_cells) array")
    n_bad = int(np.count_nonzero(~np.isfinite(J)))
    if n_bad:
        raise ConfigError(f"{name} has {n_bad} non-finite values (NaN/Inf) of {J.size}")
    return J


def _check_data(y: np.ndarray, n_meas: int, *, allow_2d: bool = True,
                mask: np.ndarray | None = None) -> np.ndarray:
    """Validate a data vector (n_meas,) or a stack of them (n_meas, m); return float64 copy-or-view.

    With ``mask`` only the kept entries must be finite; dropped entries are replaced by 0.
    """
    y = np.asarray(y, dtype=np.float64)
    ok_ndim = (1, 2) if allow_2d else (1,)
    if y.ndim not in ok_ndim or y.shape[0] != n_meas:
        want = "(n_meas,) or (n_meas, m)" if allow_2d else "(n_meas,)"
        raise FrameError(f"y.shape={y.shape}: expected {want} with n_meas={n_meas}")
    finite = np.isfinite(y)
    if mask is not None:
        finite = finite | ~mask.reshape((-1,) + (1,) * (y.ndim - 1))
    n_bad = int(np.count_nonzero(~finite))
    if n_bad:
        raise FrameError(f"y has {n_bad} non-finite values (NaN/Inf) of {y.size}")
    if mask is not None and not mask.all():
        y = np.where(mask.reshape((-1,) + (1,) * (y.ndim - 1)), y, 0.0)
    return y


def _check_weight(weight: np.ndarray, n_cells: int) -> np.ndarray:
    w = np.asarray(weight, dtype=np.float64)
    if w.shape != (n_cells,) or not np.all(np.isfinite(w)) or not np.all(w > 0):
        raise ConfigError(f"weight.shape={w.shape}: expected ({n_cells},) positive finite values")
    return w


def column_weight(J: np.ndarray, power: float) -> np.ndarray:
    """The column-normalising weight ``w = diag(J^T J)^(-power)``, scaled to max 1.

    Columns whose norm is below ``1e-12`` of the largest count as that floor (no division by zero).

    Parameters
    ----------
    J : (n_meas, n_cells) ndarray
    power : float
        ``p >= 0``; 0 gives ones (the plain iteration), 0.5 NOSER's ``diag(J^T J)^(-1/2)``.

    Returns
    -------
    w : (n_cells,) float64 ndarray, in (0, 1].
    """
    J = _check_matrix(J)
    power = float(power)
    if not (math.isfinite(power) and 0.0 <= power <= 4.0):
        raise ConfigError.bad_value("weight_power", power, "a number in 0..4")
    d = np.einsum("ij,ij->j", J, J)
    d = np.maximum(d, 1e-12 * d.max()) if d.max() > 0 else np.ones_like(d)
    w = (d / d.max()) ** -power
    return w / w.max()


def _check_damping(damping: float) -> float:
    damping = float(damping)
    if not (math.isfinite(damping) and damping >= 0.0):
        raise ConfigError(f"damping={damping!r}: expected a finite value >= 0")
    return damping


def _check_n_iter(n_iter: int | float, allow_inf: bool) -> int | float:
    if isinstance(n_iter, (bool, np.bool_)):
        raise ConfigError(f"n_iter={n_iter!r}: expected an integer >= 0")
    try:
        value = float(n_iter)
    except (TypeError, ValueError) as err:
        raise ConfigError(f"n_iter={n_iter!r}: expected an integer >= 0") from err
    if value == math.inf and allow_inf:
        return math.inf
    if not math.isfinite(value) or value < 0 or value != int(value):
        allowed = "an integer >= 0 or float('inf')" if allow_inf else "an integer >= 0"
        raise ConfigError(f"n_iter={n_iter!r}: expected {allowed}")
    return int(value)


def _resolve_step(step: float | None, s_max: float, damping: float) -> float:
    """Default step 1/(s_max^2 + lam); refuse steps outside 0 < step <= 2/(s_max^2 + lam)."""
    scale = s_max * s_max + damping
    if step is None:
        if scale == 0.0:
            raise ConfigError("step=None with s_max=0 and damping=0: no default step (J is zero)")
        return 1.0 / scale
    step = float(step)
    bound = 2.0 / scale if scale > 0.0 else math.inf
    if not (math.isfinite(step) and step > 0.0 and step <= bound * (1.0 + BOUND_RTOL)):
        raise ConfigError(
            f"step={step!r} is outside the stability bound 0 < step <= 2/(s_max^2 + damping) = {bound!r} "
            f"(s_max={s_max!r}, damping={damping!r})"
        )
    return step


# --------------------------------------------------------------------------------------------------
# closed form
# --------------------------------------------------------------------------------------------------
def filter_factors(
    s: np.ndarray,
    n_iter: int | float,
    step: float | None = None,
    damping: float = 0.0,
    *,
    rtol: float = 1e-10,
) -> np.ndarray:
    """Filter factors ``f`` of the k-step Landweber matrix ``R_k = V diag(f) U^T``.

    ``f = s (1 - (1 - step (s^2 + lam))^k) / (s^2 + lam)``, computed as
    ``-expm1(k log1p(-step (s^2 + lam))) * s / (s^2 + lam)`` (exact for huge ``k`` and tiny steps;
    for ``step (s^2 + lam) > 1`` the base is negative and ``|base|^k`` carries the sign ``(-1)^k``).
    ``n_iter = inf`` gives the limit ``s / (s^2 + lam)`` (pseudo-inverse for ``lam = 0``).
    Singular values ``s <= rtol * max(s)`` get factor 0.

    Parameters
    ----------
    s : (r,) ndarray
        Singular values, finite and ``>= 0`` (any order).
    n_iter : int or float('inf')
        Number of iterations ``k >= 0``.
    step : float, optional
        Step; ``None`` means ``1 / (s_max^2 + lam)``. Must satisfy ``0 < step <= 2/(s_max^2 + lam)``;
        ``n_iter = inf`` needs the strict inequality (at the bound the top factor oscillates).
    damping : float
        ``lam >= 0``.
    rtol : float
        Relative rank tolerance.

    Returns
    -------
    f : (r,) float64 ndarray
    """
    s = np.asarray(s, dtype=np.float64)
    if s.ndim != 1:
        raise ConfigError(f"s.shape={s.shape}: expected 1-D singular values")
    if not np.all(np.isfinite(s)) or np.any(s < 0):
        raise ConfigError(f"s has {int(np.count_nonzero(~(np.isfinite(s) & (s >= 0))))} values that are "
                          f"negative or non-finite of {s.size}")
    rtol = float(rtol)
    if not (math.isfinite(rtol) and rtol >= 0.0):
        raise ConfigError(f"rtol={rtol!r}: expected a finite value >= 0")
    n_iter = _check_n_iter(n_iter, allow_inf=True)
    lam = _check_damping(damping)
    f = np.zeros_like(s)
    s_max = float(s.max()) if s.size else 0.0
    keep = s > rtol * s_max
    if not keep.any():
        if step is not None:
            _resolve_step(step, s_max, lam)
        return f
    step = _resolve_step(step, s_max, lam)
    sk = s[keep]
    denom = sk * sk + lam
    if n_iter == 0:
        return f
    a = step * denom  # in (0, 2]: the iteration contracts by (1 - a) along each singular direction
    if n_iter == math.inf:
        if step * (s_max * s_max + lam) >= 2.0:
            raise ConfigError(
                f"n_iter=inf with step={step!r} at the stability bound 2/(s_max^2 + damping)="
                f"{2.0 / (s_max * s_max + lam)!r}: the top factor oscillates and has no limit"
            )
        f[keep] = sk / denom
        return f
    k = float(n_iter)
    one_minus_qk = np.empty_like(sk)
    pos = a < 1.0  # base q = 1 - a in [0, 1)
    one_minus_qk[pos] = -np.expm1(k * np.log1p(-a[pos]))
    one_minus_qk[a == 1.0] = 1.0  # q = 0: one step reaches the limit (k >= 1 here)
    neg = a > 1.0  # q = -(a - 1) in [-1, 0): q^k = (-1)^k (a - 1)^k
    if neg.any():
        mag = np.exp(k * np.log(a[neg] - 1.0))
        sign = -1.0 if n_iter % 2 else 1.0
        one_minus_qk[neg] = 1.0 - sign * mag
    f[keep] = one_minus_qk * sk / denom
    return f


@dataclass(frozen=True, eq=False)
class LandweberSVD:
    """Thin SVD of a Jacobian truncated to its numerical rank; the Landweber matrix in closed form.

    Build it once with :meth:`from_jacobian`; then :meth:`matrix` gives ``R_k`` for any ``k``,
    step and damping in one matrix product, and :meth:`masked` handles dropped measurements.

    Attributes
    ----------
    U : (n_meas, rank) ndarray
        Left singular vectors; rows of dropped measurements (see :meth:`masked`) are zero.
    s : (rank,) ndarray
        Kept singular values, descending, all ``> rtol * s_max``.
    Vt : (rank, n_cells) ndarray
        Right singular vectors; with a weight ``w``, those of ``J W^(1/2)`` times ``W^(1/2)``
        (columns scaled by ``sqrt(w)``), so that ``R_k = Vt^T diag(f_k) U^T`` in every case.
    keep : (n_meas,) bool ndarray
        Measurements in use (all True unless built by :meth:`masked`).
    rtol : float
        Relative rank tolerance used to truncate.
    weight : (n_cells,) ndarray or None
        The weight of the weighted iteration (module docstring), None for the plain one.
    """

    U: np.ndarray = field(repr=False)
    s: np.ndarray = field(repr=False)
    Vt: np.ndarray = field(repr=False)
    keep: np.ndarray = field(repr=False)
    rtol: float = 1e-10
    weight: np.ndarray | None = field(default=None, repr=False)

    def __post_init__(self) -> None:
        U = np.array(self.U, dtype=np.float64)
        s = np.array(self.s, dtype=np.float64)
        Vt = np.array(self.Vt, dtype=np.float64)
        keep = np.array(self.keep, dtype=bool)
        if U.ndim != 2 or s.ndim != 1 or Vt.ndim != 2 or U.shape[1] != s.size or Vt.shape[0] != s.size:
            raise ConfigError(f"U.shape={U.shape}, s.shape={s.shape}, Vt.shape={Vt.shape}: expected "
                              "(n_meas, r), (r,), (r, n_cells)")
        if keep.shape != (U.shape[0],):
            raise ConfigError(f"keep.shape={keep.shape}: expected ({U.shape[0]},)")
        if s.size == 0:
            raise ConfigError("s is empty: J has numerical rank 0 (all singular values below rtol * s_max)")
        if not (np.all(np.isfinite(s)) and np.all(s > 0) and np.all(np.diff(s) <= 0)):
            raise ConfigError(f"s={s!r}: expected finite positive singular values in descending order")
        for name, arr in (("U", U), ("s", s), ("Vt", Vt), ("keep", keep)):
            arr.flags.writeable = False
            object.__setattr__(self, name, arr)
        if self.weight is not None:
            w = _check_weight(self.weight, Vt.shape[1]).copy()
            w.flags.writeable = False
            object.__setattr__(self, "weight", w)

    # ---- construction -------------------------------------------------------------------------
    @classmethod
    def from_jacobian(cls, J: np.ndarray, rtol: float = 1e-10, weight: np.ndarray | None = None) -> LandweberSVD:
        """Thin SVD of ``J`` (of ``J W^(1/2)`` with a weight) truncated to the singular values
        ``> rtol * s_max``.

        Parameters
        ----------
        J : (n_meas, n_cells) ndarray
            Jacobian, finite, not all zero.
        rtol : float
            Relative rank tolerance, ``0 <= rtol < 1``.
        weight : (n_cells,) ndarray, optional
            Positive weight per unknown: the closed form of the weighted iteration (module docstring).
        """
        J = _check_matrix(J)
        rtol = float(rtol)
        if not (math.isfinite(rtol) and 0.0 <= rtol < 1.0):
            raise ConfigError(f"rtol={rtol!r}: expected 0 <= rtol < 1")
        if weight is None:
            return cls._from_matrix(J, np.ones(J.shape[0], dtype=bool), rtol)
        w = _check_weight(weight, J.shape[1])
        d = np.sqrt(w)
        svd = cls._from_matrix(J * d, np.ones(J.shape[0], dtype=bool), rtol)
        return cls(U=svd.U, s=svd.s, Vt=svd.Vt * d, keep=svd.keep, rtol=rtol, weight=w)

    @classmethod
    def _from_matrix(cls, J: np.ndarray, keep: np.ndarray, rtol: float) -> LandweberSVD:
        try:
            U, s, Vt = scipy.linalg.svd(J, full_matrices=False, lapack_driver="gesdd")
        except np.linalg.LinAlgError:  # gesdd occasionally fails to converge; gesvd is slower but robust
            U, s, Vt = scipy.linalg.svd(J, full_matrices=False, lapack_driver="gesvd")
        if s.size == 0 or s[0] == 0.0:
            raise ConfigError(f"J.shape={J.shape} is all zero: numerical rank 0")
        r = int(np.count_nonzero(s > rtol * s[0]))
        return cls(U=U[:, :r], s=s[:r], Vt=Vt[:r], keep=keep, rtol=rtol)

    # ---- properties ---------------------------------------------------------------------------
    @property
    def n_meas(self) -> int:
        """Number of measurements (rows of ``J``, including dropped ones)."""
        return self.U.shape[0]

    @property
    def n_cells(self) -> int:
        """Number of cells (columns of ``J``)."""
        return self.Vt.shape[1]

    @property
    def rank(self) -> int:
        """Numerical rank (number of kept singular values)."""
        return int(self.s.size)

    @property
    def s_max(self) -> float:
        """Largest singular value."""
        return float(self.s[0])

    @property
    def condition(self) -> float:
        """Condition number ``s_max / s_min`` over the kept singular values."""
        return float(self.s[0] / self.s[-1])

    def __repr__(self) -> str:
        return (f"LandweberSVD(n_meas={self.n_meas}, n_cells={self.n_cells}, rank={self.rank}, "
                f"n_kept_meas={int(self.keep.sum())}, s_max={self.s_max:.6g}, condition={self.condition:.3g}, "
                f"rtol={self.rtol:g}, weighted={self.weight is not None})")

    # ---- the closed form ----------------------------------------------------------------------
    def factors(self, n_iter: int | float, step: float | None = None, damping: float = 0.0) -> np.ndarray:
        """Filter factors ``(rank,)`` for ``n_iter`` iterations (see :func:`filter_factors`)."""
        return filter_factors(self.s, n_iter, step, damping, rtol=0.0)

    def matrix(self, n_iter: int | float, step: float | None = None, damping: float = 0.0,
               dtype: np.dtype | type = np.float32) -> np.ndarray:
        """Reconstruction matrix ``R_k = V diag(f_k) U^T`` equal to ``n_iter`` Landweber iterations.

        Parameters
        ----------
        n_iter : int or float('inf')
            Iterations ``k >= 0``; ``inf`` gives the Tikhonov / pseudo-inverse limit.
        step : float, optional
            ``None`` means ``1 / (s_max^2 + damping)``; must satisfy ``0 < step <= 2/(s_max^2 + damping)``.
        damping : float
            ``lam >= 0``.
        dtype : floating dtype
            Of the result (computed in float64, then cast).

        Returns
        -------
        R : (n_cells, n_meas) ndarray
            Zero columns at dropped measurements.
        """
        dt = np.dtype(dtype)
        if dt.kind != "f":
            raise ConfigError(f"dtype={dt!r}: expected a floating dtype (float32 or float64)")
        f = self.factors(n_iter, step, damping)
        return ((self.Vt.T * f) @ self.U.T).astype(dt, copy=False)

    def masked(self, keep: np.ndarray) -> LandweberSVD:
        """The LandweberSVD of ``J[keep]`` with ``R`` expanded back to ``n_meas`` columns.

        Dropped measurements (a broken electrode, a saturated channel) get zero rows in ``U`` and so
        zero columns in every ``R_k``. This re-SVDs only the ``n_kept x rank`` matrix
        ``U[keep] diag(s)`` (then rotates ``Vt``), which is the same as re-SVDing the 208 x n_cells
        ``J[keep]`` up to the rank truncation, and takes milliseconds: the forward model and the
        Jacobian are not rebuilt. Masks compose: measurements dropped here stay dropped; a weight
        stays the same (that of the whole ``J``; ``Vt`` carries it linearly).

        Parameters
        ----------
        keep : (n_meas,) bool ndarray
            True for measurements to use.
        """
        keep = np.asarray(keep)
        if keep.shape != (self.n_meas,) or keep.dtype != bool:
            raise ConfigError(f"keep.shape={keep.shape}, keep.dtype={keep.dtype}: expected ({self.n_meas},) bool")
        keep = keep & self.keep
        if not keep.any():
            raise ConfigError("keep drops every measurement")
        B = self.U[keep] * self.s  # J[keep] = B @ Vt with orthonormal rows in Vt
        try:
            W, s2, Zt = scipy.linalg.svd(B, full_matrices=False, lapack_driver="gesdd")
        except np.linalg.LinAlgError:  # pragma: no cover
            W, s2, Zt = scipy.linalg.svd(B, full_matrices=False, lapack_driver="gesvd")
        if s2[0] == 0.0:
            raise ConfigError("J[keep] is zero: numerical rank 0")
        r = int(np.count_nonzero(s2 > self.rtol * s2[0]))
        U = np.zeros((self.n_meas, r))
        U[keep] = W[:, :r]
        return LandweberSVD(U=U, s=s2[:r], Vt=Zt[:r] @ self.Vt, keep=keep, rtol=self.rtol, weight=self.weight)

    # ---- residuals (for parameter choice) -----------------------------------------------------
    def _coefficients(self, y: np.ndarray) -> tuple[np.ndarray, float]:
        """``c = U^T y`` and ``||(I - U U^T) y||^2`` over the kept measurements."""
        y = _check_data(y, self.n_meas, allow_2d=False, mask=self.keep)
        c = self.U.T @ y
        perp = y - self.U @ c
        return c, float(perp @ perp)


# --------------------------------------------------------------------------------------------------
# parameter choice
# --------------------------------------------------------------------------------------------------
def _residual_norms(svd: LandweberSVD, c: np.ndarray, perp2: float, ks: np.ndarray,
                    step: float, damping: float) -> np.ndarray:
    """``||y - J g_k||`` for each k in ``ks`` from the SVD: ``sum((1 - s f_k)^2 c^2) + ||y_perp||^2``."""
    out = np.empty(len(ks))
    for i, k in enumerate(ks):
        f = svd.factors(int(k), step, damping)
        res = (1.0 - svd.s * f) * c
        out[i] = math.sqrt(float(res @ res) + perp2)
    return out


def choose_by_discrepancy(
    svd: LandweberSVD,
    y: np.ndarray,
    noise_norm: float,
    tau: float = 1.1,
    step: float | None = None,
    damping: float = 0.0,
    k_max: int = 10**6,
) -> int:
    """Number of iterations by Morozov's discrepancy principle.

    Rule: the smallest ``k >= 0`` with ``||y - J g_k|| <= tau * noise_norm``. The residual is
    evaluated in closed form through the SVD (``||y - J g_k||^2 = sum_i ((1 - s_i f_i) c_i)^2 +
    ||y_perp||^2`` with ``c = U^T y``) on a logarithmic grid of k up to ``k_max``, then the first
    crossing is located exactly by integer bisection. For ``damping = 0``, or when
    ``step <= 1/(s_max^2 + damping)``, the residual is non-increasing in k, so this is the smallest such
    k; otherwise it is a k whose residual is below and whose predecessor's is above.

    Parameters
    ----------
    svd : LandweberSVD
    y : (n_meas,) ndarray
        Data (finite at the kept measurements).
    noise_norm : float
        Euclidean norm of the noise in ``y`` (over the kept measurements), ``> 0``.
    tau : float
        Safety factor, ``> 0`` (``> 1`` as the theory asks; 1.1 by default).
    step, damping
        As in :meth:`LandweberSVD.matrix`.
    k_max : int
        Largest k tried.

    Returns
    -------
    k : int

    Raises
    ------
    ConfigError
        If even ``k_max`` iterations leave the residual above ``tau * noise_norm`` (the message names
        the residual floor: data outside the range of J can never be fitted).
    """
    noise_norm = float(noise_norm)
    tau = float(tau)
    if not (math.isfinite(noise_norm) and noise_norm > 0.0):
        raise ConfigError(f"noise_norm={noise_norm!r}: expected a finite value > 0")
    if not (math.isfinite(tau) and tau > 0.0):
        raise ConfigError(f"tau={tau!r}: expected a finite value > 0")
    k_max = _check_n_iter(k_max, allow_inf=False)
    if k_max < 1:
        raise ConfigError(f"k_max={k_max!r}: expected an integer >= 1")
    damping = _check_damping(damping)
    step = _resolve_step(step, svd.s_max, damping)
    c, perp2 = svd._coefficients(y)
    target = tau * noise_norm
    grid = np.unique(np.concatenate([[0], np.round(np.geomspace(1, k_max, 256)).astype(np.int64)]))
    res = _residual_norms(svd, c, perp2, grid, step, damping)
    hit = np.flatnonzero(res <= target)
    if hit.size == 0:
        floor = _residual_norms(svd, c, perp2, [k_max], step, damping)[0]
        raise ConfigError(
            f"discrepancy not reached: residual {floor!r} at k_max={k_max} > tau*noise_norm={target!r} "
            f"(residual floor outside the range of J: {math.sqrt(perp2)!r})"
        )
    i = int(hit[0])
    if i == 0:
        return 0
    lo, hi = int(grid[i - 1]), int(grid[i])  # res(lo) > target >= res(hi)
    while hi - lo > 1:
        mid = (lo + hi) // 2
        if _residual_norms(svd, c, perp2, [mid], step, damping)[0] <= target:
            hi = mid
        else:
            lo = mid
    return hi
