"""Linear elasticity of the rubber body under the sensor's loads (scikit-fem, quadratic tetrahedra).

Small strain, isotropic, E and nu from the sensor's :class:`~cstomo_sensor.geometry.Material`.
Displacements are continuous piecewise quadratic (``ElementVector(ElementTetP2())``) so that the
nearly incompressible rubber (nu = 0.45) does not lock; the volumetric compression
theta = -div(u) is then linear in each cell.

Input meshes are plain arrays (``points (n, 3)`` in metres, ``tets (m, 4)`` vertex indices), e.g.
the fields of ``cstomo_sensor.mesh.TetMesh``; cells of either orientation are accepted.
Faces are found geometrically: the bottom face z = 0 (vertices within ``FACE_TOL`` x height), the
top face z = height (outward normal +z), and the socket wall (boundary facets on the hemisphere of
``geometry.socket_radius`` around ``geometry.socket_center``, below the top face).

Loads (REFERENCE_SENSOR.md section 4):

* :func:`solve_socket_load` - the ball in the socket, frictionless: traction t = -p n on the socket
  wall, n the rubber's outward normal, p = k max(0, -n . delta). k only scales delta, so the
  unknown is a = k delta (Pa), found by Newton on the convex function
  G(a) = 1/2 int max(0, -n.a)^2 dA - F.a, whose gradient is (int t dA) - F. The integral is the
  same facet quadrature that builds the load vector, so the discrete resultant equals F to
  rounding error. A force must push into the socket (elevation atan2(-Fz, |Fxy|) > 0); the
  reference carries elevations 15..90 deg. Below 15 deg the solve still runs (it is
  well-posed for any elevation > 0) but the contact sits on the rim, where the result depends on
  the mesh; a warning is logged.
* :func:`solve_patch_load` - uniform normal pressure on regions of the top face or of a side face.

Solver: the condensed stiffness (symmetric positive definite) is factorised once per mesh and set
of fixed dofs (SuperLU in symmetric mode, :func:`~cstomo_sensor.model.cem.symmetric_lu`: about 2 s
and 250 MB on the 6 mm calibration mesh) and kept with the assembled problem in a small cache, so
every further load on that mesh is two triangular solves (tens of ms) and exact to rounding. The
contact needs no refactorisation: the pressure law depends only on the ball's displacement a, not
on the rubber's, so each load is one linear solve with the same matrix. :func:`release` frees the
factors.

scikit-fem is imported only by this module; nothing else in the package imports it at import time.
"""
from __future__ import annotations

import hashlib
import logging
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from functools import cached_property
from typing import Any

import numpy as np
from numpy.typing import ArrayLike
from scipy.optimize import nnls
from scipy.spatial import cKDTree

from ..errors import ConfigError
from .cem import symmetric_lu
from .geometry import SensorGeometry
from .material import Material

log = logging.getLogger(__name__)

__all__ = [
    "CARRIED_ELEVATION_DEG",
    "MechanicsSolution",
    "PointSampler",
    "point_sampler",
    "solve",
    "solve_patch_load",
    "solve_socket_load",
    "uniaxial_compression",
]

FACE_TOL = 1e-4
"""Relative tolerance (x body height) for a vertex to lie on a plane face; x radius for the socket."""
CARRIED_ELEVATION_DEG = (15.0, 90.0)
"""Force elevations the reference sensor carries (REFERENCE_SENSOR.md s.4)."""
NEWTON_TOL = 1e-12
CONTACT_ACCEPT_TOL = 1e-6  # relative resultant error accepted when Newton stalls at rounding level
"""Newton stops when |int t dA - F| <= NEWTON_TOL |F| (or, when the line search stalls at
rounding level, accepts a residual below 1e3 NEWTON_TOL |F|)."""
_VOLUME_INTORDER = 2  # exact for the P2 stiffness (products of linear gradients)
_SOCKET_INTORDER = 2  # p is constant per flat facet: order 2 integrates it against P2 exactly
_PATCH_INTORDER = 4  # more quadrature points resolve the patch edges better
#: The side faces a patch load can press (cuboid bodies): face -> (normal axis, sign). A patch's
#: ``center`` is given in the face's own two coordinates: (y, z) on +-x, (x, z) on +-y, (x, y) on top.
SIDE_FACES = {"+x": (0, 1), "-x": (0, -1), "+y": (1, 1), "-y": (1, -1)}
_FACE_AXES = {"top": (0, 1), "+x": (1, 2), "-x": (1, 2), "+y": (0, 2), "-y": (0, 2)}


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
def _check_mesh(points: ArrayLike, tets: ArrayLike) -> tuple[np.ndarray, np.ndarray]:
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


