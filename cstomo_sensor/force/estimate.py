"""Force estimators, calibrated on simulated socket loads through the model's own physics.

Calibration (once per sensor and reconstruction model, cached): forces on a Fibonacci set of
directions (elevation 15..90 deg, every azimuth) and several magnitudes (1..40 N) are pushed through
the mechanics (frictionless socket contact; one solve per direction, as the contact problem is
positively homogeneous in the force; :func:`socket_mechanics`, cached and shared with the scene
field), the material law and the forward model on the
reconstruction's mesh, giving normalised voltage changes y (README, *Numerical choices*, and the reconstruction
module for the normalisation). The calibration never sees the honest-simulation meshes or seeds.

- ``linear`` (fastest): F = W y, ridge regression through the origin on the calibration set with
  noise augmentation (the device's noise measured by a tare of several frames, else 60 dB).
  One 3 x 208 product per frame (about a microsecond of arithmetic).
- ``model`` (the default, accurate): Gauss-Newton fit of the force vector to the frame through a thin-plate
  spline surrogate of the forward + mechanical model y(F) built on the calibration set (its value
  and analytic Jacobian in one small product, force/tps.py), started from the linear estimate;
  3-4 steps, about 0.04 ms per frame at 60 dB (``cstomo bench --heldout``). The surrogate follows the
  device's resistivity gradients (the drift tracker's states, passed per frame) to first order
  (:func:`response_set`): a warmed block's gradient changes how a load shows in the voltages.

Both honour the bad-channel mask (``masked``), which refits the ridge map on the kept channels.
"""
from __future__ import annotations

import hashlib
import logging
import time
from dataclasses import dataclass
from pathlib import Path
from typing import NamedTuple

import numpy as np

from ..cache import cache_load, cache_save, default_cache_dir, input_hash
from ..errors import ConfigError
from ..inverse.reconstruction import ReconstructionModel
from ..model import elasticity
from ..model.cem import ForwardModel
from ..model.geometry import DEFAULT_SNR_DB, SensorGeometry
from ..model.material import conductivity_of_theta
from ..model.mesh import MeshSpec, TetMesh, build_mesh
from .joint import gradient_coordinates
from .small import cramer3
from .tps import ThinPlateSpline

log = logging.getLogger(__name__)

CALIB_FORMAT = 1
MECHANICS_FORMAT = 1
RESPONSE_FORMAT = 1
#: The resistivity gradients' state (relative per half extent) at which the load's response to them is
#: taken (:func:`response_set`).
RESPONSE_STEP = 0.03


@dataclass(frozen=True)
class CalibrationSpec:
    n_directions: int = 40
    #: 1 N: without it the ``model`` estimator's spline between the unloaded state and 5 N read 1 N
    #: straight down as 0.86 N on the model's own mesh (2 N as 1.85 N; 0.99 x at and above 5 N)
    magnitudes: tuple[float, ...] = (1.0, 5.0, 12.0, 22.0, 40.0)
    min_elevation_deg: float = 15.0
    mechanics_mesh_size: float = 6e-3
    ridge: float = 1e-3
    noise_db: float = DEFAULT_SNR_DB


def calibration_directions(n: int, min_elevation_deg: float) -> np.ndarray:
    """(n, 3) unit force directions pushing into the socket: a Fibonacci spiral on the band of
    elevations [min_elevation, 90] deg, plus the vertical."""
    s_lo = np.sin(np.radians(min_elevation_deg))
    i = np.arange(n - 1) + 0.5
    sin_el = s_lo + (1 - s_lo) * i / (n - 1)  # uniform in area on the band
    az = np.pi * (3 - np.sqrt(5)) * i
    c = np.sqrt(1 - sin_el**2)
    d = np.column_stack([c * np.cos(az), c * np.sin(az), -sin_el])
    return np.vstack([d, [0.0, 0.0, -1.0]])


