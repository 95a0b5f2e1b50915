"""Difference imaging: the normalised sensitivity matrix on a coarse voxel basis and the precomputed
regularised Landweber matrix R, saved to and loaded from one npz file (no pickle).

Normalisation (our form of the paper's equation (21)), stated once:

- data ``y = (V - V_ref) / v_scale`` with ``v_scale = max(|V_model_ref|, 0.05 rms(V_model_ref))``
  (relative voltage change against the device's tared reference ``V_ref``; the floor keeps
  near-zero channels from amplifying noise);
- unknowns ``x = dsigma / sigma0`` per voxel (relative conductivity change, uniform in a voxel);
- ``S = diag(1 / v_scale) J_fine P sigma0``, with ``P`` (n_fine_cells, n_basis) the indicator of the
  basis voxel holding each forward cell's centroid: the derivative of the voltages with respect to a
  uniform change in each basis voxel.

Two box grids over the body (voxels holding no forward cell, the socket's cavity, are dropped):

- the *basis* (``basis_grid``, fine): the unknowns the Landweber iteration solves for;
- the *image* (``grid``, coarse): what is published, the basis image averaged by volume
  (``average``, exact over the forward cells each pair of voxels shares).

The precomputed ``R = average @ R_basis`` maps a frame to the image directly, so the per-frame cost
follows the image grid, while the unknowns are not forced to be uniform over 5 mm voxels (docs/design.md,
numerical choices: on the benchmark's scenes the image correlates better with the truth and its
maximum lands nearer the truth's). Forward accuracy follows the fine mesh.
"""
from __future__ import annotations

import json
import logging
import time
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import numpy as np
import scipy.sparse

from ..cache import UNREADABLE, build_lock, cache_load, cache_save, default_cache_dir, input_hash
from ..errors import ConfigError, ModelMismatchError
from ..frames_io import check_frame
from ..model.cem import ForwardModel
from ..model.geometry import DEFAULT_SNR_DB, SensorGeometry, noise_std
from ..model.mesh import MESH_SIZE_RANGE, MeshSpec, TetMesh, build_mesh
from ..settings import default
from .landweber import LandweberSVD, choose_by_discrepancy, column_weight

log = logging.getLogger(__name__)

RECON_FORMAT = 6  # 6: the contacts' directions; 5: a fine basis averaged onto the image grid; 4: built on the shipped meshes
V_FLOOR = 0.05  # fraction of rms(V_ref) below which a channel's normalisation is floored


@dataclass(frozen=True)
class ReconSpec:
    """Every knob of the reconstruction model (all enter the cache key).

    ``iterations`` None chooses k by the discrepancy principle: the smallest k whose residual on
    the noise-free response of a reference inclusion (:func:`reference_inclusion`) is at most
    ``tau`` times the norm of the noise of ``snr_db``; ``damping`` is relative to s_max^2.
    ``weight_power`` p weights the Landweber iteration with ``W = diag(S^T S)^(-p)`` (0 = plain).
    ``grid`` is the published image's voxels, ``basis_grid`` the unknowns' (module docstring).
    The defaults of p, tau and the basis are the triple that maximises the median image correlation
    on the benchmark's training-side socket loads among those that image its training inclusions
    within 8 mm (``cstomo bench --choose-weight``; never the held-out scenes).
    """

    mesh_size: float = default("mesh_size")
    grid: tuple[int, int, int] = default("grid")
    basis_grid: tuple[int, int, int] = (24, 24, 12)
    iterations: int | None = None
    damping: float = default("damping")
    snr_db: float = DEFAULT_SNR_DB
    weight_power: float = 0.75
    tau: float = 0.9

    def __post_init__(self) -> None:
        if not MESH_SIZE_RANGE[0] <= self.mesh_size <= MESH_SIZE_RANGE[1]:
            raise ConfigError.bad_value("mesh_size", self.mesh_size, "metres, 0.0002 <= mesh_size <= 0.02")
        for name in ("grid", "basis_grid"):
            try:
                g = tuple(int(v) for v in getattr(self, name))
            except (TypeError, ValueError):
                g = ()
            if len(g) != 3 or min(g) < 1 or max(g) > 64:
                raise ConfigError.bad_value(name, getattr(self, name), "three integers in 1..64")
            object.__setattr__(self, name, g)
        if self.iterations is not None and not (1 <= int(self.iterations) <= 10**9):
            raise ConfigError.bad_value("iterations", self.iterations, "None (automatic) or 1..1e9")
        if not (0.0 <= self.damping <= 1e6):  # the node's declared range (settings.py)
            raise ConfigError.bad_value("damping", self.damping, "0..1e6 (relative to s_max^2)")
        if not (0.0 < self.snr_db <= 200.0):
            raise ConfigError.bad_value("snr_db", self.snr_db, "0 < snr_db <= 200")
        if not (0.0 < self.tau <= 10.0):
            raise ConfigError.bad_value("tau", self.tau, "0 < tau <= 10 (discrepancy level, times the noise norm)")
        if not (0.0 <= self.weight_power <= 4.0):
            raise ConfigError.bad_value("weight_power", self.weight_power, "a number in 0..4 (0 = plain Landweber)")


