"""The held-out scenes of every benchmark: an honestly simulated device (independent 3 mm mesh,
its own seed), random socket forces, noise, and how estimates and images are judged against them."""
from __future__ import annotations

import io
import time
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from ...angles import angle_between, force_from_angles
from ...model.geometry import DEFAULT_SNR_DB, load_sensor, noise_std
from ...model.material import conductivity_of_theta
from ...model.simulate import MECHANICS_MESH_SIZE, TRUTH_MESH_SIZE, Load, Truth
from ...settings import DEFAULT_SENSOR, RATED_FORCE

#: The scene files of the repository (scenes/*.yaml): the benches' devices.
SCENES = Path(__file__).resolve().parents[3] / "scenes"
TRUTH_SEED = 9001  # the simulated device of the held-out scenes; no calibration or test uses it
FORCE_SEED = 20261121
TRAIN_TRUTH_SEED, TRAIN_FORCE_SEED = 77, 555  # the training side: parameter choice only (weight.py)
NOISE_SEED = 4242
BOUND_N = 10 * RATED_FORCE  # N: an estimate above this (10x the rated range) counts as unbounded
#: dB: the benchmarks' board, the default scene's noise (model/geometry.py DEFAULT_SNR_DB); SNRS: it and the
#: noisier board every estimator is judged at too.
SNR_DB = DEFAULT_SNR_DB
SNRS = (SNR_DB, 40.0)



def as_written(frames: np.ndarray) -> np.ndarray:
    """Frames rounded as the frames file writes them (``%.9e``)."""
    buf = io.StringIO()
    np.savetxt(buf, np.atleast_2d(frames), delimiter=",", fmt="%.9e")
    return np.loadtxt(io.StringIO(buf.getvalue()), delimiter=",", ndmin=2)


def random_forces(n: int, seed: int = FORCE_SEED) -> np.ndarray:
    """``n`` seeded socket forces (n, 3) N: 5 N up to the rated range (settings.RATED_FORCE), elevations
    20..90 deg, any azimuth."""
    rng = np.random.default_rng(seed)
    mag = rng.uniform(5.0, RATED_FORCE, n)
    el = np.radians(rng.uniform(20.0, 90.0, n))
    az = rng.uniform(-np.pi, np.pi, n)
    f = np.array([force_from_angles(m, e, a) for m, e, a in zip(mag, el, az)])
    return np.array([[float(f"{v:.9g}") for v in row] for row in f])  # as the forces file holds them


class SceneSet:
    """The held-out device and its clean loaded frames, truth conductivity changes and noise."""

    def __init__(self, n_scenes: int, cache_dir=None, say=print, truth_seed: int = TRUTH_SEED,
                 force_seed: int = FORCE_SEED) -> None:

        self.geometry = load_sensor(DEFAULT_SENSOR)
        self.truth = Truth(self.geometry, truth_h=TRUTH_MESH_SIZE, mechanics_h=MECHANICS_MESH_SIZE, seed=truth_seed, cache_dir=cache_dir)
        t = time.perf_counter()
        self.ref_clean = self.truth.reference
        self.forces = random_forces(n_scenes, force_seed)
        self._theta: dict[tuple, tuple[np.ndarray, float]] = {}
        self.clean, self.dsigma = [], []
        for f in self.forces:
            v, ds = self.frame_of(f)
            self.clean.append(v)
            self.dsigma.append(ds)
        self.clean = np.array(self.clean)
        self.seconds = time.perf_counter() - t
        say(f"scenes: {n_scenes} socket loads simulated on the truth mesh "
            f"({self.truth.forward.mesh.n_cells} cells) in {self.seconds:.1f} s")

    @property
    def rms(self) -> float:
        return float(np.sqrt(np.mean(self.ref_clean**2)))

    def frame_of(self, force: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(clean frame, truth dsigma per truth cell) of a socket force; one mechanics solve per
        direction (the frictionless contact problem is positively homogeneous in the force)."""

        f = np.asarray(force, float)
        m = float(np.linalg.norm(f))
        fwd = self.truth.forward
        if m == 0.0:
            return self.ref_clean.copy(), np.zeros(fwd.mesh.n_cells)
        d = tuple(np.round(f / m, 12))
        if d not in self._theta:
            self._theta[d] = (self.truth.theta(Load("socket", force=tuple(f))), m)
        th, m0 = self._theta[d]
        sigma, _ = conductivity_of_theta(th * (m / m0), self.geometry.material)
        return fwd.voltages(sigma), sigma - fwd.sigma0

    def noisy(self, clean: np.ndarray, reps: int, snr_db: float | None, seed: int) -> tuple[np.ndarray, np.ndarray]:
        """(noisy reference, (len(clean) * reps, n_meas) noisy frames), rounded as written."""
        rng = np.random.default_rng(seed)
        std = 0.0 if snr_db is None else noise_std(self.ref_clean, snr_db)
        ref = self.ref_clean + rng.normal(0, std, self.ref_clean.shape)
        frames = np.repeat(np.atleast_2d(clean), reps, axis=0)
        frames = frames + rng.normal(0, std, frames.shape)
        return as_written(ref)[0], as_written(frames)

    def truth_on_voxels(self, centers: np.ndarray) -> np.ndarray:
        """(n_scenes, n_voxels) truth dsigma averaged onto voxels (nearest voxel centre, by volume)."""

        mesh = self.truth.forward.mesh
        _, vox = cKDTree(centers).query(mesh.centers)
        w = np.bincount(vox, weights=mesh.volumes, minlength=len(centers))
        out = np.array([np.bincount(vox, weights=mesh.volumes * ds, minlength=len(centers)) for ds in self.dsigma])
        return out / np.maximum(w, 1e-300)


def errors(est: np.ndarray, true: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(angle error deg (NaN for a zero true force), |magnitude error| N) per frame."""

    est, true = np.atleast_2d(est), np.atleast_2d(true)
    ang = np.degrees(angle_between(est, true))
    ang = np.where(np.linalg.norm(true, axis=1) > 0, ang, np.nan)
    return ang, np.abs(np.linalg.norm(est, axis=1) - np.linalg.norm(true, axis=1))


def quantile(a, q):
    a = np.asarray(a, float)
    a = a[np.isfinite(a)]
    return float(np.quantile(a, q)) if a.size else float("nan")


def image_errors(images: np.ndarray, truth_vox: np.ndarray, centers: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(correlation, peak distance mm) per frame; ``truth_vox`` row per frame."""
    corr, dist = [], []
    for x, t in zip(images, truth_vox):
        ok = np.std(x) > 0 and np.std(t) > 0
        corr.append(float(np.corrcoef(x, t)[0, 1]) if ok else float("nan"))
        dist.append(float(np.linalg.norm(centers[np.argmax(x)] - centers[np.argmax(t)]) * 1e3))
    return np.array(corr), np.array(dist)
