"""Linear elasticity of the rubber body under the sensor's loads: its faces, the ball's contact in the
socket and pressure patches, each solved on the P2 problem of :mod:`~cstomo_sensor.model.elastic_fem`
(assembly, factorisation, solve; :class:`MechanicsSolution`, :func:`point_sampler`, :func:`release` and
:func:`kept` are that module's, named here too). The bottom face is fixed.

Input meshes are plain arrays (``points (n, 3)`` in metres, ``tets (m, 4)`` vertex indices), e.g.
the fields of ``cstomo_sensor.model.mesh.TetMesh``; cells of either orientation are accepted.
Faces are found geometrically: the bottom face z = 0 (vertices within ``FACE_TOL`` x height), the
top face z = height (outward normal +z), and the socket wall (boundary facets on the hemisphere of
``geometry.socket_radius`` around ``geometry.socket_center``, below the top face).

Loads (docs/physics.md#loads):

* :func:`solve_socket_load` - the ball in the socket, frictionless: traction t = -p n on the socket
  wall, n the rubber's outward normal, p = k max(0, -n . delta). k only scales delta, so the
  unknown is a = k delta (Pa), found by Newton on the convex function
  G(a) = 1/2 int max(0, -n.a)^2 dA - F.a, whose gradient is (int t dA) - F. The integral is the
  same facet quadrature that builds the load vector, so the discrete resultant equals F to
  rounding error. A force must push into the socket (elevation atan2(-Fz, |Fxy|) > 0); the
  sensor carries elevations 15..90 deg (docs/physics.md#socket-contact). Below 15 deg the solve still runs (it is
  well-posed for any elevation > 0) but the contact sits on the rim, where the result depends on
  the mesh; a warning is logged.
* :func:`solve_patch_load` - uniform normal pressure on regions of the top face or of a side face.

Solver: one factorisation per mesh serves every load (elastic_fem). The contact needs no
refactorisation: the pressure law depends only on the ball's displacement a, not on the rubber's, so
each load is one linear solve with the same matrix. Every load ends the same way: a traction at the
facet quadrature points, its resultant, load vector and solve (``ElasticProblem.solve_traction``).
"""
from __future__ import annotations

import logging
import math
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from ..errors import ConfigError
from .elastic_fem import ElasticProblem, MechanicsSolution, PointSampler, check_mesh, kept, point_sampler, problem, release
from .geometry import SensorGeometry

log = logging.getLogger(__name__)

__all__ = [
    "CARRIED_ELEVATION_DEG",
    "MechanicsSolution",
    "PointSampler",
    "kept",
    "point_sampler",
    "release",
    "solve",
    "solve_patch_load",
    "solve_socket_load",
]

FACE_TOL = 1e-4
"""Relative tolerance (x body height) for a vertex to lie on a plane face; x radius for the socket."""
CARRIED_ELEVATION_DEG = (15.0, 90.0)
"""Force elevations the sensor carries (docs/physics.md#socket-contact)."""
NEWTON_TOL = 1e-12
CONTACT_ACCEPT_TOL = 1e-6  # relative resultant error accepted when Newton stalls at rounding level
"""Newton stops when |int t dA - F| <= NEWTON_TOL |F| (or, when the line search stalls at
rounding level, accepts a residual below 1e3 NEWTON_TOL |F|)."""
_SOCKET_INTORDER = 2  # p is constant per flat facet: order 2 integrates it against P2 exactly
_PATCH_INTORDER = 4  # more quadrature points resolve the patch edges better
#: The side faces a patch load can press (cuboid bodies): face -> (normal axis, sign). A patch's
#: ``center`` is given in the face's own two coordinates: (y, z) on +-x, (x, z) on +-y, (x, y) on top.
SIDE_FACES = {"+x": (0, 1), "-x": (0, -1), "+y": (1, 1), "-y": (1, -1)}
_FACE_AXES = {"top": (0, 1), "+x": (1, 2), "-x": (1, 2), "+y": (0, 2), "-y": (0, 2)}


# ----------------------------------------------------------------------------------------------
def _facets(prob: ElasticProblem, geometry: SensorGeometry, which: str) -> np.ndarray:
    """Boundary facets of a face of the sensor's body: 'bottom', 'top', a side face of
    :data:`SIDE_FACES` or 'socket' (module docstring)."""
    bf, fp = prob.boundary_facets()  # fp: (3, 3 vertices, nb)
    H = geometry.height
    tol = FACE_TOL * H
    if which == "bottom":
        return bf[(np.abs(fp[2]) <= tol).all(axis=0)]
    if which == "top":
        on = (np.abs(fp[2] - H) <= tol).all(axis=0)
        return bf[on]
    if which in SIDE_FACES:  # a plane side face of a cuboid: x or y at the mesh's extent
        k, sign = SIDE_FACES[which]
        p = prob.mesh.p
        edge = p[k].max() if sign > 0 else p[k].min()
        return bf[(np.abs(fp[k] - edge) <= tol).all(axis=0)]
    if which == "socket":
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


def _fixed_bottom(prob: ElasticProblem, geometry: SensorGeometry) -> np.ndarray:
    bottom = _facets(prob, geometry, "bottom")
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

    Frictionless contact (docs/physics.md#socket-contact): t = -p n with p = k max(0, -n . delta),
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
    p, t = check_mesh(points, tets)
    F = np.asarray(force, dtype=float)
    if F.shape != (3,) or not np.isfinite(F).all():
        raise ConfigError(f"force={force!r}: expected 3 finite components in newtons")
    load = {"type": "socket", "force": F.tolist()}
    prob = problem(p, t, geometry.material)
    fixed = _fixed_bottom(prob, geometry)
    facets = _facets(prob, geometry, "socket")
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

    from scipy.optimize import nnls  # here, not at the top: scipy.optimize costs 0.6 s of every node's start

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
    return prob.solve_traction(fb, -pres[None] * fb.normals, fixed, load, a)


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
    p, t = check_mesh(points, tets)
    if not (isinstance(total_force, (int, float, np.floating, np.integer)) and math.isfinite(total_force)):
        raise ConfigError(f"total_force={total_force!r}: expected a finite number of newtons")
    if len(patches) == 0:
        raise ConfigError("patches=[]: expected at least one patch")
    load = {"type": "patches", "patches": [dict(q) for q in patches], "total_force": float(total_force)}
    prob = problem(p, t, geometry.material)
    fixed = _fixed_bottom(prob, geometry)
    faces = {q.get("face", "top") if isinstance(q, Mapping) else None for q in patches}
    face = faces.pop()
    if faces or face not in _FACE_AXES:
        raise ConfigError(f"patches: face {sorted(map(str, faces | {face}))}: expected one face of "
                          f"{list(_FACE_AXES)} for every patch of a load")
    if face != "top" and geometry.shape != "cuboid":
        raise ConfigError(f"patches: face={face!r} needs a cuboid body, not a {geometry.shape}")
    top = _facets(prob, geometry, face)
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
    return prob.solve_traction(fb, -pres[None] * fb.normals, fixed, load)


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