def volume_average(mesh: TetMesh, image_voxel: np.ndarray, basis_voxel: np.ndarray) -> scipy.sparse.csr_matrix:
    """(n_image, n_basis) matrix of the volume average onto the image's voxels of a piecewise-constant
    basis image: entry (i, b) is the volume the two voxels share (forward cells in both) over the
    image voxel's volume; rows sum to 1."""
    vol = np.bincount(image_voxel, weights=mesh.volumes)
    A = scipy.sparse.csr_matrix((mesh.volumes / vol[image_voxel], (image_voxel, basis_voxel)),
                                shape=(len(vol), int(basis_voxel.max()) + 1))
    A.sum_duplicates()
    return A


def voxel_basis(geometry: SensorGeometry, mesh: TetMesh, grid: tuple[int, int, int]):
    """Assign forward cells to voxels of a box grid.

    Returns
    -------
    cell_voxel : (n_cells,) int, voxel of each forward cell (0..n_voxels-1).
    centers : (n_voxels, 3) volume-weighted centroids of the voxels' forward cells, m, body frame.
    volumes : (n_voxels,) m^3.
    """
    lo = mesh.points.min(axis=0)
    hi = mesh.points.max(axis=0)
    g = np.array(grid)
    ijk = np.clip(((mesh.centers - lo) / (hi - lo) * g).astype(int), 0, g - 1)
    flat = np.ravel_multi_index(ijk.T, grid)
    used, cell_voxel = np.unique(flat, return_inverse=True)
    vol = np.bincount(cell_voxel, weights=mesh.volumes)
    centers = np.stack([np.bincount(cell_voxel, weights=mesh.volumes * mesh.centers[:, i]) for i in range(3)], 1)
    return cell_voxel, centers / vol[:, None], vol