class _Problem:
    """The assembled stiffness and the bases on one mesh (internal)."""

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
        self.height = float(points[:, 2].max())
        self._lu: dict[str, tuple[Any, np.ndarray]] = {}

    # -- faces ----------------------------------------------------------------------------
    def boundary_facets(self, geometry: SensorGeometry | None, which: str) -> np.ndarray:
        m = self.mesh
        bf = m.boundary_facets()
        fp = m.p[:, m.facets[:, bf]]  # (3, 3 vertices, nb)
        H = geometry.height if geometry is not None else self.height
        tol = FACE_TOL * H
        if which == "bottom":
            return bf[(np.abs(fp[2]) <= tol).all(axis=0)]
        if which == "top":
            on = (np.abs(fp[2] - H) <= tol).all(axis=0)
            return bf[on]
        if which in SIDE_FACES:  # a plane side face of a cuboid: x or y at the mesh's extent
            k, sign = SIDE_FACES[which]
            edge = m.p[k].max() if sign > 0 else m.p[k].min()
            return bf[(np.abs(fp[k] - edge) <= tol).all(axis=0)]
        if which == "socket":
            if geometry is None:
                raise ConfigError("boundary_facets(which='socket') needs the sensor geometry")
            R = geometry.socket_radius
            if R <= 0:
                raise ConfigError(f"geometry {geometry.name!r}: socket_radius={R!r}, expected a socket (> 0)")
            c = geometry.socket_center
            cen = fp.mean(axis=1)  # (3, nb)
            r = np.linalg.norm(fp - c[:, None, None], axis=0)  # (3, nb)
            on_sphere = (np.abs(r - R) <= max(0.05 * R, 10 * FACE_TOL * R)).all(axis=0)
            below = cen[2] < H - tol
            return bf[on_sphere & below]
        raise ConfigError(f"which={which!r}: expected 'bottom', 'top', 'socket' or one of {list(SIDE_FACES)}")

    def facet_basis(self, facets: np.ndarray, intorder: int):
        from skfem import FacetBasis  # heavy: only where the elasticity is assembled

        return FacetBasis(self.mesh, self.elem, facets=facets, intorder=intorder)

    def load_vector(self, fb, traction: np.ndarray) -> np.ndarray:
        """Assemble int t . v dA for a traction given at the facet quadrature points (3, nf, nq)."""
        from skfem import LinearForm, asm  # heavy: only where the elasticity is assembled

        @LinearForm
        def form(v, w):
            return w.t[0] * v[0] + w.t[1] * v[1] + w.t[2] * v[2]

        return asm(form, fb, t=traction)

    def solve(self, f: np.ndarray, fixed: np.ndarray, load: Mapping[str, Any], resultant: np.ndarray,
              delta: np.ndarray | None = None) -> MechanicsSolution:
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

    def _theta_vertices(self, u: np.ndarray) -> np.ndarray:
        """-div u at the reference vertices of each (re-oriented) cell, mapped to the input order."""
        g = self._vertex_basis.interpolate(u).grad  # (3, 3, m, 4)
        th = -(g[0, 0] + g[1, 1] + g[2, 2])  # (m, 4) in the order of self.tets
        flipped = (self.tets != self.tets_in).any(axis=1)
        th[flipped] = th[flipped][:, [0, 1, 3, 2]]
        return th


