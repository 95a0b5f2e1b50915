"""Landweber: the closed form against the plain iteration, numerical extremes, masking, parameter choice.

Expected values come from the plain iteration (a slow, obviously correct loop, with the other
test-only solvers in reference_landweber.py), from matrices built
with known singular values, or from analytic limits; never from numbers the closed form produced.
"""
from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from reference_landweber import apply, choose_by_gcv, landweber

from cstomo_sensor.errors import ConfigError, FrameError
from cstomo_sensor.inverse.landweber import LandweberSVD, choose_by_discrepancy, column_weight, filter_factors

N_MEAS, N_CELLS, RANK = 208, 120, 104


def orthogonal(rng: np.random.Generator, n: int) -> np.ndarray:
    q, r = np.linalg.qr(rng.standard_normal((n, n)))
    return q * np.sign(np.diag(r))


def known_matrix(s: np.ndarray, m: int, n: int, seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """J = U diag(s) V^T with U, V random orthogonal; s padded with exact zeros."""
    rng = np.random.default_rng(seed)
    U, V = orthogonal(rng, m), orthogonal(rng, n)
    S = np.zeros((m, n))
    S[np.arange(len(s)), np.arange(len(s))] = s
    return U @ S @ V.T, U, V


@pytest.fixture(scope="module")
def rank_deficient():
    """208 x 120, singular values geometric 1 .. 1e-8 (104 of them), then exact zeros (reciprocity)."""
    s = np.geomspace(1.0, 1e-8, RANK)
    J, U, V = known_matrix(s, N_MEAS, N_CELLS, seed=1)
    return J, s


@pytest.fixture(scope="module")
def svd(rank_deficient):
    return LandweberSVD.from_jacobian(rank_deficient[0])


def rel(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.linalg.norm(a - b) / np.linalg.norm(b))


# ---- closed form == iterations ---------------------------------------------------------------
@pytest.mark.parametrize("damping_rel", [0.0, 1e-3, 0.1])
def test_closed_form_matrix_equals_iterations(rank_deficient, svd, damping_rel):
    J, s = rank_deficient
    lam = damping_rel * s[0] ** 2
    step = 1.0 / (s[0] ** 2 + lam)  # s_max = 1 by construction
    ks = (1, 7, 50, 400)
    snapshots = {}

    def grab(k, g):
        if k in ks:
            snapshots[k] = g.copy()

    # Iterating on the identity gives R_k column by column (the slow, plainly correct version).
    landweber(J, np.eye(N_MEAS), max(ks), step=step, damping=lam, callback=grab)
    assert sorted(snapshots) == list(ks)
    assert svd.rank == RANK
    for k in ks:
        R = svd.matrix(k, step=step, damping=lam, dtype=np.float64)
        assert R.shape == (N_CELLS, N_MEAS)
        assert rel(R, snapshots[k]) < 1e-6, f"k={k}, lam={lam}, rel={rel(R, snapshots[k])}"


def test_default_step_matches_between_iteration_and_closed_form(rank_deficient, svd):
    J, _ = rank_deficient
    y = np.random.default_rng(3).standard_normal(N_MEAS)
    for lam in (0.0, 0.05):
        g_it = landweber(J, y, 30, damping=lam)
        g_cf = apply(svd, y, 30, damping=lam)
        assert rel(g_cf, g_it) < 1e-10


def test_filter_factors_match_naive_power_formula():
    s = np.array([2.0, 1.0, 0.3, 1e-3, 0.0])
    lam, step, k = 0.01, 0.2, 37
    a = step * (s[:4] ** 2 + lam)
    naive = s[:4] * (1 - (1 - a) ** k) / (s[:4] ** 2 + lam)
    f = filter_factors(s, k, step, lam)
    np.testing.assert_allclose(f[:4], naive, rtol=1e-12)
    assert f[4] == 0.0


@settings(max_examples=60, deadline=None)
@given(
    m=st.integers(1, 9),
    n=st.integers(1, 9),
    sv=st.lists(st.floats(0.2, 3.0), min_size=9, max_size=9),
    k=st.integers(1, 200),
    step_frac=st.floats(0.05, 1.95),
    lam_rel=st.sampled_from([0.0, 1e-3, 0.3]),
    seed=st.integers(0, 2**16),
)
def test_property_closed_form_equals_iterations(m, n, sv, k, step_frac, lam_rel, seed):
    r = min(m, n)
    s = np.sort(np.array(sv[:r]))[::-1]
    J, _, _ = known_matrix(s, m, n, seed)
    lam = lam_rel * s[0] ** 2
    step = step_frac / (s[0] ** 2 + lam)  # inside the bound 2/(s_max^2 + lam)
    y = np.random.default_rng(seed + 1).standard_normal(m)
    g_it = landweber(J, y, k, step=step, damping=lam)
    g_cf = apply(LandweberSVD.from_jacobian(J), y, k, step=step, damping=lam)
    assert np.allclose(g_cf, g_it, rtol=1e-6, atol=1e-9 * np.linalg.norm(g_it)), (g_cf, g_it)


# ---- exact and limiting cases ----------------------------------------------------------------
def test_zero_data_gives_exact_zero(rank_deficient, svd):
    J, _ = rank_deficient
    y = np.zeros(N_MEAS)
    assert not np.any(apply(svd, y, 50))
    assert not np.any(apply(svd, y, math.inf, damping=0.1))
    assert not np.any(landweber(J, y, 20))
    assert not np.any(landweber(J, y, 20, adaptive=True))


def test_k1_is_step_times_transpose(rank_deficient, svd):
    J, _ = rank_deficient
    step = 0.7
    R1 = svd.matrix(1, step=step, dtype=np.float64)
    np.testing.assert_allclose(R1, step * J.T, rtol=0, atol=1e-13)
    assert not np.any(svd.matrix(0, dtype=np.float64))


def test_huge_k_reaches_analytic_limits_without_overflow():
    s = np.geomspace(1.0, 1e-8, RANK)
    k, step = 10**6, 1.0  # step = 1/s_max^2
    f = filter_factors(s, k, step, 0.0)
    assert np.all(np.isfinite(f))
    big = s >= 1e-2  # (1 - s^2)^k <= exp(-100): pseudo-inverse factor 1/s
    np.testing.assert_allclose(f[big], 1.0 / s[big], rtol=1e-12)
    small = s <= 1e-6  # k step s^2 <= 1e-6: f = k step s (1 - k step s^2 / 2 + ...)
    np.testing.assert_allclose(f[small], k * step * s[small], rtol=1e-6)
    tiny = s <= 1e-7
    np.testing.assert_allclose(f[tiny], k * step * s[tiny] * (1 - k * step * s[tiny] ** 2 / 2), rtol=1e-12)
    # Damped: every factor tends to the Tikhonov factor s/(s^2 + lam) (contraction 1 - step*lam per step).
    lam = 1e-3
    fd = filter_factors(s, k, 1.0 / (1.0 + lam), lam)
    np.testing.assert_allclose(fd, s / (s**2 + lam), rtol=1e-12)
    np.testing.assert_allclose(filter_factors(s, math.inf, None, lam), s / (s**2 + lam), rtol=1e-12)
    np.testing.assert_allclose(filter_factors(s, math.inf), 1.0 / s, rtol=1e-12)


def test_tiny_step_is_exact_to_first_order():
    s = np.array([1.0, 1e-4])
    step, k = 1e-20, 1000
    np.testing.assert_allclose(filter_factors(s, k, step), k * step * s, rtol=1e-12)


@pytest.mark.parametrize("lam", [0.0, 0.1])
def test_step_at_bound_stays_bounded_and_above_is_refused(rank_deficient, svd, lam):
    J, s = rank_deficient
    bound = 2.0 / (s[0] ** 2 + lam)
    top = s[0] / (s[0] ** 2 + lam)
    for k in (10**6, 10**6 + 1):
        f = svd.factors(k, bound, lam)
        assert np.all(np.isfinite(f))
        # the top direction has base 1 - bound (s_max^2 + lam) = -1: factor 0 for even k, 2 s/(s^2+lam) odd
        expected = 0.0 if k % 2 == 0 else 2 * top
        # (s_max from the SVD differs from 1 in the last bits; |base|^k then drifts by ~k eps)
        assert f[0] == pytest.approx(expected, abs=1e-7 * top)
        assert np.all(np.abs(f) <= 2 * s[: svd.rank] / (s[: svd.rank] ** 2 + lam) * (1 + 1e-9))
    y = np.random.default_rng(5).standard_normal(N_MEAS)
    g = landweber(J, y, 200, step=bound, damping=lam)
    assert np.all(np.isfinite(g))
    assert np.linalg.norm(g) < 1e3 * np.linalg.norm(apply(svd, y, 200, damping=lam))
    above = bound * 1.001
    for call in (lambda: svd.matrix(10, step=above, damping=lam),
                 lambda: landweber(J, y, 10, step=above, damping=lam),
                 lambda: svd.matrix(10, step=-1.0)):
        with pytest.raises(ConfigError, match=r"step=.*stability bound"):
            call()
    with pytest.raises(ConfigError, match="oscillates"):
        svd.matrix(math.inf, step=bound, damping=lam)


def test_ill_conditioned_jacobian_is_finite():
    s = np.geomspace(1.0, 1e-12, 60)
    J, _, _ = known_matrix(s, 80, 120, seed=11)
    svd = LandweberSVD.from_jacobian(J, rtol=1e-13)
    assert svd.condition > 1e11, f"condition={svd.condition:.3g}"
    y = np.random.default_rng(12).standard_normal(80)
    for k in (1, 1000, 10**6, math.inf):
        g = apply(svd, y, k)
        R = svd.matrix(k)
        assert np.all(np.isfinite(g)) and np.all(np.isfinite(R)), f"k={k}, condition={svd.condition:.3g}"


def test_float32_matrix_agrees_with_float64(rank_deficient, svd):
    J, _ = rank_deficient
    rng = np.random.default_rng(7)
    y = J @ rng.standard_normal(N_CELLS) + 1e-3 * rng.standard_normal(N_MEAS)
    for k, lam in ((50, 0.0), (400, 1e-3)):
        R32 = svd.matrix(k, damping=lam)
        assert R32.dtype == np.float32
        g32 = R32.astype(np.float64) @ y.astype(np.float32).astype(np.float64)
        g32_native = R32 @ y.astype(np.float32)
        g64 = svd.matrix(k, damping=lam, dtype=np.float64) @ y
        assert rel(g32, g64) < 1e-5
        assert rel(g32_native.astype(np.float64), g64) < 1e-5


# ---- validation ------------------------------------------------------------------------------
@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
def test_non_finite_data_is_refused(rank_deficient, svd, bad):
    J, _ = rank_deficient
    y = np.ones(N_MEAS)
    y[[3, 17]] = bad
    with pytest.raises(FrameError, match="2 non-finite"):
        apply(svd, y, 10)
    with pytest.raises(FrameError, match="2 non-finite"):
        landweber(J, y, 10)
    with pytest.raises(FrameError, match="2 non-finite"):
        choose_by_discrepancy(svd, y, 1.0)


def test_shapes_and_options_are_validated(rank_deficient, svd):
    J, _ = rank_deficient
    with pytest.raises(FrameError, match=r"y.shape=\(207,\)"):
        apply(svd, np.ones(207), 3)
    with pytest.raises(ConfigError, match="n_iter"):
        svd.matrix(-1)
    with pytest.raises(ConfigError, match="n_iter"):
        svd.matrix(2.5)
    with pytest.raises(ConfigError, match="damping"):
        svd.matrix(3, damping=-1.0)
    with pytest.raises(ConfigError, match="non-finite"):
        LandweberSVD.from_jacobian(np.where(np.eye(3) > 0, np.nan, 1.0))
    with pytest.raises(ConfigError, match="rank 0"):
        LandweberSVD.from_jacobian(np.zeros((4, 3)))
    with pytest.raises(ConfigError, match="adaptive"):
        landweber(J, np.ones(N_MEAS), 3, step=0.5, adaptive=True)
    with pytest.raises(ConfigError, match="dtype"):
        svd.matrix(3, dtype=np.int32)


# ---- masking ---------------------------------------------------------------------------------
def test_masked_matrix_has_zero_columns_and_equals_direct_svd(rank_deficient, svd):
    J, _ = rank_deficient
    keep = np.ones(N_MEAS, dtype=bool)
    keep[[0, 5, 13, 100, 207]] = False
    msvd = svd.masked(keep)
    direct = LandweberSVD.from_jacobian(J[keep])
    assert msvd.rank == direct.rank
    assert msvd.s_max == pytest.approx(direct.s_max, rel=1e-12)
    for k, lam in ((1, 0.0), (50, 0.0), (400, 1e-3), (math.inf, 1e-2)):
        R = msvd.matrix(k, damping=lam, dtype=np.float64)
        assert R.shape == (N_CELLS, N_MEAS)
        assert not np.any(R[:, ~keep])
        Rd = direct.matrix(k, damping=lam, dtype=np.float64)
        assert rel(R[:, keep], Rd) < 1e-8, f"k={k}, lam={lam}"
    # Independent of any SVD: k iterations on the kept rows.
    y = np.random.default_rng(9).standard_normal(N_MEAS)
    step = 1.0 / direct.s_max**2
    np.testing.assert_allclose(apply(msvd, y, 50, step=step), landweber(J[keep], y[keep], 50, step=step),
                               rtol=1e-8, atol=1e-12)
    # NaN at a dropped measurement is ignored; at a kept one it is refused.
    y_bad = y.copy()
    y_bad[5] = np.nan
    assert np.all(np.isfinite(apply(msvd, y_bad, 50)))
    y_bad[6] = np.nan
    with pytest.raises(FrameError, match="1 non-finite"):
        apply(msvd, y_bad, 50)


# ---- weighted (preconditioned) Landweber --------------------------------------------------------
@pytest.mark.parametrize("power, damping_rel", [(0.5, 0.0), (1.0, 0.0), (0.75, 0.05)])
def test_weighted_closed_form_equals_weighted_iterations(rank_deficient, power, damping_rel):
    """The slow version iterates g += step (W J^T (y - J g) - lam g) on the identity (R_k column by
    column); the closed form goes through the SVD of J W^(1/2)."""
    J, _ = rank_deficient
    J = J * np.geomspace(1.0, 1e-3, N_CELLS)  # columns of very different norms, as deep voxels have
    w = column_weight(J, power)
    assert w.max() == 1.0 and w.min() < 1e-2  # the weight does something
    svd = LandweberSVD.from_jacobian(J, weight=w)
    a_max = np.linalg.norm(J * np.sqrt(w), 2)
    lam = damping_rel * a_max**2
    step = 1.0 / (a_max**2 + lam)
    ks = (1, 9, 60)
    snapshots = {}
    landweber(J, np.eye(N_MEAS), max(ks), step=step, damping=lam, weight=w,
              callback=lambda k, g: snapshots.__setitem__(k, g.copy()) if k in ks else None)
    for k in ks:
        R = svd.matrix(k, step=step, damping=lam, dtype=np.float64)
        assert rel(R, snapshots[k]) < 1e-6, f"k={k}, p={power}, rel={rel(R, snapshots[k])}"
    R1 = svd.matrix(1, step=step, dtype=np.float64)  # one step: step W J^T exactly
    np.testing.assert_allclose(R1, step * w[:, None] * J.T, rtol=0, atol=1e-12 * np.abs(R1).max())


def test_weight_power_zero_gives_the_plain_matrix_exactly(rank_deficient, svd):
    J, _ = rank_deficient
    w = column_weight(J, 0.0)
    assert np.array_equal(w, np.ones(N_CELLS))
    weighted = LandweberSVD.from_jacobian(J, weight=w)
    for k in (1, 37, 10**6):  # equal to rounding, scaled to the matrix (BLAS kernels differ between machines)
        R = svd.matrix(k, dtype=np.float64)
        np.testing.assert_allclose(weighted.matrix(k, dtype=np.float64), R, rtol=0, atol=1e-12 * np.abs(R).max())
    G = landweber(J, np.eye(N_MEAS)[:, :3], 5)
    np.testing.assert_allclose(landweber(J, np.eye(N_MEAS)[:, :3], 5, weight=w), G, rtol=0, atol=1e-12 * np.abs(G).max())


def test_weighted_huge_k_reaches_the_weighted_pseudo_inverse():
    """k = 10^6 only through the closed form: the limit is W^(1/2) pinv(J W^(1/2)) (numpy's pinv)."""
    rng = np.random.default_rng(5)
    J = known_matrix(np.geomspace(1.0, 1e-2, 30), 40, 30, seed=5)[0] * rng.uniform(0.1, 1.0, 30)
    w = column_weight(J, 0.5)
    svd = LandweberSVD.from_jacobian(J, weight=w)
    R = svd.matrix(10**6, dtype=np.float64)
    limit = np.sqrt(w)[:, None] * np.linalg.pinv(J * np.sqrt(w))
    assert np.all(np.isfinite(R)) and rel(R, limit) < 1e-9
    assert not np.any(apply(svd, np.zeros(40), 10**6))  # zero input gives exactly zero
    assert not np.any(landweber(J, np.zeros(40), 30, weight=w))


def test_weighted_masked_equals_direct_and_bad_weights_are_refused(rank_deficient):
    J, _ = rank_deficient
    w = column_weight(J, 0.5)
    keep = np.ones(N_MEAS, dtype=bool)
    keep[[3, 77, 150]] = False
    y = np.random.default_rng(8).standard_normal(N_MEAS)
    msvd = LandweberSVD.from_jacobian(J, weight=w).masked(keep)
    step = 1.0 / msvd.s_max**2
    np.testing.assert_allclose(apply(msvd, y, 40, step=step), landweber(J[keep], y[keep], 40, step=step, weight=w),
                               rtol=1e-8, atol=1e-12)
    for bad in (-w, np.where(np.arange(N_CELLS) == 4, np.nan, w), w[:-1]):
        with pytest.raises(ConfigError, match="weight"):
            LandweberSVD.from_jacobian(J, weight=bad)
        with pytest.raises(ConfigError, match="weight"):
            landweber(J, y, 3, weight=bad)
    with pytest.raises(ConfigError, match="adaptive"):
        landweber(J, y, 3, adaptive=True, weight=w)
    for power in (-0.5, np.nan, 5.0):
        with pytest.raises(ConfigError, match="weight_power"):
            column_weight(J, power)


# ---- adaptive step ---------------------------------------------------------------------------
def test_adaptive_residual_decreases_monotonically():
    s = np.geomspace(1.0, 1e-3, 20)
    J, _, _ = known_matrix(s, 30, 25, seed=21)
    y = np.random.default_rng(22).standard_normal(30)
    residuals = [np.linalg.norm(y)]
    landweber(J, y, 300, adaptive=True, callback=lambda k, g: residuals.append(np.linalg.norm(y - J @ g)))
    res = np.array(residuals)
    assert len(res) == 301
    assert np.all(np.diff(res) <= 1e-12 * res[0]), np.diff(res).max()
    assert res[-1] < 0.9 * res[0]
    # The paper's step is exact line search: it beats (or ties) the fixed step 1/s_max^2 after one step.
    g1 = landweber(J, y, 1, adaptive=True)
    g1_fixed = landweber(J, y, 1)
    assert np.linalg.norm(y - J @ g1) <= np.linalg.norm(y - J @ g1_fixed) + 1e-15


def test_adaptive_stops_at_exact_zero_residual():
    # J = 2 [I 0]: the first adaptive step alpha = 1/4 fits y exactly (powers of two, no rounding);
    # the next alpha would be 0/0.
    J = np.hstack([2.0 * np.eye(4), np.zeros((4, 3))])
    y = np.array([1.0, -3.0, 0.5, 7.0])
    seen = []
    g = landweber(J, y, 10, adaptive=True, callback=lambda k, g: seen.append(k))
    assert seen == [1]
    assert np.all(np.isfinite(g))
    assert np.array_equal(J @ g, y)
    # Data orthogonal to the range of J: J^T Q = 0 at once.
    Jz = np.vstack([np.eye(3), np.zeros((1, 3))])
    g = landweber(Jz, np.array([0.0, 0.0, 0.0, 1.0]), 5, adaptive=True)
    assert np.array_equal(g, np.zeros(3))


def test_adaptive_damped_analogue_converges_to_tikhonov():
    s = np.geomspace(1.0, 0.1, 8)
    J, _, _ = known_matrix(s, 10, 8, seed=31)
    y = np.random.default_rng(32).standard_normal(10)
    lam = 0.05
    g = landweber(J, y, 2000, damping=lam, adaptive=True)
    tik = np.linalg.solve(J.T @ J + lam * np.eye(8), J.T @ y)
    np.testing.assert_allclose(g, tik, rtol=1e-8)


# ---- parameter choice ------------------------------------------------------------------------
def test_discrepancy_picks_first_k_below_tau_noise():
    m, n = 60, 40
    s = np.geomspace(1.0, 1e-3, n)
    J, U, V = known_matrix(s, m, n, seed=41)
    rng = np.random.default_rng(42)
    g_true = V[:, :n] @ (np.sqrt(s) * rng.standard_normal(n))  # satisfies a Picard condition
    noise = 3e-4 * rng.standard_normal(m)  # chosen so that k lies where the log grid is coarse (bisection)
    y = J @ g_true + noise
    tau, step = 1.1, 1.0
    eta = float(np.linalg.norm(noise))
    k = choose_by_discrepancy(LandweberSVD.from_jacobian(J), y, eta, tau=tau, step=step)
    assert k == choose_by_discrepancy(LandweberSVD.from_jacobian(J), y, eta, tau=tau, step=step)
    assert 300 < k < 20000, k
    residuals = [float(np.linalg.norm(y))]
    landweber(J, y, k, step=step, callback=lambda i, g: residuals.append(float(np.linalg.norm(y - J @ g))))
    assert residuals[k] <= tau * eta < residuals[k - 1], (k, residuals[k - 1], residuals[k], tau * eta)
    with pytest.raises(ConfigError, match="discrepancy not reached"):
        choose_by_discrepancy(LandweberSVD.from_jacobian(J), y, eta, tau=0.1, step=step, k_max=1000)
    # Data already inside the noise level: no iteration.
    assert choose_by_discrepancy(LandweberSVD.from_jacobian(J), noise, 1.2 * eta / tau, tau=tau) == 0


def test_gcv_picks_lambda_near_error_optimum():
    m, n = 120, 80
    s = np.geomspace(1.0, 1e-4, n)
    J, U, V = known_matrix(s, m, n, seed=51)
    rng = np.random.default_rng(52)
    g_true = V[:, :n] @ (s * rng.standard_normal(n))
    y = J @ g_true + 1e-3 * rng.standard_normal(m)
    lam = choose_by_gcv(LandweberSVD.from_jacobian(J), y)
    assert lam == choose_by_gcv(LandweberSVD.from_jacobian(J), y)
    # The error-optimal lam, found independently by normal equations on a fine grid.
    grid = np.geomspace(1e-10, 1.0, 201)
    errs = [np.linalg.norm(np.linalg.solve(J.T @ J + t * np.eye(n), J.T @ y) - g_true) for t in grid]
    best = grid[int(np.argmin(errs))]
    assert best / 30 < lam < best * 30, (lam, best)
