"""The linear-elastic problem on a tetrahedral mesh (scikit-fem, quadratic tetrahedra): assembly,
one factorisation per mesh, the solve of a traction load, and the solution's volumetric compression.

Small strain, isotropic, E and nu from a :class:`~cstomo_sensor.model.material.Material`.
Displacements are continuous piecewise quadratic (``ElementVector(ElementTetP2())``) so that the
nearly incompressible rubber (nu = 0.45) does not lock; the volumetric compression
theta = -div(u) is then linear in each cell.

Input meshes are plain arrays (``points (n, 3)`` in metres, ``tets (m, 4)`` vertex indices), e.g.
the fields of ``cstomo_sensor.model.mesh.TetMesh``; cells of either orientation are accepted. Nothing here
knows the sensor: its faces and loads are :mod:`~cstomo_sensor.model.elasticity`'s.

Solver: the condensed stiffness (symmetric positive definite) is factorised once per mesh and set
of fixed dofs (SuperLU in symmetric mode, :func:`~cstomo_sensor.model.cem.symmetric_lu`: about 2 s
and 250 MB on the 6 mm calibration mesh) and kept with the assembled problem in a small cache
(:func:`problem`), so every further load on that mesh is two triangular solves (tens of ms) and
exact to rounding. :func:`release` frees the factors (at the end of a :func:`kept` block, when in one).
When the cache is full, the problem cheapest to set up again goes first, not merely the oldest: a small mesh
used once (a patch scene's, 1 s) does not push out a 4 mm mechanics mesh's factor (15-30 s).

scikit-fem is imported only by this module, inside its functions; nothing else in the package
imports it at import time.
"""
from __future__ import annotations

import hashlib
from collections.abc import Mapping
from contextlib import contextmanager
from dataclasses import dataclass, field
from functools import cached_property
from typing import Any

import numpy as np
from numpy.typing import ArrayLike
from scipy.spatial import cKDTree

from ..errors import ConfigError
from .cem import symmetric_lu
from .material import Material

__all__ = ["ElasticProblem", "MechanicsSolution", "PointSampler", "check_mesh", "kept", "point_sampler", "problem",
           "release"]

_VOLUME_INTORDER = 2  # exact for the P2 stiffness (products of linear gradients)


# ----------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class MechanicsSolution:
    """A solved linear-elastic state on a tetrahedral mesh.

    Attributes
    ----------
    points : (n, 3) ndarray
        Mesh vertices, m (body frame).
    tets : (m, 4) int ndarray
        Cells as given (orientation fixed internally only).
    dofs : (N,) ndarray
        The P2 displacement coefficients (scikit-fem ``ElementVector(ElementTetP2())`` numbering,
        interleaved x, y, z), m.
    displacement : (n, 3) ndarray
        Displacement at the vertices, m.
    theta_vertices : (m, 4) ndarray
        Volumetric compression -div(u) of each cell at its four vertices (it is linear per cell).
    strain_energy : float
        1/2 u^T K u = 1/2 f . u, J.
    resultant : (3,) ndarray
        The discrete integral of the applied tractions, N (equals the requested force).
    delta : (3,) ndarray or None
        For socket loads: k delta, the ball's rigid displacement times the bed stiffness, Pa
        (k is arbitrary, only the direction and relative size matter). None otherwise.
    load : dict
        The load that was applied (for records).
    """

    points: np.ndarray
    tets: np.ndarray
    dofs: np.ndarray
    displacement: np.ndarray
    theta_vertices: np.ndarray
    strain_energy: float
    resultant: np.ndarray
    delta: np.ndarray | None = None
    load: Mapping[str, Any] = field(default_factory=dict)

    def cell_theta(self) -> np.ndarray:
        """Mean volumetric compression of each cell (exact mean of the linear field).

        Returns
        -------
        (m,) ndarray
        """
        return self.theta_vertices.mean(axis=1)

    def theta_at(self, x: ArrayLike) -> np.ndarray:
        """Volumetric compression at arbitrary points (see :class:`PointSampler`; to sample many
        solutions on one mesh at the same points, build the sampler once with :func:`point_sampler`).

        Parameters
        ----------
        x : (k, 3) array_like
            Points, m, body frame.

        Returns
        -------
        (k,) ndarray
        """
        return point_sampler(self.points, self.tets, x)(self.theta_vertices)