_CACHE: dict[str, _Problem] = {}
_CACHE_SIZE = 2


def _problem(points: np.ndarray, tets: np.ndarray, mat: Material) -> _Problem:
    """The assembled problem for a mesh and material, reused across loads (a small LRU cache).

    Solving many loads on one mesh (scenes, calibration, tests) then assembles and factorises the
    stiffness once; the key is a hash of the arrays' bytes and of (E, nu).
    """
    h = hashlib.sha1(points.tobytes())
    h.update(tets.tobytes())
    h.update(np.array([mat.E, mat.nu]).tobytes())
    key = h.hexdigest()
    prob = _CACHE.pop(key, None) or _Problem(points, tets, mat)
    _CACHE[key] = prob
    while len(_CACHE) > _CACHE_SIZE:
        _CACHE.pop(next(iter(_CACHE)))
    return prob


def release() -> None:
    """Drop the assembled problems and their factors (call after a batch of loads, e.g. the
    calibration, so that a long-running process does not keep hundreds of MB)."""
    _CACHE.clear()


def _fixed_bottom(prob: _Problem, geometry: SensorGeometry) -> np.ndarray:
    bottom = prob.boundary_facets(geometry, "bottom")
    if len(bottom) == 0:
        raise ConfigError("mesh: no boundary facet on the bottom face z = 0 to fix")
    return prob.basis.get_dofs(facets=bottom).flatten()


# ----------------------------------------------------------------------------------------------
def _socket_contact(n: np.ndarray, w: np.ndarray, force: np.ndarray) -> np.ndarray:
    """Newton for a = k delta with int max(0, -n.a) (-n) dA = F (see module docstring).

    Parameters
    ----------
    n : (3, Q) outward unit normals at the quadrature points
    w : (Q,) quadrature weights (area)
    force : (3,) N

    Returns
    -------
    a : (3,) Pa
    """
    fnorm = float(np.linalg.norm(force))
    area = float(w.sum())

    def G(a: np.ndarray) -> float:
        p = np.maximum(0.0, -(a @ n))
        return 0.5 * float(w @ p**2) - float(force @ a)

    def grad(a: np.ndarray) -> np.ndarray:
        p = np.maximum(0.0, -(a @ n))
        return -(n * (w * p)).sum(axis=1) - force

    H_all = (n * w) @ n.T
    a = np.linalg.solve(H_all, force) if np.linalg.cond(H_all) < 1e12 else force / area
    g = grad(a)
    for it in range(100):
        if np.linalg.norm(g) <= NEWTON_TOL * fnorm:
            log.debug("socket contact: Newton converged in %d iterations", it)
            return a
        active = (a @ n) < 0
        H = (n * (w * active)) @ n.T + 1e-12 * area * np.eye(3)
        step = -np.linalg.solve(H, g)
        g0, G0, t = float(g @ step), G(a), 1.0
        while G(a + t * step) > G0 + 1e-4 * t * g0 and t > 1e-12:
            t *= 0.5
        if t <= 1e-12:  # no descent left: rounding level
            break
        a = a + t * step
        g = grad(a)
        if not np.isfinite(a).all() or np.linalg.norm(a) > 1e6 * fnorm / area:
            break
    # Newton can stall at rounding level before NEWTON_TOL on some meshes (a line search that finds no
    # descent; seen at 1.2e-9 on a fresh pytetwild mesh): a resultant within 1e-6 of |F| is a force
    # error of a micronewton per newton, far below the sensor's noise, and is accepted. A force the
    # socket cannot carry leaves a residual of order |F|.
    if np.isfinite(a).all() and np.linalg.norm(g) <= CONTACT_ACCEPT_TOL * fnorm:
        return a
    raise ConfigError(
        f"force={tuple(float(f) for f in force)} N: the socket contact did not converge "
        f"(residual {np.linalg.norm(g) / fnorm:.2e} of |F|); expected a force the socket can carry, "
        f"elevation {CARRIED_ELEVATION_DEG[0]:g}..{CARRIED_ELEVATION_DEG[1]:g} deg"
    )