@dataclass(frozen=True, eq=False)
class ReconstructionModel:
    """The precomputed difference-imaging model; ``R @ y`` is one frame's image.

    Attributes
    ----------
    R : (n_voxels, n_meas) float32, x = R y: the image, ``average @ R_basis``.
    S : (n_meas, n_basis) float64 normalised sensitivity of the basis voxels (SVD and masking).
    v_scale : (n_meas,) V.   model_reference : (n_meas,) V.   sigma0 : S/m.
    centers : (n_voxels, 3) m, body frame.   volumes : (n_voxels,) m^3 (the image's voxels).
    iterations, damping, step, weight_power : the (weighted) Landweber settings R equals.
    key : hash of every input.
    fit : (n_meas, n_meas) float32, ``S @ R_basis``: the data the basis image explains (residuals).
    basis_centers : (n_basis, 3) m.   average : (n_voxels, n_basis) sparse volume average.
    contact : (k, n_meas) the normalised changes (``dV / v_scale``) of the electrodes' contact impedances
    rising by 1 (relative): all alike, then linearly with the electrode's position along x, y, z (by 1
    per half of the electrodes' extent): directions the drift tracker follows (force/slow_states/drift.py).
    """

    R: np.ndarray
    S: np.ndarray
    v_scale: np.ndarray
    model_reference: np.ndarray
    sigma0: float
    centers: np.ndarray
    volumes: np.ndarray
    iterations: int
    damping: float
    step: float
    key: str
    meta: dict
    weight_power: float = 0.0
    fit: np.ndarray | None = None
    basis_centers: np.ndarray | None = None
    average: scipy.sparse.csr_matrix | None = None
    contact: np.ndarray | None = None

    @property
    def n_meas(self) -> int:
        return self.R.shape[1]

    @property
    def n_cells(self) -> int:
        return self.R.shape[0]

    def snr_noise(self, snr_db: float) -> np.ndarray:
        """Per-channel std of the normalised noise ``y`` of a board ``snr_db`` below the model's reference
        (:func:`~cstomo_sensor.model.geometry.noise_std` over ``v_scale``)."""
        return noise_std(self.model_reference, snr_db) / self.v_scale

    def normalise(self, frames: np.ndarray, reference: np.ndarray) -> np.ndarray:
        """``y = (V - V_ref) / v_scale`` for (n_meas,) or (n_frames, n_meas) frames; refuses NaN/Inf."""
        v = check_frame(frames, self.n_meas, "frame", batch=True)
        return (v - check_frame(reference, self.n_meas, "reference")) / self.v_scale

    def reconstruct(self, frames: np.ndarray, reference: np.ndarray) -> np.ndarray:
        """Conductivity change per voxel, S/m: (n_voxels,) or (n_frames, n_voxels)."""
        y = self.normalise(frames, reference)
        return (y @ self.R.T.astype(np.float64)) * self.sigma0

    def svd(self, weight_power: float | None = None) -> LandweberSVD:
        """The (weighted) SVD that R is made from: of ``S W^(1/2)``, ``W = diag(S^T S)^(-p)``."""
        p = self.weight_power if weight_power is None else float(weight_power)
        return LandweberSVD.from_jacobian(self.S, weight=column_weight(self.S, p) if p else None)

    def matrices(self, svd: LandweberSVD, iterations: int, step: float, lam: float = 0.0,
                 dtype=np.float32) -> tuple[np.ndarray, np.ndarray]:
        """(R, fit) of an SVD of S (weighted and/or masked) and Landweber settings: the basis
        matrix in float64, averaged onto the image's voxels, then cast."""
        Rb = svd.matrix(iterations, step, lam, dtype=np.float64)
        return (self.average @ Rb).astype(dtype), (self.S @ Rb).astype(dtype)

    def with_settings(self, iterations: int, damping: float = 0.0,
                      weight_power: float | None = None) -> ReconstructionModel:
        """A copy whose R equals other Landweber settings (one SVD of S, no forward model);
        ``weight_power`` None keeps this model's."""
        p = self.weight_power if weight_power is None else float(weight_power)
        svd = self.svd(p)
        lam = damping * svd.s_max**2
        step = 1.0 / (svd.s_max**2 + lam)
        R, fit = self.matrices(svd, iterations, step, lam)
        return ReconstructionModel(R, self.S, self.v_scale, self.model_reference, self.sigma0, self.centers,
                                   self.volumes, int(iterations), float(damping), step, self.key, dict(self.meta), p,
                                   fit, self.basis_centers, self.average, self.contact)

    # -- one file, no pickle ----------------------------------------------------------------
    def arrays(self) -> dict[str, np.ndarray]:
        """The arrays :meth:`save` writes (:data:`MODEL_ARRAYS`; the sparse average as (row, col), weights)."""
        arrays = {k: getattr(self, k) for k in MODEL_ARRAYS[:-2]}
        a = self.average.tocoo()
        arrays["average"] = np.stack([a.row, a.col]).astype(np.int64)
        arrays["average_weights"] = a.data
        return arrays

    def save(self, path: str | Path) -> None:
        arrays = self.arrays()
        scalars = {"sigma0": self.sigma0, "iterations": self.iterations, "damping": self.damping,
                   "step": self.step, "weight_power": self.weight_power, "meta": self.meta}
        cache_save(Path(path), self.key, scalars=np.array(json.dumps(scalars)), **arrays)

    @classmethod
    def load(cls, path: str | Path, key: str | None = None) -> ReconstructionModel:
        """Load; with ``key``, a model built for other inputs raises :class:`ModelMismatchError`."""
        try:
            with np.load(path, allow_pickle=False) as z:
                found = str(z["cache_key"])
                arrays = {k: z[k] for k in z.files}
        except UNREADABLE as err:
            raise ConfigError(f"model file {path}: unreadable ({type(err).__name__}: {err}); rebuild it") from err
        if key is not None and found != key:
            raise ModelMismatchError(f"{path}: model built for inputs {found}, expected {key}; rebuild it")
        return cls.from_arrays(arrays)

    @classmethod
    def from_arrays(cls, z: dict[str, np.ndarray]) -> ReconstructionModel:
        """The model of the arrays :meth:`save` writes (a cache entry as :func:`cache_load` gives it)."""
        s = json.loads(str(z["scalars"]))
        rows, cols = z["average"]
        average = scipy.sparse.csr_matrix((z["average_weights"], (rows, cols)),
                                          shape=(len(z["centers"]), len(z["basis_centers"])))
        return cls(z["R"], z["S"], z["v_scale"], z["model_reference"], s["sigma0"], z["centers"],
                   z["volumes"], s["iterations"], s["damping"], s["step"], str(z["cache_key"]), s["meta"],
                   s["weight_power"], z["fit"], z["basis_centers"], average, z["contact"])