@dataclass(frozen=True)
class PointSampler:
    """Points located in a tetrahedral mesh: the cell holding each and its barycentric coordinates.

    Each point is located among the 32 cells with the nearest centroids. A point outside the mesh
    (e.g. a reconstruction cell centre a rounding error outside a curved face) takes the candidate
    cell it is least outside of, at its barycentric coordinates clipped to that cell, i.e. a value
    the field takes on the mesh; far-away points get such a value too, without an error.

    Attributes
    ----------
    cells : (k,) int ndarray
    weights : (k, 4) ndarray, non-negative, rows summing to 1.
    """

    cells: np.ndarray
    weights: np.ndarray

    def __call__(self, vertex_values: np.ndarray) -> np.ndarray:
        """(k,) values at the points of a field linear per cell, given at the cells' vertices
        (``vertex_values`` (m, 4), e.g. :attr:`MechanicsSolution.theta_vertices`)."""
        return np.einsum("ki,ki->k", self.weights, vertex_values[self.cells])


def point_sampler(points: ArrayLike, tets: ArrayLike, x: ArrayLike) -> PointSampler:
    """Locate points ``x`` (k, 3) in the mesh ``points`` (n, 3), ``tets`` (m, 4) (one KD-tree)."""
    x = np.atleast_2d(np.asarray(x, dtype=float))
    if x.ndim != 2 or x.shape[1] != 3:
        raise ConfigError(f"points.shape={x.shape}: expected (k, 3)")
    v = np.asarray(points)[np.asarray(tets)]  # (m, 4, 3)
    T = np.transpose(v[:, 1:, :] - v[:, :1, :], (0, 2, 1))  # columns v1-v0, v2-v0, v3-v0
    inv, v0 = np.linalg.inv(T), v[:, 0, :]
    kk = min(32, len(v))
    _, cand = cKDTree(v.mean(axis=1)).query(x, k=kk)
    cand = cand.reshape(len(x), kk)
    lam123 = np.einsum("kcij,kcj->kci", inv[cand], x[:, None, :] - v0[cand])  # (k, kk, 3)
    lam = np.concatenate([1.0 - lam123.sum(-1, keepdims=True), lam123], axis=-1)  # (k, kk, 4)
    best = np.argmax(lam.min(axis=-1), axis=1)
    rows = np.arange(len(x))
    lam_b = np.clip(lam[rows, best], 0.0, None)
    lam_b /= lam_b.sum(axis=1, keepdims=True)
    return PointSampler(cand[rows, best], lam_b)


# ----------------------------------------------------------------------------------------------
def check_mesh(points: ArrayLike, tets: ArrayLike) -> tuple[np.ndarray, np.ndarray]:
    """``points`` as (n, 3) finite floats and ``tets`` as (m, 4) int64 indices into them, else a
    :class:`~cstomo_sensor.errors.ConfigError` naming what is wrong."""
    p = np.asarray(points, dtype=float)
    t = np.asarray(tets)
    if p.ndim != 2 or p.shape[1] != 3:
        raise ConfigError(f"points.shape={p.shape}: expected (n, 3)")
    if t.ndim != 2 or t.shape[1] != 4 or not np.issubdtype(t.dtype, np.integer):
        raise ConfigError(f"tets.shape={t.shape}, dtype={t.dtype}: expected (m, 4) integers")
    if len(t) == 0 or t.min() < 0 or t.max() >= len(p):
        raise ConfigError(f"tets: indices must lie in [0, {len(p)}), got [{t.min()}, {t.max()}]")
    if not np.isfinite(p).all():
        raise ConfigError("points: contain NaN or inf")
    return p, t.astype(np.int64)


