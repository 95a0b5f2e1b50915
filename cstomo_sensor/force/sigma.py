"""Every force with its error bar: the 1-sigma uncertainty of a frame's force (issue 26, item 3).

The force's error covariance of one frame, from the same estimate that gave the force::

    cov_F = W S W^T  +  (W D_F) P (W D_F)^T  +  (e |W r| (s - 1))^2 / 3 I  +  (k |F|)^2 / 3 I  +  (u W o)(u W o)^T

- ``W`` (3, n_meas): the estimator's map of a change to a force near the frame's load (``linear``: the
  estimator itself; ``model``: its own Gauss-Newton fit's, ``k (J^T J)^-1 J^T B w``: ``J`` the
  surrogate's Jacobian at the force found, ``B`` the fit's basis, ``w`` the channels' weights, ``k`` its
  force unit; so ``W S W^T = k^2 (1 + 1/N) (J^T J)^-1``, the fit's Cramer-Rao bound. Its linear part,
  the ridge regression it starts from, is about 2x as sensitive to the noise and to the states below:
  the robot bench's device_b read 0.76 N of noise through it where its forces scatter by 0.37 N);
- ``S``: the per-channel noise of the change, the frame's and the reference's (``change_noise`` of
  the estimator's ``noise``: measured by the tare, estimated from the frames, or assumed);
- ``P``: the drift tracker's covariance of its measured states (the scale, the contacts' and the
  gradient's), after this frame's predict and update: it grows while the joint is loaded (nothing is
  measured then), so a loaded warm-up's forces carry a growing sigma. ``D_F`` the states' directions
  in the change (``r = V_ref / y_scale`` for the scale, the contacts' and the gradient's directions),
  the scale's plus the load's own change (a scale error ``d`` scales the load's change too:
  ``W (d (r + y))``; ``= d (W r + F)`` for ``linear``). Without drift tracking this term is absent (nothing is tracked, and
  the drift is not in the error bar);
- ``e``: :data:`UNDESCRIBED`, the share of the tracked uniform change ``s - 1`` (its force ``W r (s - 1)``)
  that the tracker's directions do not describe; isotropic;
- ``k``: the calibration's residual, a relative error of the force's norm (isotropic): from a device
  calibration's cross-validated 90th percentiles of the magnitude and angle errors over its n loads,
  taken at their 90 % upper bound (:func:`relative_error`), else the nominal model's stated held-out accuracy
  (:data:`NOMINAL_ACCURACY`, docs/benchmark.md: for the nominal sensor; a device off the nominal one
  without calibration is worse, up to 40 % in magnitude);
- the creep compensation's: ``o`` the creep offset the frame was corrected by, ``u`` the relative
  uncertainty of its coefficient (:data:`CREEP_REL_ASSUMED` for the assumed 2..6 % per decade,
  :data:`CREEP_REL_FITTED` for a calibration's fitted one).

What is constant (``W S W^T``, ``W D``; for ``model`` ``B w D``) is computed when the estimator or the
tracker changes (a reference, a noise, a mask, a calibration); per frame: for ``model`` the fit's
(3, k) (k, m) product and one 3 x 3 solve, then a (3, m) (m, m) product, and for the creep its
offset through the map. ``sigma`` is the square root of the diagonal (fx, fy, fz), ``sigma_n`` of its
trace: the rms of the force error's norm. Not included: a foreign load, a change of the device none of
the tracker's directions describe (beyond :data:`UNDESCRIBED`), the model's mismatch with the device
beyond the calibration's residual, the filter (``~/wrench_filtered`` has no sigma).
"""
from __future__ import annotations

import math

import numpy as np

from .joint import solve_small

#: The nominal model's held-out accuracy (docs/benchmark.md, the nominal sensor at 60 dB): angle deg,
#: magnitude % (median) per estimator; the sigma of an uncalibrated stream takes this as its
#: calibration residual (a median of a normal's absolute value is 0.674 of its sigma).
NOMINAL_ACCURACY = {"model": (0.5, 0.8), "linear": (0.8, 2.0)}
#: The part of the tracked uniform change that the tracker's directions do not describe (a real
#: device's contacts, a gradient that is not linear, a scale of 10 % and more): a relative error of the
#: change's own force ``W r (s - 1)``, isotropic (issue 26: the 30-minute warm-up, 12 % by its end on
#: the robot bench's devices, read up to 2 N at rest where the tracker's covariance said 0.2 N; now
#: p99 1.1 N on device_b, 0.7 N on device_a, at 12 %: 0.0025 of the model estimator's own map).
UNDESCRIBED = 0.0025
#: A normal's 90th percentile of |x| in sigmas, and a 2-D one's (Rayleigh) of its norm.
_P90_1D, _P90_2D, _P50_1D, _P50_2D = 1.645, 2.146, 0.674, 1.177
#: Relative 1-sigma of the creep coefficient: assumed (uniform over 2..6 % around 4 %: 1.15 / 4), and
#: fitted by a calibration (its held loads: assumed 10 %).
CREEP_REL_ASSUMED = 0.29
CREEP_REL_FITTED = 0.10