def solve_socket_load(
    points: ArrayLike, tets: ArrayLike, geometry: SensorGeometry, force: ArrayLike
) -> MechanicsSolution:
    """Displacement of the body under the ball's force on the socket wall, bottom face fixed.

    Frictionless contact of REFERENCE_SENSOR.md s.4: t = -p n with p = k max(0, -n . delta),
    delta chosen so that the integral of t over the socket wall (the same facet quadrature that
    builds the load vector) equals ``force``; hence the discrete resultant equals the force to
    ~1e-12 relative and the moment about the socket centre is the discretisation error of the
    faceted sphere.

    Parameters
    ----------
    points : (n, 3) array_like
        Vertices, m, body frame (z up, bottom face at z = 0).
    tets : (m, 4) array_like of int
    geometry : SensorGeometry
        Must have a socket (``socket_radius > 0``).
    force : (3,) array_like
        The force the ball exerts on the sensor, N, body axes (= wrench-frame axes). It must push
        into the socket: elevation atan2(-Fz, hypot(Fx, Fy)) > 0 deg; the reference range is
        15..90 deg (lower elevations are solved, with a warning: rim contact, mesh-dependent).

    Returns
    -------
    MechanicsSolution
        With ``delta`` = k delta (Pa) and ``resultant`` the discrete traction integral.

    Raises
    ------
    ConfigError
        Bad shapes, a force that pulls out of the socket or is not finite, no socket facets.
    """
    p, t = _check_mesh(points, tets)
    F = np.asarray(force, dtype=float)
    if F.shape != (3,) or not np.isfinite(F).all():
        raise ConfigError(f"force={force!r}: expected 3 finite components in newtons")
    load = {"type": "socket", "force": F.tolist()}
    prob = _problem(p, t, geometry.material)
    fixed = _fixed_bottom(prob, geometry)
    facets = prob.boundary_facets(geometry, "socket")
    if len(facets) == 0:
        raise ConfigError(
            f"mesh: no boundary facet on the socket sphere (centre {geometry.socket_center.tolist()} m, "
            f"radius {geometry.socket_radius} m)"
        )
    fnorm = float(np.linalg.norm(F))
    if fnorm == 0.0:
        return prob.solve(np.zeros(prob.basis.N), fixed, load, np.zeros(3), np.zeros(3))
    elevation = math.degrees(math.atan2(-F[2], math.hypot(F[0], F[1])))
    lo, hi = CARRIED_ELEVATION_DEG
    if elevation <= 0.0:
        raise ConfigError(
            f"force={tuple(F.tolist())} N (elevation {elevation:.2f} deg): the socket cannot carry a force "
            f"that does not push into it; expected elevation {lo:g}..{hi:g} deg (solvable above 0 deg)"
        )
    fb = prob.facet_basis(facets, _SOCKET_INTORDER)
    n = fb.normals.reshape(3, -1)
    w = fb.dx.reshape(-1)

    _, miss = nnls(-n, F)  # is F in the cone of the facets' inward pushes -n?
    if miss > 1e-9 * fnorm:
        lowest = float(np.degrees(np.arctan2(n[2], np.hypot(n[0], n[1]))).min())
        raise ConfigError(
            f"force={tuple(F.tolist())} N (elevation {elevation:.2f} deg): the faceted socket of this mesh "
            f"cannot carry it (its facets carry elevations down to about {lowest:.1f} deg; a finer mesh "
            f"reaches lower); expected elevation {lo:g}..{hi:g} deg"
        )
    if elevation < lo - 1e-9:
        log.warning(
            "force %s N: elevation %.1f deg is below the carried range %g..%g deg; rim contact, "
            "mesh-dependent stresses", F.tolist(), elevation, lo, hi,
        )
    a = _socket_contact(n, w, F)
    pres = np.maximum(0.0, -(a @ fb.normals.reshape(3, -1))).reshape(fb.dx.shape)  # (nf, nq)
    traction = -pres[None] * fb.normals  # (3, nf, nq)
    resultant = (traction * fb.dx[None]).sum(axis=(1, 2))
    f = prob.load_vector(fb, traction)
    return prob.solve(f, fixed, load, resultant, a)


