"""The estimators' training data: known socket loads through the model's own physics (cached).

Forces on a Fibonacci set of directions (elevation 15..90 deg, every azimuth) and several magnitudes
(1..40 N) are pushed through the mechanics (frictionless socket contact; one solve per direction, as
the contact problem is positively homogeneous in the force; :func:`socket_mechanics`, cached and shared
with the scene field), the material law and the forward model on the reconstruction's mesh, giving
normalised voltage changes y (:func:`calibration_set`; docs/design.md, *Numerical choices*, and the
reconstruction module for the normalisation); :func:`response_set` gives how those y change on a
warmed block's resistivity gradients (issue 26). The estimators (force/estimators/estimate.py) are fitted on
them. The calibration never sees the honest-simulation meshes or seeds.
"""
from __future__ import annotations

import hashlib
import logging
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ...cache import build_lock, cache_load, cache_save, default_cache_dir, input_hash
from ...inverse.reconstruction import ReconstructionModel
from ...model import elasticity
from ...model.cem import ForwardModel
from ...model.geometry import DEFAULT_SNR_DB, SensorGeometry
from ...model.material import conductivity_of_theta
from ...model.mesh import MeshSpec, TetMesh, build_mesh
from ...settings import RATED_FORCE
from .scale_fit import gradient_coordinates

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
    magnitudes: tuple[float, ...] = (1.0, 5.0, 12.0, 22.0, RATED_FORCE)  # the rated force last
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
    with build_lock(path):  # one process builds it, another waits and reads it (cache.build_lock)
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
    with build_lock(path):  # one process builds it, another waits and reads it (cache.build_lock)
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
    (:func:`~.scale_fit.gradient_coordinates`, :func:`~.scale_fit.gradient_directions`), the gradient's own
    unloaded change taken out (the pipeline removes it as the tracker's offset): the load's response
    on a warmed block, ``[y_g(F) - y_g(0) - y(F)] / g``, by a secant at ``g`` = :data:`RESPONSE_STEP`
    (the 30-minute warm-up's 15 K with a 30 % gradient reaches 0.03; within 1 % of the secant at 0.01).
    Three forward solves per load, the same physics as the calibration (cached; docs/benchmark.md)."""
    key = input_hash({**_calibration_key(geometry, model, spec), "response": RESPONSE_FORMAT, "step": RESPONSE_STEP})
    path = Path(cache_dir or default_cache_dir()) / "calibration" / f"{geometry.name}-response-{key}.npz"
    with build_lock(path):  # one process builds it, another waits and reads it (cache.build_lock)
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
