"""The scene's own stress field and the frame's consistency with the scene's load model.

Scene field
-----------
For a socket scene (the joint) the mechanics predicts the whole stress field from the force.
The frictionless contact problem is positively homogeneous in the force, so the field of a force
F is ``|F| * theta1(F / |F|)`` with ``theta1`` the volumetric compression per newton of a
direction. ``theta1`` is solved once per calibration direction (the estimators' 40 directions,
:func:`~cstomo_sensor.force.estimators.training.calibration_directions`, on the calibration's mechanics mesh:
the very solves of the calibration, :func:`~cstomo_sensor.force.estimators.training.socket_mechanics`)
and sampled at the reconstruction's cell centres, the points the node publishes (cached on disk,
keyed by every input). Between directions it is interpolated by a thin-plate spline of degree 1
on the unit directions (force/estimators/tps.py: exact at the 40 directions; measured error against direct
solves at new directions in docs/node.md). Per frame: one (45 x n_cells) product, the material law
for the published conductivity change, and K theta for the mean stress.

Consistency
-----------
Socket loads change the normalised voltages y only within a low-dimensional set: the span of the
calibration set's changes, whitened by the noise. The statistic is the part of the whitened change
outside that span, per remaining degree of freedom::

    c = || (I - Q^T Q) (y / noise) ||^2 / (n_kept - k)

(Q: the k leading right singular vectors of the whitened calibration changes, those whose rms over
the set is at least ``RANK_NOISE`` of the noise). For a socket load at the stated noise c is about
1 (a chi-square per degree of freedom); the device's mismatch with the model adds to it, growing
with the load. ``noise`` is an input: the noise of the change ``V - V_ref``, the frame's and the
reference's (``Pipeline._update_consistency``: the estimator's per-channel noise times
``sqrt(1 + 1/n)`` for a reference averaged from n frames; a one-frame reference doubles the variance).

The flag trips when c exceeds ``threshold = q / dof + ||allowance / noise||^2 / dof``: q the
chi-square quantile of 1 - 1e-4 (noise alone trips it once in 10^4 frames), ``allowance`` the
per-channel rms of the change a rated socket load leaves outside the span on a device within the
honest simulation's mismatch (+-20 % contact impedance, 0.2 mm electrode jitter):
``MISMATCH_REL`` of the reference's rms: on the held-out device of ``cstomo bench --scene`` the
noise-free statistic of 101 random socket loads (5-40 N, elevation 20-90 deg) at 60 dB noise units is
at most 7.8 (38.8 N at 21 deg elevation, rim contact), and the allowance is 10.2 of them (1.3 x).
So the threshold is about 12.1 at 60 dB and 1.5 at 40 dB for noise at that level (a 20-frame reference
at 60 dB: 11.6; a one-frame reference, whose noise counts twice: 6.7, in units of that larger noise).
"""
from __future__ import annotations

import logging
import time
from pathlib import Path

import numpy as np

from ...cache import build_lock, cache_load, cache_save, default_cache_dir, input_hash
from ...inverse.reconstruction import ReconstructionModel
from ...model import elasticity
from ...model.geometry import SensorGeometry
from ...model.material import StressField, conductivity_of_theta, pressure_of_theta
from ..estimators.tps import ThinPlateSpline
from ..estimators.training import CalibrationSpec, calibration_directions, socket_mechanics

log = logging.getLogger(__name__)

SCENE_FIELD_FORMAT = 1
#: Singular directions of the whitened calibration set kept as "explained by socket loads": those
#: whose rms over the set reaches this multiple of the noise (8 at 60 dB; 7 after a one-frame tare,
#: whose own noise counts: Pipeline._update_consistency). Fewer directions leave more
#: of a foreign load unexplained: on a simulated device (seed 77, 60 dB) a 10 N press on the top face
#: 18 mm from the axis gave 3.5-4.0 with 0.3 (15 directions) against at most 4.4 for socket loads,
#: 9-12 with 1.0 (11) and 14-20 with 2.0 (8), socket loads staying at most 4.7.
RANK_NOISE = 2.0
#: The chi-square tail that noise alone may trip (per frame), and the mismatch allowance (module docstring).
FALSE_ALARM_NOISE = 1e-4
_Z_TAIL = 3.719  # the standard normal quantile of 1 - FALSE_ALARM_NOISE
MISMATCH_REL = 3.2e-3