# ----------------------------------------------------------------------------------------------
def _patch_mask(patch: Mapping[str, Any], x: np.ndarray, y: np.ndarray, i: int) -> np.ndarray:
    if not isinstance(patch, Mapping):
        raise ConfigError(f"patches[{i}]={patch!r}: expected a mapping with 'shape' and 'center'")
    shape = patch.get("shape")
    try:
        cx, cy = (float(v) for v in patch["center"])
    except (KeyError, TypeError, ValueError) as err:
        raise ConfigError(f"patches[{i}].center={patch.get('center')!r}: expected (x, y) in metres") from err
    if shape == "square":
        s = float(patch.get("size", float("nan")))
        if not s > 0:
            raise ConfigError(f"patches[{i}].size={patch.get('size')!r}: expected a positive side length, m")
        return (np.abs(x - cx) <= s / 2) & (np.abs(y - cy) <= s / 2)
    if shape == "circle":
        r = float(patch.get("radius", float("nan")))
        if not r > 0:
            raise ConfigError(f"patches[{i}].radius={patch.get('radius')!r}: expected a positive radius, m")
        return np.hypot(x - cx, y - cy) <= r
    raise ConfigError(f"patches[{i}].shape={shape!r}: expected one of 'square', 'circle'")


def solve_patch_load(
    points: ArrayLike,
    tets: ArrayLike,
    geometry: SensorGeometry,
    patches: Sequence[Mapping[str, Any]],
    total_force: float,
) -> MechanicsSolution:
    """Displacement under uniform normal pressure on regions of one face, bottom face fixed.

    The face is the top one, or a side face of a cuboid given by ``face`` ('+x', '-x', '+y', '-y';
    the same for every patch of the load), where ``center`` holds the face's own two coordinates
    ((y, z) on +-x, (x, z) on +-y). A patch is ``{"shape": "square", "size": s, "center": (x, y)}`` (axis-aligned, side s) or
    ``{"shape": "circle", "radius": r, "center": (x, y)}``, metres. One pressure acts on the union
    of the patches, so the force splits over the patches by area. Approximation: a top-face
    quadrature point (degree-4 rule, 6 per facet) is loaded when it lies inside a patch, so a
    patch edge is resolved to within a facet; the pressure is then scaled so that the discrete
    resultant is exactly -total_force times the face's outward normal.

    Parameters
    ----------
    points : (n, 3) array_like
    tets : (m, 4) array_like of int
    geometry : SensorGeometry
    patches : sequence of mappings
    total_force : float
        Total normal force, N, positive when pressing into the face.

    Returns
    -------
    MechanicsSolution
    """
    p, t = _check_mesh(points, tets)
    if not (isinstance(total_force, (int, float, np.floating, np.integer)) and math.isfinite(total_force)):
        raise ConfigError(f"total_force={total_force!r}: expected a finite number of newtons")
    if len(patches) == 0:
        raise ConfigError("patches=[]: expected at least one patch")
    load = {"type": "patches", "patches": [dict(q) for q in patches], "total_force": float(total_force)}
    prob = _problem(p, t, geometry.material)
    fixed = _fixed_bottom(prob, geometry)
    faces = {q.get("face", "top") if isinstance(q, Mapping) else None for q in patches}
    face = faces.pop()
    if faces or face not in _FACE_AXES:
        raise ConfigError(f"patches: face {sorted(map(str, faces | {face}))}: expected one face of "
                          f"{list(_FACE_AXES)} for every patch of a load")
    if face != "top" and geometry.shape != "cuboid":
        raise ConfigError(f"patches: face={face!r} needs a cuboid body, not a {geometry.shape}")
    top = prob.boundary_facets(geometry, face)
    if len(top) == 0:
        raise ConfigError(f"mesh: no boundary facet on the {face} face")
    fb = prob.facet_basis(top, _PATCH_INTORDER)
    X = np.asarray(fb.global_coordinates())  # (3, nf, nq)
    a, b = _FACE_AXES[face]
    inside = np.zeros(fb.dx.shape, dtype=bool)
    for i, q in enumerate(patches):
        mask = _patch_mask(q, X[a], X[b], i)
        if not mask.any():
            raise ConfigError(f"patches[{i}]={dict(q)!r}: covers no part of the {face} face of the mesh")
        inside |= mask
    area = float(fb.dx[inside].sum())
    pres = np.where(inside, float(total_force) / area, 0.0)
    traction = -pres[None] * fb.normals
    resultant = (traction * fb.dx[None]).sum(axis=(1, 2))
    f = prob.load_vector(fb, traction)
    return prob.solve(f, fixed, load, resultant)