class ElasticProblem:
    """The assembled stiffness and the bases on one mesh; get it through :func:`problem` (cached).

    Attributes
    ----------
    mesh : skfem.MeshTet
        The mesh, cells re-oriented to positive volume.
    basis : skfem.Basis
        The P2 vector basis (``basis.get_dofs`` finds the dofs to fix).
    K : sparse matrix
        The stiffness.
    """

    def __init__(self, points: np.ndarray, tets: np.ndarray, mat: Material) -> None:
        from skfem import Basis, ElementTetP2, ElementVector, MeshTet, asm  # heavy: only where the elasticity is assembled
        from skfem.models.elasticity import lame_parameters, linear_elasticity  # heavy: only where the elasticity is assembled

        t = tets.copy()
        v = points[t]
        det = np.einsum("ij,ij->i", np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0]), v[:, 3] - v[:, 0])
        if (np.abs(det) <= 1e-14 * np.ptp(points, axis=0).max() ** 3).any():
            raise ConfigError(f"tets: {(np.abs(det) <= 0).sum()} degenerate (zero-volume) cells")
        t[det < 0, 2], t[det < 0, 3] = tets[det < 0, 3], tets[det < 0, 2]
        self.points, self.tets_in, self.tets = points, tets, t
        self.mesh = MeshTet(points.T.copy(), t.T.copy())
        self.elem = ElementVector(ElementTetP2())
        self.basis = Basis(self.mesh, self.elem, intorder=_VOLUME_INTORDER)
        self.K = asm(linear_elasticity(*lame_parameters(mat.E, mat.nu)), self.basis)
        self._lu: dict[str, tuple[Any, np.ndarray]] = {}
        self._facet_bases: dict[tuple[str, int], Any] = {}
        #: what setting this problem up again would cost, relative (:func:`problem`): its dofs cubed (a sparse 3D
        #: factorisation grows faster than their square: the 6 mm mesh's 28k dofs take a tenth of the 4 mm mesh's 39k);
        #: a count, not a timing, so a loaded host ranks the problems as a quiet one does
        self.setup_cost = float(self.basis.N) ** 3

    def boundary_facets(self) -> tuple[np.ndarray, np.ndarray]:
        """(facet indices (nb,), their vertices' coordinates (3, 3 vertices, nb)) of the boundary."""
        bf = self.mesh.boundary_facets()
        return bf, self.mesh.p[:, self.mesh.facets[:, bf]]

    def facet_basis(self, facets: np.ndarray, intorder: int):
        """The basis on ``facets`` with a quadrature of order ``intorder`` (normals, ``dx``, points); built
        once per set of facets and order (every socket load on a mesh takes the same: a third of a load's
        solve when built anew)."""
        from skfem import FacetBasis  # heavy: only where the elasticity is assembled

        key = (hashlib.sha1(np.ascontiguousarray(facets, dtype=np.int64).tobytes()).hexdigest(), int(intorder))
        if key not in self._facet_bases:
            self._facet_bases[key] = FacetBasis(self.mesh, self.elem, facets=facets, intorder=intorder)
        return self._facet_bases[key]

    def load_vector(self, fb, traction: np.ndarray) -> np.ndarray:
        """Assemble int t . v dA for a traction given at the facet quadrature points (3, nf, nq)."""
        from skfem import LinearForm, asm  # heavy: only where the elasticity is assembled

        @LinearForm
        def form(v, w):
            return w.t[0] * v[0] + w.t[1] * v[1] + w.t[2] * v[2]

        return asm(form, fb, t=traction)

    def solve_traction(self, fb, traction: np.ndarray, fixed: np.ndarray, load: Mapping[str, Any],
                       delta: np.ndarray | None = None) -> MechanicsSolution:
        """The state under a traction (3, nf, nq) at the quadrature points of ``fb``, the dofs
        ``fixed`` held at zero: its resultant (the same quadrature), load vector and solve."""
        resultant = (traction * fb.dx[None]).sum(axis=(1, 2))
        return self.solve(self.load_vector(fb, traction), fixed, load, resultant, delta)

    def solve(self, f: np.ndarray, fixed: np.ndarray, load: Mapping[str, Any], resultant: np.ndarray,
              delta: np.ndarray | None = None) -> MechanicsSolution:
        """The state under the load vector ``f`` with the dofs ``fixed`` held at zero (one
        factorisation per set of fixed dofs, kept for the next load)."""
        from skfem import condense  # heavy: only where the elasticity is assembled

        u = np.zeros(self.basis.N)
        if np.any(f):
            key = hashlib.sha1(np.ascontiguousarray(fixed, dtype=np.int64).tobytes()).hexdigest()
            if key not in self._lu:  # set up once per set of fixed dofs, reuse for every load
                A, _, _, I = condense(self.K, f, D=fixed)
                self._lu = {key: (symmetric_lu(A).solve, I)}
            solve, I = self._lu[key]
            u[I] = solve(f[I])
        disp = u[self.basis.nodal_dofs].T.copy()  # (n, 3)
        theta_v = self._theta_vertices(u)
        return MechanicsSolution(
            points=self.points,
            tets=self.tets_in,
            dofs=u,
            displacement=disp,
            theta_vertices=theta_v,
            strain_energy=float(0.5 * f @ u),
            resultant=np.asarray(resultant, dtype=float),
            delta=delta,
            load=dict(load),
        )

    @cached_property
    def _vertex_basis(self):
        """The basis evaluated at the reference vertices of each cell (built once per mesh)."""
        from skfem import Basis  # heavy: only where the elasticity is assembled

        X = np.array([[0.0, 1.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0], [0.0, 0.0, 0.0, 1.0]])
        return Basis(self.mesh, self.elem, quadrature=(X, np.full(4, 1.0 / 24)))

    @cached_property
    def _vertex_divergence(self) -> tuple[np.ndarray, np.ndarray]:
        """(div of each local basis function at each cell's vertices (n_local, m, 4), the cells' dofs
        (n_local, m)): -div u at the vertices is then one contraction per load (built once per mesh)."""
        vb = self._vertex_basis
        return np.array([b[0].grad[0, 0] + b[0].grad[1, 1] + b[0].grad[2, 2] for b in vb.basis]), vb.element_dofs

    def _theta_vertices(self, u: np.ndarray) -> np.ndarray:
        """-div u at the reference vertices of each (re-oriented) cell, mapped to the input order (the
        basis's interpolation of u, summed as a contraction: a tenth of its cost per load)."""
        div, dofs = self._vertex_divergence
        th = -np.einsum("icq,ic->cq", div, u[dofs])  # (m, 4) in the order of self.tets
        flipped = (self.tets != self.tets_in).any(axis=1)
        th[flipped] = th[flipped][:, [0, 1, 3, 2]]
        return th