def relative_error(calibration, estimator: str) -> tuple[float, str]:
    """(k, where it comes from): the rms of the force error's norm over ``|F|`` that the calibration's
    residual leaves (its radial and two tangential components). A calibration with a cross-validated
    ``after``: from its 90th percentiles; else :data:`NOMINAL_ACCURACY` (medians)."""
    cv = getattr(calibration, "cv", None) or {}
    after = cv.get("after") if calibration is not None else None
    if after:
        # a p90 of n held-out loads is a sample: its sigma's one-sided 90 % upper bound (chi-square of n
        # degrees of freedom, Wilson-Hilferty), so that loads the calibration never saw are covered too
        # (n = 20: 1.27 x; the robot bench's device a read 1.6-2 % of its frames beyond 3 sigma without it)
        n = max(int(cv.get("judged_loads") or cv.get("loads") or 0), 2)
        h = 2.0 / (9.0 * n)
        bound = (1.0 - h - 1.2816 * math.sqrt(h)) ** -1.5
        mag = bound * after["magnitude_pct_p90"] / 100.0 / _P90_1D
        ang = bound * math.radians(after["angle_deg_p90"]) / _P90_2D
        where = f"calibration {calibration.path or ''} (cross-validated p90 of {n} loads)".replace("  ", " ")
    else:
        a, m = NOMINAL_ACCURACY.get(estimator, NOMINAL_ACCURACY["linear"])
        mag, ang = m / 100.0 / _P50_1D, math.radians(a) / _P50_2D
        where = "the nominal model's held-out accuracy (docs/benchmark.md)" if calibration is None else \
            f"the nominal model's held-out accuracy (calibration {calibration.path} not cross-validated)"
    return math.sqrt(mag * mag + 2.0 * ang * ang), where