#: The arrays of a saved model (besides its key and its JSON ``scalars``).
MODEL_ARRAYS = ("R", "S", "v_scale", "model_reference", "centers", "volumes", "fit", "basis_centers",
                "contact", "average", "average_weights")


def model_inputs(geometry: SensorGeometry, spec: ReconSpec) -> dict:
    return {"format": RECON_FORMAT, "geometry": asdict(geometry), "spec": asdict(spec),
            "mesh": MeshSpec(h=spec.mesh_size).__dict__}


def reference_inclusion(geometry: SensorGeometry, centers: np.ndarray) -> np.ndarray:
    """x for the parameter-choice rule: +20 % in the voxels within 8 mm of the point 2 mm below the
    socket's bottom (or of the top centre): the size of the region a 20 N load compresses."""
    c = geometry.socket_center - np.array([0, 0, geometry.socket_radius + 2e-3])
    d = np.linalg.norm(centers - c, axis=1)
    return 0.2 * (d <= max(8e-3, d.min()))


def discrepancy_iterations(geometry: SensorGeometry, svd: LandweberSVD, S: np.ndarray, v_scale: np.ndarray,
                           model_reference: np.ndarray, centers: np.ndarray, step: float, lam: float,
                           snr_db: float = ReconSpec.snr_db, tau: float = ReconSpec.tau) -> int:
    """k by the discrepancy principle at ``tau`` times the noise of ``snr_db`` on the noise-free
    response of :func:`reference_inclusion` (the rule of ``ReconSpec(iterations=None)``)."""
    noise_norm = float(np.linalg.norm(noise_std(model_reference, snr_db) / v_scale))
    y = S @ reference_inclusion(geometry, centers)
    return int(choose_by_discrepancy(svd, y, noise_norm, tau=tau, step=step, damping=lam))


def build_model(geometry: SensorGeometry, spec: ReconSpec = ReconSpec(), cache_dir=None,
                progress=None) -> ReconstructionModel:
    """Build (or load from the cache) the reconstruction model of a sensor."""
    say = progress or (lambda msg: log.info("%s", msg))
    key = input_hash(model_inputs(geometry, spec))
    path = Path(cache_dir or default_cache_dir()) / "models" / f"{geometry.name}-{key}.npz"
    with build_lock(path):  # one process builds it, another waits and reads it (cache.build_lock)
        hit = cache_load(path, key, names=(*MODEL_ARRAYS, "scalars"))
        if hit is not None:
            model = ReconstructionModel.from_arrays(hit)
            model.meta["cache_hit"] = True
            return model
        t = time.perf_counter()
        say(f"mesh of {geometry.name} (h = {spec.mesh_size * 1e3:.1f} mm): shipped with the package, cached, or meshed now")
        mesh = build_mesh(geometry, MeshSpec(h=spec.mesh_size), cache_dir)
        seconds = {"mesh": time.perf_counter() - t}
        model = model_of_mesh(geometry, spec, mesh, key, say)
        model.meta["seconds"] = seconds | model.meta["seconds"]
        model.save(path)
        return model


