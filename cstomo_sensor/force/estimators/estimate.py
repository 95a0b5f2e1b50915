"""Force estimators, fitted on simulated socket loads through the model's own physics (the training
data, cached: force/estimators/training.py; the calibration never sees the honest-simulation meshes or seeds).

- ``linear`` (fastest): F = W y, ridge regression through the origin on the calibration set with
  noise augmentation (the device's noise measured by a tare of several frames, else 60 dB).
  One 3 x 208 product per frame (about a microsecond of arithmetic).
- ``model`` (the default, accurate): Gauss-Newton fit of the force vector to the frame through a thin-plate
  spline surrogate of the forward + mechanical model y(F) built on the calibration set (its value
  and analytic Jacobian in one small product, force/estimators/tps.py), started from the linear estimate
  (or, while the load moves within the noise, from the previous frame's fit moved by its own step for the
  frame's change: :data:`WARM_SIGMAS`); 2-4 steps, about 0.04 ms per frame at 60 dB (``cstomo bench
  --heldout``). The surrogate follows the
  device's resistivity gradients (the drift tracker's states, passed per frame) to first order
  (:func:`~.training.response_set`): a warmed block's gradient changes how a load shows in the voltages.

Both honour the bad-channel mask (``masked``), which refits the ridge map on the kept channels.
"""
from __future__ import annotations

import logging
import math
from typing import NamedTuple

import numpy as np

from ...errors import ConfigError
from ...inverse.reconstruction import ReconstructionModel
from ...model.geometry import SensorGeometry
from ...settings import ESTIMATORS
from .linalg import cramer3
from .tps import ThinPlateSpline
from .training import CalibrationSpec, calibration_set, response_set

log = logging.getLogger(__name__)


#: :meth:`ModelEstimator.estimate` keeps its surrogate's coefficients while the device's states it follows
#: move by less than this (relative resistivity per half extent: a load's response changes by 1e-4 of
#: itself, far below the noise; the 30-minute warm-up's gradient grows to 0.03).
STATE_TOLERANCE = 1e-4
#: :meth:`ModelEstimator.estimate` stops its Gauss-Newton iteration once a step is shorter than this (N): near
#: its solution each step is about a tenth of the one before, so the force is within about a tenth of it of the
#: iteration's limit whatever it started from (below the noise by more than three orders: 0.28 N at 60 dB).
STEP_TOLERANCE_N = 1e-4
#: ... and it starts from the previous fit's force moved by that fit's own step for the change since (its
#: Jacobian and normal matrix, :class:`ModelFit`: one 3 x k product and a 3 x 3 solve, where a step costs ~25 us)
#: while that move is within WARM_SIGMAS of the force's per-frame noise (at least WARM_MIN_N newtons): a held
#: load, a rest, a slow change start within a few hundredths of a newton of their solution (2-3 steps instead of
#: 4-5); a new load, the first frame, a frame after a fit that did not end finite start from the linear estimate,
#: as before. The start moves where the iteration stops only within STEP_TOLERANCE_N: the forces and every
#: by-product the slow states read (the fit's residual and Jacobian, :class:`ModelFit`) are the cold start's
#: to that tolerance.
WARM_SIGMAS, WARM_MIN_N = 6.0, 0.5


class LinearEstimator:
    """F = W y (ridge regression through the origin on the calibration set, kept channels only)."""

    name = "linear"

    def __init__(self, forces: np.ndarray, y: np.ndarray, noise: np.ndarray, ridge: float,
                 keep: np.ndarray | None = None) -> None:
        self.forces, self.y, self.noise, self.ridge = forces, y, noise, ridge
        self.keep = np.ones(y.shape[1], bool) if keep is None else keep
        Y = y[:, self.keep]
        # through the origin (no change, no force: a zero frame gives exactly zero); noise
        # augmentation in expectation adds n * diag(noise^2) to the normal matrix
        A = Y.T @ Y + len(Y) * np.diag(self.noise[self.keep] ** 2)
        A += ridge * np.trace(A) / len(A) * np.eye(len(A))
        Wk = np.linalg.solve(A, Y.T @ forces).T  # (3, n_keep)
        self.W = np.zeros((3, y.shape[1]))
        self.W[:, self.keep] = Wk

    def estimate(self, y: np.ndarray, state=None) -> np.ndarray:
        """The force (N) of the change ``y``; ``state`` (the device's, :class:`ModelEstimator`) is not used."""
        return self.W.dot(y)  # ndarray.dot: the frame path uses one kind of product, without np.dot's dispatch (issue 27)

    def masked(self, keep: np.ndarray) -> LinearEstimator:
        return LinearEstimator(self.forces, self.y, self.noise, self.ridge, keep)

    def with_set(self, forces: np.ndarray, y: np.ndarray) -> LinearEstimator:
        """The same estimator on another training set (a device calibration's corrected one)."""
        return LinearEstimator(forces, y, self.noise, self.ridge, self.keep)

    def with_noise(self, noise: np.ndarray) -> LinearEstimator:
        """The same estimator for a device whose per-channel noise (y units) is ``noise``."""
        return LinearEstimator(self.forces, self.y, noise, self.ridge, self.keep)