class ForceSigma:
    """The per-frame uncertainty of one estimator and tracker (module docstring).

    Parameters
    ----------
    W : (3, n_meas) ndarray
        The estimator's linear map (zero on excluded channels).
    noise : (n_meas,) ndarray
        Per-channel noise std of the change (y units).
    keep : (n_meas,) bool ndarray
    D : (m, n_meas) ndarray or None
        The tracker's measured states' directions (the scale's first), or None without tracking.
    k_rel : float
        The calibration's relative residual (:func:`relative_error`).
    creep_rel : float
        The creep coefficient's relative 1-sigma (0: no creep term).
    """

    def __init__(self, W: np.ndarray, noise: np.ndarray, keep: np.ndarray, D: np.ndarray | None,
                 k_rel: float, creep_rel: float = 0.0, estimator=None) -> None:
        W = np.asarray(W, float) * keep
        Wn = W * np.where(keep, noise, 0.0)
        self.noise_var = np.einsum("ij,ij->i", Wn, Wn).tolist()  # diag(W S W^T)
        self.W = np.ascontiguousarray(W)
        self.WD = None
        if D is not None:  # (3, m + 1): the tracker's measured states, then its rate (no direction of its own)
            D = np.asarray(D, float)
            self.WD = np.zeros((3, len(D) + 1))
            self.WD[:, :len(D)] = W @ D.T
            self._WDT = np.ascontiguousarray(self.WD.T)
            self._change2 = UNDESCRIBED ** 2 * float(self.WD[:, 0].dot(self.WD[:, 0])) / 3.0
        self.k2 = float(k_rel) ** 2 / 3.0
        self.creep_rel = float(creep_rel)
        # the model estimator's own map of a change near the frame's load (its Gauss-Newton fit's:
        # ``k (J^T J)^-1 J^T B w``), in place of its linear part's ``W``
        self.est = estimator if getattr(estimator, "name", None) == "model" else None  # the model estimator
        self._loc, self._loc_for = None, None
        if self.est is not None:
            est = self.est
            kept = np.asarray(est.keep, bool)
            self._all_kept = bool(kept.all())
            self._Bw = np.ascontiguousarray(est.basis * est.w)  # (k, n_keep): a change into the fit's basis
            self._kept = kept
            # the change's noise in the fit's units (1 + 1/N: the frame's and the reference's)
            self._noise_w2 = float(np.mean((np.asarray(noise, float)[kept] * est.w) ** 2))
            self._BwX = None  # the states' directions in the basis: r + y (y set per frame), the others, r
            m = 0
            if D is not None:
                m = len(D)
                BwD = self._Bw @ (D[:, kept] * keep[kept]).T  # (k, m)
                self._Bwr = np.ascontiguousarray(BwD[:, 0])
                self._BwX = np.ascontiguousarray(np.hstack([BwD, BwD[:, :1]]))
                self._WDl = np.zeros((3, m + 1))  # the states' force map, then the rate's (none)
            self._n0 = n0 = m + 1 if D is not None else 0  # where (J^T J)^-1 starts in the solution
            self._rhs = np.zeros((3, n0 + 3))
            self._rhs[:, n0:] = np.eye(3)

    def _local(self):
        """(noise variances (3,), the states' force map (3, m + 1) with the load's own scale change or
        None, the undescribed change's variance per axis over (s - 1)^2) of the model estimator's latest
        fit; None (no fit yet, a singular fit: the linear part's map then). The solution ``X`` of the
        fit's normal equations is kept (:meth:`creep_force`)."""
        est = self.est
        fit = est.last_fit
        if fit is None:
            return None
        if fit is self._loc_for:
            return self._loc
        k, n0, rhs = est.scale, self._n0, self._rhs
        Jt = fit.out[1:]  # (3, k): the Jacobian's transpose at the fit's last iterate (force/joint.py)
        BwX = self._BwX
        if BwX is not None:
            col = BwX[:, 0]
            col[:] = fit.by  # B w y: a scale error scales the load's change too
            col += self._Bwr
            rhs[:, :n0] = Jt.dot(BwX)
        try:  # the last iteration's J^T J
            X = solve_small(fit.normal[:, 1:], rhs)
        except np.linalg.LinAlgError:
            self._loc, self._loc_for = None, fit
            return None
        self._X = X
        x = X.tolist()
        c = k * k * self._noise_w2
        noise_var = [c * x[0][n0], c * x[1][n0 + 1], c * x[2][n0 + 2]]
        WD, change2 = None, 0.0
        if BwX is not None:
            m = n0 - 1
            WD = self._WDl
            np.multiply(X[:, :m], k, out=WD[:, :m])
            change2 = UNDESCRIBED ** 2 * k * k * (x[0][m] ** 2 + x[1][m] ** 2 + x[2][m] ** 2) / 3.0
        self._loc, self._loc_for = (noise_var, WD, change2), fit
        return self._loc

    def creep_force(self, offset: np.ndarray) -> np.ndarray:
        """The force of a creep offset (n_meas,): ``W o`` (taken before the compensator moves on; the
        model estimator's own map near the frame's load when it has one)."""
        loc = self._local() if self.est is not None else None
        if loc is None:
            return self.W.dot(offset)
        o = offset if self._all_kept else np.asarray(offset, float)[self._kept]
        return self.est.scale * self._X[:, self._n0:].dot(self.est.last_fit.out[1:].dot(self._Bw.dot(o)))

    def __call__(self, force: np.ndarray, P: np.ndarray | None, creep_force: np.ndarray | None = None,
                 change: float = 0.0) -> tuple[tuple[float, float, float], float]:
        """((sigma fx, fy, fz), sigma_n) of a frame's ``force`` (3,), the tracker's covariance ``P``
        ((m+1, m+1): its measured states, then the scale's rate; None: no tracking), the force of the
        creep offset the frame was corrected by (:meth:`creep_force`; None: none) and the tracked
        uniform change ``s - 1`` (:data:`UNDESCRIBED`)."""
        f = force.tolist()
        cal = self.k2 * (f[0] * f[0] + f[1] * f[1] + f[2] * f[2])
        loc = self._local() if self.est is not None else None
        noise_var = self.noise_var if loc is None else loc[0]
        v = [x + cal for x in noise_var]
        if P is not None and self.WD is not None:
            if loc is not None:  # the local map's scale column has the load's own change already
                WD = loc[1]
                G = WD.dot(P)
                M = G.dot(WD.T).tolist()
                c2 = loc[2] * change * change
                for i in range(3):
                    v[i] += M[i][i] + c2
            else:
                # (WD + f e0^T) P (WD + f e0^T)^T: a scale error scales the load's change too; its diagonal
                G = self.WD.dot(P)
                M = G.dot(self._WDT).tolist()
                u = G[:, 0].tolist()
                p00 = float(P[0, 0])
                c2 = self._change2 * change * change
                for i in range(3):
                    v[i] += M[i][i] + 2.0 * f[i] * u[i] + p00 * f[i] * f[i] + c2
        if creep_force is not None and self.creep_rel:
            c = creep_force.tolist()
            r2 = self.creep_rel * self.creep_rel
            for i in range(3):
                v[i] += r2 * c[i] * c[i]
        v0, v1, v2 = (max(x, 0.0) for x in v)
        return (math.sqrt(v0), math.sqrt(v1), math.sqrt(v2)), math.sqrt(v0 + v1 + v2)