def mismatch_allowance(model: ReconstructionModel) -> np.ndarray:
    """(n_meas,) the mismatch allowance in y units: ``MISMATCH_REL`` rms(reference) / v_scale."""
    return MISMATCH_REL * np.sqrt(np.mean(model.model_reference**2)) / model.v_scale


def per_newton_fields(geometry: SensorGeometry, model: ReconstructionModel, spec: CalibrationSpec,
                      cache_dir=None) -> tuple[np.ndarray, np.ndarray]:
    """(directions (n, 3), theta per newton (n, n_cells) at the model's cell centres), cached."""
    dirs = calibration_directions(spec.n_directions, spec.min_elevation_deg)
    centers = np.asarray(model.centers, dtype=float)
    key = input_hash({"format": SCENE_FIELD_FORMAT, "geometry": geometry.digest(), "centers": centers,
                      "mechanics_mesh_size": spec.mechanics_mesh_size, "directions": dirs})
    path = Path(cache_dir or default_cache_dir()) / "scene_fields" / f"{geometry.name}-{key}.npz"
    with build_lock(path):  # one process builds it, another waits and reads it (cache.build_lock)
        hit = cache_load(path, key, names=("directions", "theta"))
        if hit is not None:
            return hit["directions"], hit["theta"]
        t0 = time.perf_counter()
        mech, _, theta_v = socket_mechanics(geometry, spec, cache_dir)  # shared with the calibration
        sample = elasticity.point_sampler(mech.points, mech.tets, centers)
        theta = np.array([sample(t) for t in theta_v])
        cache_save(path, key, directions=dirs, theta=theta)
        log.info("scene field: %d directions in %.1f s", len(dirs), time.perf_counter() - t0)
        return dirs, theta


class SceneField:
    """The mechanics' field of a socket force at the published points (module docstring).

    Parameters
    ----------
    directions : (n, 3) ndarray
        Unit force directions.
    theta : (n, n_cells) ndarray
        Volumetric compression per newton of each direction at the points.
    geometry : SensorGeometry
        Its material turns theta into pressure and conductivity.
    """

    def __init__(self, directions: np.ndarray, theta: np.ndarray, geometry: SensorGeometry) -> None:
        self.material = mat = geometry.material
        self.spline = ThinPlateSpline(directions, theta)
        n = len(directions)
        # the spline at a unit direction d: nodes p_i on the unit sphere give |d - p_i|^2 = 2 - 2 d.p_i
        self._p = np.ascontiguousarray(self.spline.points)  # (n, 3)
        self._coef = np.ascontiguousarray(self.spline.M.T)  # (n + 4, n_cells): [c | d_0 | d]
        self._basis = np.ones(n + 4)
        self._r2 = np.empty(n)
        self._log = np.empty(n)
        self.sigma0 = float(conductivity_of_theta(np.zeros(1), mat)[0][0])
        # the material law without its clipping, where no clipping can happen (field())
        self._theta_ok = (np.log(mat.phi_c / mat.phi0) + 1e-3, np.log(1.0 / mat.phi0) - 1e-3)

    def theta(self, force: np.ndarray) -> np.ndarray:
        """(n_cells,) volumetric compression under ``force`` (3,) N."""
        f = np.asarray(force, dtype=float)
        m = float(np.sqrt(f @ f))
        if not m > 0:
            return np.zeros(self._coef.shape[1])
        d = f / m
        n, r2, lg, b = len(self._p), self._r2, self._log, self._basis
        np.dot(self._p, d, out=r2)
        np.subtract(2.0, 2.0 * r2, out=r2)
        np.maximum(r2, 1e-300, out=r2)
        np.log(r2, out=lg)
        np.multiply(r2, lg, out=b[:n])
        b[:n] *= 0.5  # phi(r) = r^2 log r = r^2 log(r^2) / 2
        b[n + 1:] = d
        return m * (b @ self._coef)

    def field(self, force: np.ndarray) -> StressField:
        """The :class:`StressField` of ``force``: conductivity change by the material law, theta, K theta."""
        th = self.theta(force)
        mat = self.material
        lo, hi = self._theta_ok
        if th.size and lo < th.min() and th.max() < hi:  # the law of conductivity_of_theta, unclipped
            sigma = ((mat.phi0 * np.exp(th) - mat.phi_c) / (1.0 - mat.phi_c)) ** mat.tau / mat.rho_h
            clipped = np.zeros(th.shape, bool)
        else:
            sigma, clipped = conductivity_of_theta(th, mat)
        return StressField(sigma - self.sigma0, th, pressure_of_theta(th, mat), clipped)

    @classmethod
    def build(cls, geometry: SensorGeometry, model: ReconstructionModel, spec: CalibrationSpec = CalibrationSpec(),
              cache_dir=None) -> SceneField | None:
        """The scene field of a socket sensor; None for a sensor without a socket (patch scenes)."""
        if geometry.socket_radius <= 0:
            return None
        return cls(*per_newton_fields(geometry, model, spec, cache_dir), geometry)