class ModelFit(NamedTuple):
    """A frame's fit (:attr:`ModelEstimator.last_fit`), valid until the next frame (its arrays are the
    estimator's work arrays): ``yw`` the change in noise units, ``by`` its coordinates in the fit's basis,
    ``step`` the last Gauss-Newton step and ``x`` the force (units of :attr:`ModelEstimator.scale`) it ended
    at, ``out`` (4, k) the residual's negative and the Jacobian's transpose at the iterate before that step,
    ``normal`` (3, 4) ``[-J^T r | J^T J]`` there. The joint fit of force and scale (force/estimators/scale_fit.py) and the
    force's sigma (force/slow_states/sigma.py) are made from it."""
    yw: np.ndarray
    by: np.ndarray
    step: tuple
    x: tuple
    out: np.ndarray
    normal: np.ndarray


class ModelEstimator:
    """Gauss-Newton fit of F to y through a radial-basis surrogate of the forward + mechanics.

    ``response`` (k, n, n_meas) or None: how each node's y changes per unit of k device states
    (:func:`response_set`: the resistivity gradients the drift tracker follows); the surrogate then
    follows the states :meth:`estimate` is given, to first order (its coefficients are linear in its
    node values: ``coef(g) = coef_0 + sum_k g_k C_k``)."""

    name = "model"

    def __init__(self, forces: np.ndarray, y: np.ndarray, noise: np.ndarray, ridge: float,
                 keep: np.ndarray | None = None, iterations: int = 6, response: np.ndarray | None = None) -> None:

        self.linear = LinearEstimator(forces, y, noise, ridge, keep)
        self.keep = self.linear.keep
        self.forces, self.y, self.noise, self.ridge = forces, y, noise, ridge
        self.response = response
        self.iterations = iterations
        self.scale = 10.0  # N: forces enter the surrogate in units of 10 N
        self._W_unit = self.linear.W / self.scale  # the linear estimate's map in those units
        yk = y[:, self.keep]
        self.w = 1.0 / self.noise[self.keep]
        # the fit runs in noise units (y * w), in the subspace that the calibration's weighted
        # changes span down to 1e-3 of the noise (rms over the set): the surrogate's outputs lie in
        # the span of its nodes' values, so the Gauss-Newton steps are those of the full residual
        # to within 1e-3 noise units per load; ~50 of the 208 coordinates
        yw = yk * self.w
        _, s, vt = np.linalg.svd(yw, full_matrices=False)
        self.basis = vt[: max(3, int(np.count_nonzero(s / np.sqrt(len(yw)) > 1e-3)))]  # (k, n_keep)
        self.surrogate = ThinPlateSpline(forces / self.scale, yw @ self.basis.T)  # value + Jacobian (tps.py)
        self._all_kept = bool(self.keep.all())
        self._yw = np.empty(len(self.w))  # estimate()'s work arrays
        self._out = np.empty((4, len(self.basis)))
        self._jt, self._out_t = self._out[1:], self._out.T  # its views, made once
        self._G = np.empty((3, 4))
        # the spline's coefficients with the frame's target taken from its constant term (row n),
        # so that one product gives the residual (with its sign changed) and the Jacobian
        n = len(forces)
        self._coef0 = self.surrogate.coefficients
        self._coef = self._coef0.copy()
        self._d0, self._d0_target = self._coef0[n].copy(), self._coef[n]
        # ... and their change per unit state (response), and the state they are for
        self._dcoef = None if response is None else np.array(
            [self.surrogate.coefficients_of((r[:, self.keep] * self.w) @ self.basis.T) for r in response]
        ).reshape(len(response), -1)  # (k, (n + 4) m): one product gives the change of every coefficient
        self._state = None
        self.last_fit: ModelFit | None = None
        # the warm start's bound (WARM_SIGMAS): the force's per-frame noise (N, the linear estimate's 1-sigma of
        # its norm), in units of scale, squared
        Wn = self.linear.W * np.where(self.keep, self.noise, 0.0)
        self._warm2 = (max(WARM_MIN_N, WARM_SIGMAS * float(np.sqrt(np.sum(Wn * Wn)))) / self.scale) ** 2
        self._warm: ModelFit | None = None  # the fit the next frame starts from (None: the linear estimate)

    def _follow(self, state) -> None:
        """The surrogate's coefficients for the device ``state`` (None: the nominal device), unless it
        is within :data:`STATE_TOLERANCE` of the one they are for (a few microseconds otherwise)."""
        now, tol = self._state, STATE_TOLERANCE
        if state is None or now is None:
            if state is now:
                return
        else:
            for a, b in zip(state, now):
                if not -tol <= a - b <= tol:
                    break
            else:
                return
        coef = self._coef
        if state is None:
            coef[:] = self._coef0
        else:
            np.dot(state, self._dcoef, out=coef.reshape(-1))  # (state: 3 floats, a list)
            coef += self._coef0
        self._d0[:] = coef[len(self.forces)]
        self._state = None if state is None else tuple(state)

    def estimate(self, y: np.ndarray, state=None) -> np.ndarray:
        """The force (N) of the change ``y`` (n_meas,); ``state``: the device's states the surrogate
        follows (``response``; the drift tracker's resistivity gradients, 3 floats; None: nominal)."""
        if self._dcoef is not None:
            self._follow(state)
        yw = np.multiply(y, self.w, out=self._yw) if self._all_kept else y[self.keep] * self.w
        by = self.basis.dot(yw)
        x = None
        fit = self._warm
        if fit is not None:  # a warm start (WARM_SIGMAS): the previous fit's force moved by its step for the change since
            (_, a, b, c), (_, d, e, f), (_, g, h, i) = fit.normal.tolist()
            v0, v1, v2 = fit.out[1:].dot(by - fit.by).tolist()  # (its work arrays: read before this fit writes them)
            dx = cramer3(a, b, c, d, e, f, g, h, i, v0, v1, v2)
            if dx is not None and dx[0] * dx[0] + dx[1] * dx[1] + dx[2] * dx[2] < self._warm2:
                px = fit.x
                x = (px[0] + dx[0], px[1] + dx[1], px[2] + dx[2])
        if x is None:
            x = self._W_unit.dot(y).tolist()  # the linear estimate, in units of scale: Python floats through the iteration
        np.subtract(self._d0, by, out=self._d0_target)
        spline, coef, out, tol2 = self.surrogate, self._coef, self._out, (STEP_TOLERANCE_N / self.scale) ** 2
        jt, out_t, G = self._jt, self._out_t, self._G
        for _ in range(self.iterations):
            # the residual's negative -r (row 0 of out) and the Jacobian's transpose (rows 1..3) in
            # one product, then the normal equations in one more: G = [-J^T r | J^T J]
            spline.basis_rows(x).dot(coef, out=out)
            jt.dot(out_t, out=G)
            (u, a, b, c), (v, d, e, f), (w, g, h, i) = G.tolist()
            step = cramer3(a, b, c, d, e, f, g, h, i, -u, -v, -w)
            if step is None:  # a flat surrogate (far outside the calibration): least squares
                step = np.linalg.lstsq(out[1:].T, -out[0], rcond=None)[0].tolist()
            s0, s1, s2 = step
            x = (x[0] + s0, x[1] + s1, x[2] + s2)
            if not s0 * s0 + s1 * s1 + s2 * s2 >= tol2:  # |step| < 1e-4 N (or NaN: stop)
                break
        self.last_fit = fit = ModelFit(yw, by, step, x, out, G)
        self._warm = fit if math.isfinite(x[0] + x[1] + x[2]) else None  # the next frame's start
        k = self.scale
        return np.array((x[0] * k, x[1] * k, x[2] * k))

    def forget(self) -> None:
        """The next frame starts from the linear estimate (:data:`WARM_SIGMAS`), as a fresh estimator's."""
        self._warm = None

    def _like(self, forces, y, noise, keep) -> ModelEstimator:
        return ModelEstimator(forces, y, noise, self.ridge, keep, self.iterations, self.response)

    def masked(self, keep: np.ndarray) -> ModelEstimator:
        return self._like(self.forces, self.y, self.noise, keep)

    def with_set(self, forces: np.ndarray, y: np.ndarray) -> ModelEstimator:
        """The same estimator on another training set (a device calibration's corrected one: the same
        loads, row by row, so the same ``response``)."""
        return self._like(forces, y, self.noise, self.keep)

    def with_noise(self, noise: np.ndarray) -> ModelEstimator:
        """The same estimator for a device whose per-channel noise (y units) is ``noise``."""
        return self._like(self.forces, self.y, noise, self.keep)


def build_estimator(name: str, geometry: SensorGeometry, model: ReconstructionModel, cache_dir=None,
                    progress=None, spec: CalibrationSpec = CalibrationSpec()):
    """The estimator called ``name`` ('linear' or 'model'), calibrated (cached) for ``model``."""
    if name not in ESTIMATORS:
        raise ConfigError.bad_value("estimator", name, f"one of {list(ESTIMATORS)}")
    if geometry.socket_radius <= 0:
        raise ConfigError(f"sensor {geometry.name!r} has no socket: force estimation needs one")
    forces, y = calibration_set(geometry, model, spec, cache_dir, progress)
    # the unloaded state is a calibration point too: no load, no change
    forces, y = np.vstack([np.zeros(3), forces]), np.vstack([np.zeros(y.shape[1]), y])
    if name == "linear":
        return LinearEstimator(forces, y, model.snr_noise(spec.noise_db), spec.ridge)
    dy = response_set(geometry, model, spec, cache_dir, progress)
    response = np.concatenate([np.zeros((len(dy), 1, y.shape[1])), dy], axis=1)
    return ModelEstimator(forces, y, model.snr_noise(spec.noise_db), spec.ridge, response=response)