def model_of_mesh(geometry: SensorGeometry, spec: ReconSpec, mesh: TetMesh, key: str = "",
                  say=None) -> ReconstructionModel:
    """The model of a given forward mesh, not cached: forward solve, Jacobian, voxel sums, (weighted)
    SVD, k and R (what :func:`build_model` does after meshing; the benchmark times it)."""
    say = say or (lambda msg: log.info("%s", msg))
    seconds = {}
    say(f"mesh: {mesh.n_nodes} nodes, {mesh.n_cells} cells; assembling and solving 16 drives")
    fm = ForwardModel(geometry, mesh)
    sol = fm.solve()
    seconds.update(fm.seconds, **sol.seconds)
    t = time.perf_counter()
    J = fm.jacobian(solution=sol)
    seconds["jacobian"] = time.perf_counter() - t
    t = time.perf_counter()
    eps = 0.01  # contact impedances 1 % higher, alike and along x, y, z (the warm side's contacts)
    z = np.full(geometry.n_electrodes, geometry.contact_impedance)
    e = np.asarray(geometry.electrode_centers(), float)
    lo, hi = e.min(axis=0), e.max(axis=0)
    along = [(e[:, k] - 0.5 * (lo[k] + hi[k])) / (0.5 * (hi[k] - lo[k])) for k in range(3) if hi[k] > lo[k]]
    contact = np.array([(fm.with_contact_impedance(z * (1 + eps * w)).voltages() - sol.voltages) / eps
                        for w in [np.ones_like(z), *along]])
    seconds["contact"] = time.perf_counter() - t
    t = time.perf_counter()
    image_voxel, centers, volumes = voxel_basis(geometry, mesh, spec.grid)
    cell_voxel, basis_centers, basis_volumes = voxel_basis(geometry, mesh, spec.basis_grid)
    Vref = sol.voltages
    v_scale = np.maximum(np.abs(Vref), V_FLOOR * np.sqrt(np.mean(Vref**2)))
    S = np.zeros((J.shape[0], len(basis_volumes)))
    for i in range(J.shape[0]):
        S[i] = np.bincount(cell_voxel, weights=J[i], minlength=len(basis_volumes))
    S *= geometry.material.sigma0 / v_scale[:, None]
    p = spec.weight_power
    svd = LandweberSVD.from_jacobian(S, weight=column_weight(S, p) if p else None)
    lam = spec.damping * svd.s_max**2
    step = 1.0 / (svd.s_max**2 + lam)
    if spec.iterations is None:
        k = discrepancy_iterations(geometry, svd, S, v_scale, Vref, basis_centers, step, lam, spec.snr_db, spec.tau)
    else:
        k = int(spec.iterations)
    model = ReconstructionModel(None, S, v_scale, Vref, geometry.material.sigma0, centers, volumes, k, spec.damping,
                                step, key, {}, p, None, basis_centers, volume_average(mesh, image_voxel, cell_voxel),
                                contact / v_scale)
    R, fit = model.matrices(svd, k, step, lam)
    seconds["landweber"] = time.perf_counter() - t
    meta = {"seconds": seconds, "mesh": mesh.summary(), "mesh_h": spec.mesh_size, "rank": svd.rank, "condition": svd.condition,
            "n_voxels": len(volumes), "n_basis": len(basis_volumes), "cache_hit": False}
    say(f"reconstruction: {len(basis_volumes)} basis voxels averaged onto {len(volumes)}, rank {svd.rank}, k = {k}, "
        f"damping = {spec.damping:g}, weight p = {p:g}")
    return replace(model, R=R, fit=fit, meta=meta)