def uniaxial_compression(
    points: ArrayLike, tets: ArrayLike, material: Material, pressure: float
) -> MechanicsSolution:
    """A cuboid compressed between frictionless plates: the exact check of the solver.

    Rollers on the faces x = min, y = min and z = min (normal displacement zero: no friction, no
    rigid motion), uniform pressure on z = max. The exact solution is uniform strain
    eps_zz = -p/E, eps_xx = eps_yy = nu p / E, theta = (1 - 2 nu) p / E, which P2 reproduces.

    Parameters
    ----------
    points : (n, 3) array_like
        Vertices of an axis-aligned cuboid, m.
    tets : (m, 4) array_like of int
    material : Material
    pressure : float
        Pa, positive in compression.

    Returns
    -------
    MechanicsSolution
    """
    p, t = _check_mesh(points, tets)
    prob = _problem(p, t, material)
    lo, hi = p.min(axis=0), p.max(axis=0)
    tol = FACE_TOL * float((hi - lo).max())
    fixed = []
    for k in range(3):  # dofs are interleaved x, y, z at every location: component = index mod 3
        on = prob.basis.get_dofs(lambda x, k=k: np.abs(x[k] - lo[k]) <= tol).flatten()
        fixed.append(on[on % 3 == k])
    fixed_all = np.unique(np.concatenate([np.ravel(a) for a in fixed]).astype(np.int64))
    bf = prob.mesh.boundary_facets()
    top = bf[(np.abs(prob.mesh.p[2, prob.mesh.facets[:, bf]] - hi[2]) <= tol).all(axis=0)]
    fb = prob.facet_basis(top, _SOCKET_INTORDER)
    traction = -float(pressure) * fb.normals
    resultant = (traction * fb.dx[None]).sum(axis=(1, 2))
    f = prob.load_vector(fb, traction)
    return prob.solve(f, fixed_all, {"type": "uniaxial", "pressure": float(pressure)}, resultant)


def solve(points: ArrayLike, tets: ArrayLike, geometry: SensorGeometry, load: Mapping[str, Any]) -> MechanicsSolution:
    """Dispatch on a load mapping.

    ``{"type": "socket", "force": (fx, fy, fz)}`` -> :func:`solve_socket_load`;
    ``{"type": "patches", "patches": [...], "total_force": F}`` -> :func:`solve_patch_load`.
    """
    kind = load.get("type") if isinstance(load, Mapping) else None
    try:
        if kind == "socket":
            return solve_socket_load(points, tets, geometry, load["force"])
        if kind == "patches":
            return solve_patch_load(points, tets, geometry, load["patches"], load["total_force"])
    except KeyError as err:
        raise ConfigError(f"load={load!r}: missing key {err.args[0]!r}") from err
    raise ConfigError(f"load.type={kind!r}: expected one of 'socket', 'patches'")