_CACHE: dict[str, ElasticProblem] = {}
_CACHE_SIZE = 2
_CHEAP = 0.5  # a problem whose setup costs under this fraction of the costliest other's is dropped first


def problem(points: np.ndarray, tets: np.ndarray, mat: Material) -> ElasticProblem:
    """The assembled problem for a mesh (checked by :func:`check_mesh`) and material, reused across
    loads (a small cache).

    Solving many loads on one mesh (scenes, calibration, tests) then assembles and factorises the
    stiffness once; the key is a hash of the arrays' bytes and of (E, nu). Beyond the cache's size the
    problem dropped is, of all but the one asked for now, the least recently used of those cheap to set up
    again (under :data:`_CHEAP` of the costliest's ``setup_cost``), else the least recently used: a large
    mesh's factor outlives small meshes used since. Which problems are kept changes no result, only what is
    set up again.
    """
    h = hashlib.sha1(points.tobytes())
    h.update(tets.tobytes())
    h.update(np.array([mat.E, mat.nu]).tobytes())
    key = h.hexdigest()
    prob = _CACHE.pop(key, None) or ElasticProblem(points, tets, mat)
    _CACHE[key] = prob  # the one asked for now: last (the most recently used), never dropped here
    while len(_CACHE) > _CACHE_SIZE:
        others = list(_CACHE)[:-1]  # the least recently used first
        costliest = max(_CACHE[k].setup_cost for k in others)
        del _CACHE[next((k for k in others if _CACHE[k].setup_cost < _CHEAP * costliest), others[0])]
    return prob


_KEPT = [0]  # depth of the kept() blocks around this moment


def release() -> None:
    """Drop the assembled problems and their factors (call after a batch of loads, e.g. the
    calibration, so that a long-running process does not keep hundreds of MB); inside a
    :func:`kept` block, at that block's end instead."""
    if not _KEPT[0]:
        _CACHE.clear()


@contextmanager
def kept():
    """Keep the assembled problems and their factors until the block ends: a :func:`release` inside
    it waits for the end. For work that solves several batches of loads on one device (its
    calibration, then the loads of one timeline, then another's: each batch releases when done),
    which would otherwise assemble and factorise the same mesh once per batch (10-30 s and several
    hundred MB each on the 4 mm mechanics mesh); the block holds at most the cache's two problems."""
    _KEPT[0] += 1
    try:
        yield
    finally:
        _KEPT[0] -= 1
        release()