def change_noise(noise: np.ndarray, reference_frames: int) -> np.ndarray:
    """Per-channel noise of a change ``V - V_ref``: a frame's ``noise`` plus that of a reference
    averaged from ``reference_frames`` frames."""
    return np.asarray(noise, dtype=float) * np.sqrt(1.0 + 1.0 / reference_frames)


def noise_expectation(measured_frames: int | None) -> float:
    """The consistency statistic's mean for noise alone when the per-channel noise it whitens by was
    measured as the std of ``measured_frames`` frames (None: given or estimated from many frames: 1).
    Whitening by an estimated variance ``s^2`` of ``n - 1`` degrees of freedom inflates each channel's
    term by ``E[sigma^2 / s^2] = (n - 1) / (n - 3)`` (a tare of 10 frames: 1.29; 20: 1.12; 50: 1.04);
    below 5 frames it is taken at 5's (2.0)."""
    if not measured_frames or measured_frames < 2:
        return 1.0
    n = max(int(measured_frames), 5)
    return (n - 1.0) / (n - 3.0)


class Consistency:
    """The consistency statistic of a frame against the socket load model (module docstring).

    Parameters
    ----------
    y : (n, n_meas) ndarray
        The calibration set's normalised changes (socket loads through the model).
    noise : (n_meas,) ndarray
        Per-channel noise std of y, the frame's and the reference's together (module docstring).
    allowance : (n_meas,) ndarray or None
        The model mismatch allowed for (:func:`mismatch_allowance`); None: none.
    keep : (n_meas,) bool ndarray or None
        Channels in use.
    expected : float
        ``c``'s mean for noise alone (:func:`noise_expectation`: above 1 when ``noise`` was measured
        from few frames).

    Attributes
    ----------
    threshold : float
        ``c`` above it trips the foreign-load flag (module docstring).
    """

    def __init__(self, y: np.ndarray, noise: np.ndarray, allowance: np.ndarray | None = None,
                 keep: np.ndarray | None = None, expected: float = 1.0) -> None:
        self.expected = float(expected)
        self.y, self.noise = np.asarray(y), np.asarray(noise, dtype=float)
        self.allowance = np.zeros_like(self.noise) if allowance is None else np.asarray(allowance, dtype=float)
        self.keep = np.ones(self.y.shape[1], bool) if keep is None else np.asarray(keep, bool)
        self.w = np.where(self.keep, 1.0 / self.noise, 0.0)
        yw = self.y * self.w
        _, s, vt = np.linalg.svd(yw, full_matrices=False)
        k = int(np.count_nonzero(s / np.sqrt(len(yw)) >= RANK_NOISE))
        self.Q = np.ascontiguousarray(vt[:k])  # (k, n_meas), zero on excluded channels
        self.dof = max(int(self.keep.sum()) - k, 1)
        a = 2.0 / (9.0 * self.dof)  # Wilson-Hilferty: the chi-square quantile per degree of freedom
        self.threshold = float((1 - a + _Z_TAIL * np.sqrt(a)) ** 3
                               + np.sum((self.allowance * self.w) ** 2) / self.dof)
        self._z = np.empty(self.y.shape[1])

    def __call__(self, y: np.ndarray) -> float:
        """The statistic of one frame's change ``y`` (n_meas,)."""
        z = np.multiply(y, self.w, out=self._z)
        p = self.Q.dot(z)
        return float((z.dot(z) - p.dot(p)) / self.dof)

    def masked(self, keep: np.ndarray) -> Consistency:
        return Consistency(self.y, self.noise, self.allowance, keep, self.expected)