def socket_mechanics(geometry: SensorGeometry, spec: CalibrationSpec, cache_dir=None,
                     progress=None) -> tuple[TetMesh, np.ndarray, np.ndarray]:
    """The calibration's mechanics, shared by the force calibration (:func:`calibration_set`) and the
    scene field (``scene_field.per_newton_fields``): one socket solve per calibration direction on the
    mechanics mesh, one factorisation for all of them (cached on disk, keyed by the geometry, the
    mesh's own arrays and the directions; a stale entry is rebuilt).

    Returns
    -------
    mesh : TetMesh
        The mechanics mesh (``spec.mechanics_mesh_size``).
    directions : (n, 3) ndarray
        :func:`calibration_directions` of ``spec``.
    theta : (n, m, 4) ndarray
        Volumetric compression per newton along each direction at the vertices of each of the mesh's
        m cells (``MechanicsSolution.theta_vertices``; sample it with ``elasticity.point_sampler``).
    """
    say = progress or (lambda m: log.info("%s", m))
    h = spec.mechanics_mesh_size
    mech = build_mesh(geometry, MeshSpec(h=h, h_electrode=h), cache_dir)
    dirs = calibration_directions(spec.n_directions, spec.min_elevation_deg)
    mesh_digest = hashlib.sha256(np.ascontiguousarray(mech.points).tobytes()
                                 + np.ascontiguousarray(mech.tets, dtype=np.int64).tobytes()).hexdigest()
    key = input_hash({"format": MECHANICS_FORMAT, "geometry": geometry.digest(), "mesh": mesh_digest,
                      "directions": dirs})
    path = Path(cache_dir or default_cache_dir()) / "socket_mechanics" / f"{geometry.name}-{key}.npz"
    hit = cache_load(path, key, names=("theta",))
    if hit is not None:
        return mech, dirs, hit["theta"]
    t0 = time.perf_counter()
    theta = np.empty((len(dirs), len(mech.tets), 4))
    for i, d in enumerate(dirs):
        # one factorisation of the mechanics serves every direction (elasticity module docstring)
        theta[i] = elasticity.solve_socket_load(mech.points, mech.tets, geometry, d).theta_vertices
        if i % 10 == 0:
            say(f"socket mechanics: direction {i + 1}/{len(dirs)}")
    elasticity.release()
    cache_save(path, key, theta=theta)
    log.info("socket mechanics: %d directions in %.1f s", len(dirs), time.perf_counter() - t0)
    return mech, dirs, theta


def _calibration_key(geometry: SensorGeometry, model: ReconstructionModel, spec: CalibrationSpec) -> dict:
    # y depends on the forward mesh, the model reference and v_scale, not on the voxel grid or
    # the Landweber settings: one calibration serves every grid
    return {"format": CALIB_FORMAT, "geometry": geometry.digest(), "mesh_h": model.meta["mesh_h"],
            "v_scale": model.v_scale, "reference": model.model_reference, "spec": spec.__dict__}


def _calibration_loads(geometry: SensorGeometry, model: ReconstructionModel, spec: CalibrationSpec,
                       cache_dir=None, progress=None, what: str = "calibrating force estimators"):
    """(the forward model on the model's mesh, its mesh, the calibration's loads: an iterator of
    (force (3,) N, per-cell conductivity))."""
    say = progress or (lambda m: log.info("%s", m))
    mech, dirs, theta = socket_mechanics(geometry, spec, cache_dir, progress)
    fwd_mesh = build_mesh(geometry, MeshSpec(h=model.meta["mesh_h"]), cache_dir)
    sample = elasticity.point_sampler(mech.points, mech.tets, fwd_mesh.centers)  # located once

    def loads():
        for i, d in enumerate(dirs):
            theta1 = sample(theta[i])  # per N
            for m in spec.magnitudes:
                yield m * d, conductivity_of_theta(m * theta1, geometry.material)[0]
            if i % 10 == 0:
                say(f"{what}: direction {i + 1}/{len(dirs)}")

    return ForwardModel(geometry, fwd_mesh), fwd_mesh, loads()


def calibration_set(geometry: SensorGeometry, model: ReconstructionModel, spec: CalibrationSpec,
                    cache_dir=None, progress=None) -> tuple[np.ndarray, np.ndarray]:
    """(forces (n, 3), y (n, n_meas)) noise-free, through the model's mesh (cached)."""
    key = input_hash(_calibration_key(geometry, model, spec))
    path = Path(cache_dir or default_cache_dir()) / "calibration" / f"{geometry.name}-{key}.npz"
    hit = cache_load(path, key, names=("forces", "y"))
    if hit is not None:
        return hit["forces"], hit["y"]
    t0 = time.perf_counter()
    fm, _, loads = _calibration_loads(geometry, model, spec, cache_dir, progress)
    forces, ys = [], []
    for f, sigma in loads:
        forces.append(f)
        ys.append((fm.voltages(sigma) - model.model_reference) / model.v_scale)
    forces, ys = np.array(forces), np.array(ys)
    cache_save(path, key, forces=forces, y=ys)
    log.info("calibration: %d loads in %.1f s", len(forces), time.perf_counter() - t0)
    return forces, ys


def response_set(geometry: SensorGeometry, model: ReconstructionModel, spec: CalibrationSpec,
                 cache_dir=None, progress=None) -> np.ndarray:
    """(3, n, n_meas): how the calibration set's y (:func:`calibration_set`, same rows) changes per unit
    state of the resistivity gradients along x, y and z that the drift tracker follows
    (:func:`~.joint.gradient_coordinates`, :func:`~.joint.gradient_directions`), the gradient's own
    unloaded change taken out (the pipeline removes it as the tracker's offset): the load's response
    on a warmed block, ``[y_g(F) - y_g(0) - y(F)] / g``, by a secant at ``g`` = :data:`RESPONSE_STEP`
    (the 30-minute warm-up's 15 K with a 30 % gradient reaches 0.03; within 1 % of the secant at 0.01).
    Three forward solves per load, the same physics as the calibration (cached; docs/benchmark.md)."""
    key = input_hash({**_calibration_key(geometry, model, spec), "response": RESPONSE_FORMAT, "step": RESPONSE_STEP})
    path = Path(cache_dir or default_cache_dir()) / "calibration" / f"{geometry.name}-response-{key}.npz"
    hit = cache_load(path, key, names=("dy",))
    if hit is not None:
        return hit["dy"]
    forces, y = calibration_set(geometry, model, spec, cache_dir, progress)
    t0 = time.perf_counter()
    fm, mesh, loads = _calibration_loads(geometry, model, spec, cache_dir, progress,
                                         "the calibration's response to the resistivity gradients")
    factor = 1.0 + RESPONSE_STEP * gradient_coordinates(model, mesh.centers).T  # (3, n_cells): resistivity
    v0 = np.array([fm.voltages(geometry.material.sigma0 / f) for f in factor])  # unloaded, per gradient
    dy = np.empty((3, *y.shape))
    for i, (_, sigma) in enumerate(loads):
        for k, f in enumerate(factor):
            dy[k, i] = ((fm.voltages(sigma / f) - v0[k]) / model.v_scale - y[i]) / RESPONSE_STEP
    cache_save(path, key, dy=dy)
    log.info("calibration's response to the resistivity gradients: %d solves in %.1f s", 3 * (len(y) + 1),
             time.perf_counter() - t0)
    return dy


def _noise_y(model: ReconstructionModel, db: float) -> np.ndarray:
    """Per-channel std of the normalised noise at ``db`` (the assumption without a measured noise:
    :data:`~cstomo_sensor.force.device.DEFAULT_NOISE_DB`; a tare of several frames replaces it)."""
    ref = model.model_reference
    return np.sqrt(np.mean(ref**2)) * 10 ** (-db / 20) / model.v_scale


#: :meth:`ModelEstimator.estimate` keeps its surrogate's coefficients while the device's states it follows
#: move by less than this (relative resistivity per half extent: a load's response changes by 1e-4 of
#: itself, far below the noise; the 30-minute warm-up's gradient grows to 0.03).
STATE_TOLERANCE = 1e-4


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
    ``normal`` (3, 4) ``[-J^T r | J^T J]`` there. The joint fit of force and scale (force/joint.py) and the
    force's sigma (force/sigma.py) are made from it."""
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
            np.dot(state, self._dcoef, out=coef.reshape(-1))
            coef += self._coef0
        self._d0[:] = coef[len(self.forces)]
        self._state = None if state is None else tuple(state)

    def estimate(self, y: np.ndarray, state=None) -> np.ndarray:
        """The force (N) of the change ``y`` (n_meas,); ``state``: the device's states the surrogate
        follows (``response``; the drift tracker's resistivity gradients, 3 floats; None: nominal)."""
        if self._dcoef is not None:
            self._follow(state)
        x = self._W_unit.dot(y).tolist()  # the linear estimate, in units of scale: Python floats through the iteration
        yw = np.multiply(y, self.w, out=self._yw) if self._all_kept else y[self.keep] * self.w
        by = self.basis.dot(yw)
        np.subtract(self._d0, by, out=self._d0_target)
        spline, coef, out, tol2 = self.surrogate, self._coef, self._out, (1e-4 / self.scale) ** 2
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
        self.last_fit = ModelFit(yw, by, step, x, out, G)
        k = self.scale
        return np.array((x[0] * k, x[1] * k, x[2] * k))

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


#: The force estimators by name; the first is the default: ``model``, the more accurate, whose
#: per-frame cost with the drift tracking (``cstomo bench --frame-cost``) is within the 0.1 ms aim.
ESTIMATORS = ("model", "linear")


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
        return LinearEstimator(forces, y, _noise_y(model, spec.noise_db), spec.ridge)
    dy = response_set(geometry, model, spec, cache_dir, progress)
    response = np.concatenate([np.zeros((len(dy), 1, y.shape[1])), dy], axis=1)
    return ModelEstimator(forces, y, _noise_y(model, spec.noise_db), spec.ridge, response=response)

