"""Tetrahedral meshes of the sensor bodies, their electrode patches, quality.

Meshes are cached on disk (:mod:`cstomo_sensor.cache`). The meshes the default sensor needs (the
model's, the calibration's mechanics and the honest simulation's) ship with the package in
``cstomo_sensor/data/meshes`` (compressed npz, keyed like a cache entry by a hash of every input
but the mesher's version): a build whose inputs match one uses it instead of meshing, so the
default model is the same on every machine and needs no pytetwild (pytetwild gives a slightly
different mesh on every run). Any other geometry or size is meshed and cached as before.

The surface is made with pyvista, the tetrahedra with pytetwild (both imported only when a mesh is
actually built; pytetwild runs in a child process in a temporary directory, :func:`_tetrahedralize`).
One knob sets the size: ``h``, the target edge length in metres; a sizing field refines towards
``h_electrode`` at the electrodes (and ``h / 2`` at the socket wall).

Electrodes are named boundary data. Each electrode is the exact disc of its geometry: every boundary
triangle that the disc touches carries the integrals of its P1 shape functions over the covered part
(exact for triangles the disc covers whole, a 144-point midpoint rule on cut triangles), so the patch
area equals the disc's to the quadrature's accuracy whatever the mesh, and moves continuously when an
electrode is jittered (the honest-simulation mismatch).
"""
from __future__ import annotations

import logging
import os
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, field
from functools import cached_property
from importlib.metadata import PackageNotFoundError, version
from pathlib import Path

import numpy as np

from ..cache import build_lock, cache_load, cache_save, default_cache_dir, input_hash
from ..errors import ConfigError, MeshError
from ..settings import MESH_SIZE_RANGE  # m: the element sizes a mesh may be asked for
from .geometry import SensorGeometry

log = logging.getLogger(__name__)

MESH_FORMAT = 3  # bump when the mesher or the file layout changes: old cache entries are not reused
MIN_QUALITY = 0.02  # smallest accepted normalised tetrahedron quality (1 = regular, 0 = flat)


@dataclass(frozen=True)
class ElectrodePatch:
    """The boundary integrals of one electrode.

    Attributes
    ----------
    nodes : (k, 3) int ndarray, node indices of the boundary triangles the electrode touches.
    mass : (k, 3, 3) ndarray, integral of phi_i phi_j over the covered part of each triangle, m^2.
    load : (k, 3) ndarray, integral of phi_i over the covered part, m^2.
    """

    name: str
    nodes: np.ndarray
    mass: np.ndarray
    load: np.ndarray

    @property
    def area(self) -> float:
        return float(self.load.sum())

    @property
    def n_triangles(self) -> int:
        return len(self.nodes)


@dataclass(frozen=True)
class TetMesh:
    """A tetrahedral mesh in metres (body frame) with positively oriented tetrahedra.

    Attributes
    ----------
    points : (n_nodes, 3) float ndarray.
    tets : (n_cells, 4) int ndarray.
    """

    points: np.ndarray
    tets: np.ndarray
    info: dict = field(default_factory=dict, compare=False)

    def __post_init__(self) -> None:
        if self.points.ndim != 2 or self.points.shape[1] != 3:
            raise MeshError(f"{self.points.shape=}, expected (n_nodes, 3)")
        if self.tets.ndim != 2 or self.tets.shape[1] != 4:
            raise MeshError(f"{self.tets.shape=}, expected (n_cells, 4)")

    @property
    def n_nodes(self) -> int:
        return len(self.points)

    @property
    def n_cells(self) -> int:
        return len(self.tets)

    @cached_property
    def volumes(self) -> np.ndarray:
        """(n_cells,) signed volumes (positive for every accepted mesh)."""
        p = self.points[self.tets]
        return np.einsum("ij,ij->i", np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), p[:, 3] - p[:, 0]) / 6.0

    @cached_property
    def centers(self) -> np.ndarray:
        """(n_cells, 3) centroids."""
        return self.points[self.tets].mean(axis=1)

    @cached_property
    def quality(self) -> np.ndarray:
        """(n_cells,) normalised quality 6 sqrt(2) V / l_rms^3 (1 for a regular tetrahedron, 0 flat)."""
        p = self.points[self.tets]
        e = [p[:, j] - p[:, i] for i, j in ((0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3))]
        lrms = np.sqrt(sum(np.einsum("ij,ij->i", v, v) for v in e) / 6.0)
        return 6.0 * np.sqrt(2.0) * self.volumes / lrms**3

    @cached_property
    def boundary(self) -> np.ndarray:
        """(n_faces, 3) boundary triangles, ordered so that their normals point out of the body."""
        local = np.array([[1, 2, 3], [0, 3, 2], [0, 1, 3], [0, 2, 1]])  # outward for positive tets
        faces = self.tets[:, local].reshape(-1, 3)
        key = np.sort(faces, axis=1)
        _, inv, cnt = np.unique(key, axis=0, return_inverse=True, return_counts=True)
        return faces[cnt[inv.ravel()] == 1]

    def boundary_geometry(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Centroids (b, 3), unit outward normals (b, 3) and areas (b,) of :attr:`boundary`."""
        p = self.points[self.boundary]
        n = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
        a = np.linalg.norm(n, axis=1)
        return p.mean(axis=1), n / a[:, None], a / 2.0

    def summary(self) -> dict:
        q = self.quality
        return {
            "nodes": self.n_nodes,
            "cells": self.n_cells,
            "volume_m3": float(self.volumes.sum()),
            "min_quality": float(q.min()),
            "p01_quality": float(np.percentile(q, 1)),
            "min_volume_m3": float(self.volumes.min()),
        }


def check_quality(mesh: TetMesh, min_quality: float = MIN_QUALITY) -> None:
    """Raise :class:`MeshError` on inverted or near-degenerate tetrahedra."""
    q = mesh.quality
    if np.any(mesh.volumes <= 0) or q.min() < min_quality:
        raise MeshError(
            f"mesh quality: min normalised quality {q.min():.3g} (bound {min_quality}), "
            f"{int(np.sum(mesh.volumes <= 0))} inverted or flat tetrahedra"
        )


# -- electrodes --------------------------------------------------------------------------------
_SUB = 12  # cut triangles: 12 x 12 = 144 sub-triangles, midpoint rule


def _sub_barycentric(n: int = _SUB) -> np.ndarray:
    """Barycentric coordinates (n*n, 3) of the centroids of the n^2 equal sub-triangles."""
    pts = []
    for i in range(n):
        for j in range(n - i):
            pts.append(((i + 1 / 3) / n, (j + 1 / 3) / n))  # upward triangles
            if i + j < n - 1:
                pts.append(((i + 2 / 3) / n, (j + 2 / 3) / n))  # downward triangles
    a = np.array(pts)
    return np.column_stack([1 - a.sum(1), a])


_P1_MASS = (np.ones((3, 3)) + np.eye(3)) / 12.0  # int phi_i phi_j over a triangle / its area


def electrode_patches(mesh: TetMesh, geometry: SensorGeometry) -> tuple[ElectrodePatch, ...]:
    """The boundary integrals of every electrode disc of ``geometry`` on ``mesh``.

    A boundary point belongs to electrode e when its outward normal is within 45 degrees of the
    electrode's normal and its distance to the disc's axis, measured in the electrode's tangent
    plane, is at most the radius (on the cylinder this is the disc projected onto the curved wall).
    """
    cen, nrm, area = mesh.boundary_geometry()
    tri = mesh.boundary
    bary = _sub_barycentric()
    out = []
    for e in geometry.electrodes:
        c, n, r = np.asarray(e.center), np.asarray(e.normal), e.radius
        p = mesh.points[tri]  # (b, 3, 3)
        facing = nrm @ n > np.cos(np.pi / 4)
        rel = p - c
        d_axis = np.linalg.norm(rel - (rel @ n)[..., None] * n, axis=-1)  # (b, 3)
        near = facing & (np.linalg.norm(cen - c, axis=1) < r + 2 * np.sqrt(area.max() * 4))
        near &= np.abs(rel @ n).max(axis=1) < r  # on this face, not across the body
        inside_all = near & np.all(d_axis <= r, axis=1)
        idx = np.flatnonzero(near)
        mass = np.zeros((len(idx), 3, 3))
        load = np.zeros((len(idx), 3))
        full = inside_all[idx]
        mass[full] = _P1_MASS * area[idx][full, None, None]
        load[full] = area[idx][full, None] / 3.0
        cut = idx[~full]
        if len(cut):
            q = np.einsum("sk,bkd->bsd", bary, p[cut])  # (c, s, 3)
            qr = q - c
            inside = np.linalg.norm(qr - (qr @ n)[..., None] * n, axis=-1) <= r  # (c, s)
            w = inside * (area[cut] / len(bary))[:, None]  # (c, s)
            load[~full] = w @ bary
            mass[~full] = np.einsum("cs,si,sj->cij", w, bary, bary)
        keep = load.sum(axis=1) > 0
        out.append(ElectrodePatch(e.name, tri[idx[keep]], mass[keep], load[keep]))
        if not keep.any():
            raise MeshError(f"electrode {e.name} at {np.round(c * 1e3, 3)} mm touches no boundary triangle")
    return tuple(out)


def face_patch(mesh: TetMesh, facets: np.ndarray, name: str) -> ElectrodePatch:
    """An electrode covering whole boundary triangles (``facets``: boolean mask or indices into
    :attr:`TetMesh.boundary`), with exact P1 integrals."""
    tri = mesh.boundary[facets]
    _, _, area = mesh.boundary_geometry()
    a = area[facets]
    return ElectrodePatch(name, tri, _P1_MASS * a[:, None, None], np.repeat(a[:, None] / 3.0, 3, axis=1))


# -- building ----------------------------------------------------------------------------------
@dataclass(frozen=True)
class MeshSpec:
    """Every input of a mesh: the body, its electrodes (for refinement) and the size knobs (m)."""

    h: float = 3.0e-3
    h_electrode: float | None = None  # default h / 5, at most 0.6 mm
    refine_socket: bool = True

    def __post_init__(self) -> None:
        if not (MESH_SIZE_RANGE[0] <= self.h <= MESH_SIZE_RANGE[1]):
            raise ConfigError(f"mesh size h={self.h!r} m: expected 0.2 mm <= h <= 20 mm")
        if self.h_electrode is not None and not (5e-5 <= self.h_electrode <= self.h):
            raise ConfigError(f"h_electrode={self.h_electrode!r} m: expected 0.05 mm <= h_electrode <= h")

    @property
    def he(self) -> float:
        return self.h_electrode if self.h_electrode is not None else min(self.h / 5.0, 6.0e-4)


def _surface(geometry: SensorGeometry, h: float):
    import pyvista as pv  # heavy (VTK): only where a surface is made or rendered

    H = geometry.height
    if geometry.shape == "cuboid":
        lx, ly, _ = geometry.size
        body = pv.Box(bounds=(-lx / 2, lx / 2, -ly / 2, ly / 2, 0.0, H), level=8, quads=False)
    else:
        R = geometry.size[0]
        body = pv.Cylinder(center=(0, 0, H / 2), direction=(0, 0, 1), radius=R, height=H,
                           resolution=96, capping=True)
    body = body.triangulate().clean()
    if geometry.socket_radius > 0:
        sph = pv.Sphere(radius=geometry.socket_radius, center=tuple(geometry.socket_center),
                        theta_resolution=64, phi_resolution=64).triangulate()
        body = body.boolean_difference(sph).clean().triangulate()
    v = np.asarray(body.points, dtype=np.float64)
    f = np.asarray(body.faces).reshape(-1, 4)[:, 1:].astype(np.int32)
    return v, f


def _sizing_field(geometry: SensorGeometry, spec: MeshSpec):
    """A background tetrahedral grid with target edge lengths (fTetWild's --bg-mesh)."""
    import pyvista as pv  # heavy (VTK): only where a surface is made or rendered

    lo = np.array([-geometry.horizontal_half_extent] * 2 + [0.0]) - 1e-3
    hi = np.array([geometry.horizontal_half_extent] * 2 + [geometry.height]) + 1e-3
    if geometry.shape == "cuboid":
        lo[:2], hi[:2] = -np.array(geometry.size[:2]) / 2 - 1e-3, np.array(geometry.size[:2]) / 2 + 1e-3
    step = min(spec.h / 2, 1.0e-3)
    axes = [np.linspace(lo[i], hi[i], max(3, int(np.ceil((hi[i] - lo[i]) / step)) + 1)) for i in range(3)]
    grid = pv.RectilinearGrid(*axes).cast_to_unstructured_grid().triangulate()
    bp = np.asarray(grid.points, dtype=np.float64)
    bt = np.asarray(grid.cells_dict[pv.CellType.TETRA], dtype=np.int32)
    ec = geometry.electrode_centers()
    r = geometry.electrodes[0].radius
    d = np.min(np.linalg.norm(bp[:, None, :] - ec[None], axis=-1), axis=1) - r
    size = np.clip(spec.he + 0.5 * np.maximum(d, 0.0), spec.he, spec.h)
    if geometry.socket_radius > 0 and spec.refine_socket:
        ds = np.abs(np.linalg.norm(bp - geometry.socket_center, axis=1) - geometry.socket_radius)
        size = np.minimum(size, np.clip(spec.h / 2 + 0.5 * ds, spec.h / 2, spec.h))
    return bp, bt, size


def _mesh_inputs(geometry: SensorGeometry, spec: MeshSpec) -> dict:
    return {**_mesh_inputs_base(geometry, spec), "pytetwild": _pytetwild_version()}


def _pytetwild_version() -> str:
    try:
        return version("pytetwild")
    except PackageNotFoundError:  # only shipped meshes can be used; meshing will say what is missing
        return "none"


def _mesh_inputs_base(geometry: SensorGeometry, spec: MeshSpec) -> dict:
    # the electrodes are an input only where the mesh is refined at them (he < h, _sizing_field): a mesh
    # without that refinement (the mechanics') is one for every device of the body, whatever its
    # electrodes' places (a device's moved electrodes use the nominal body's shipped mechanics mesh)
    refined = spec.he < spec.h
    return {
        "format": MESH_FORMAT,
        "shape": geometry.shape,
        "size": list(geometry.size),
        "socket_radius": geometry.socket_radius,
        "electrodes": [list(e.center) + [e.radius] for e in geometry.electrodes] if refined else "not refined",
        "h": spec.h,
        "he": spec.he,
        "refine_socket": spec.refine_socket,
    }


#: Where the shipped meshes live (package data; see the module docstring).
SHIPPED_DIR = Path(__file__).resolve().parent.parent / "data" / "meshes"


def _shipped(geometry: SensorGeometry, inputs: dict) -> tuple[Path, str]:
    """Path and key of the shipped mesh for ``inputs``: the cache key without the mesher's version
    (a shipped mesh is the mesh of these inputs, whichever pytetwild is installed, if any)."""
    key = input_hash({k: v for k, v in inputs.items() if k != "pytetwild"})
    return SHIPPED_DIR / f"{geometry.shape}-{key}.npz", key


def ship_mesh(geometry: SensorGeometry, spec: MeshSpec, mesh: TetMesh) -> Path:
    """Write ``mesh`` as the shipped mesh of (geometry, spec) (maintainers: docs/design.md, "Reproducible
    models"); int32 cells, compressed."""
    path, key = _shipped(geometry, _mesh_inputs_base(geometry, spec))
    path.parent.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(path, cache_key=np.array(key), points=mesh.points, tets=mesh.tets.astype(np.int32))
    return path


#: The child that runs pytetwild (:func:`_tetrahedralize`): inputs from in.npz, outputs to out.npz, in
#: its working directory; exit status 3 when pytetwild is not installed.
_TETWILD_CHILD = """
import sys
import numpy as np
try:
    import pytetwild
except ImportError as err:
    print(err, file=sys.stderr)
    sys.exit(3)
with np.load("in.npz") as a:
    pts, tets = pytetwild.tetrahedralize(a["v"], a["f"], edge_length_abs=float(a["h"]), quiet=True, num_threads=0,
                                         bg_vertices=a["bp"], bg_tets=a["bt"], bg_values=a["size"])
np.savez("out.npz", points=pts, tets=tets)
"""


def _tetrahedralize(v: np.ndarray, f: np.ndarray, h: float, bp: np.ndarray, bt: np.ndarray, size: np.ndarray,
                    ) -> tuple[np.ndarray, np.ndarray]:
    """pytetwild's tetrahedra of the surface (v, f) with edge length ``h`` and the sizing field
    (bp, bt, size), meshed in a child process whose working directory is a temporary directory,
    removed afterwards.

    fTetWild writes a debug copy of the surface, ``__tracked_surface.stl`` (about 400 kB), into the
    working directory, unconditionally (pytetwild 0.4 has no option for its path). Changing the
    working directory of this process instead would be seen by every thread (the node's), so the
    mesher runs in a child: nothing is left where ``cstomo`` or the node was started, and a crash of
    the mesher is a :class:`MeshError`, not the end of the caller. A missing pytetwild raises
    :class:`ModuleNotFoundError` naming it, as an import here would."""
    with tempfile.TemporaryDirectory(prefix="cstomo-mesh-") as tmp:
        np.savez(Path(tmp) / "in.npz", v=v, f=f, h=h, bp=bp, bt=bt, size=size)
        env = dict(os.environ, PYTHONPATH=os.pathsep.join(p for p in sys.path if p))  # this process's packages
        run = subprocess.run([sys.executable, "-c", _TETWILD_CHILD], cwd=tmp, env=env, capture_output=True,
                             text=True, errors="replace")
        if run.returncode == 3:
            raise ModuleNotFoundError(f"meshing needs pytetwild ({run.stderr.strip()})", name="pytetwild")
        if run.returncode != 0:
            tail = " | ".join(run.stderr.strip().splitlines()[-3:])
            raise MeshError(f"pytetwild failed (exit status {run.returncode}): {tail or 'no message'}")
        with np.load(Path(tmp) / "out.npz") as out:
            return out["points"], out["tets"]


def build_mesh(geometry: SensorGeometry, spec: MeshSpec = MeshSpec(), cache_dir: str | os.PathLike | None = None,
               ) -> TetMesh:
    """Mesh ``geometry`` (or load it from the cache, keyed by a hash of every input).

    ``info`` of the result holds ``cache_hit``, ``seconds`` (per stage) and the cache ``key``.
    """
    t0 = time.perf_counter()
    shipped, skey = _shipped(geometry, _mesh_inputs_base(geometry, spec))
    hit = cache_load(shipped, skey, names=("points", "tets"))  # None when absent or not for these inputs
    if hit is not None:
        return TetMesh(hit["points"], hit["tets"].astype(np.int64),
                       info={"cache_hit": True, "shipped": True, "key": skey,
                             "seconds": {"mesh": time.perf_counter() - t0}})
    inputs = _mesh_inputs(geometry, spec)
    key = input_hash(inputs)
    path = Path(cache_dir or default_cache_dir()) / "meshes" / f"{geometry.shape}-{key}.npz"
    with build_lock(path):  # one process builds it, another waits and reads it (cache.build_lock)
        hit = cache_load(path, key, names=("points", "tets"))
        if hit is not None:
            mesh = TetMesh(hit["points"], hit["tets"].astype(np.int64),
                           info={"cache_hit": True, "key": key, "seconds": {"mesh": time.perf_counter() - t0}})
            return mesh
        log.info("meshing %s with h=%.2f mm, electrodes %.2f mm (pytetwild; cached afterwards)",
                 geometry.name, spec.h * 1e3, spec.he * 1e3)
        v, f = _surface(geometry, spec.h)
        bp, bt, size = _sizing_field(geometry, spec)
        pts, tets = _tetrahedralize(v, f, spec.h, bp, bt, size)
        pts = np.ascontiguousarray(pts, dtype=np.float64)
        tets = np.ascontiguousarray(tets, dtype=np.int64)
        used = np.unique(tets)
        if len(used) != len(pts):  # drop unreferenced points
            remap = -np.ones(len(pts), dtype=np.int64)
            remap[used] = np.arange(len(used))
            pts, tets = pts[used], remap[tets]
        mesh = TetMesh(pts, tets)
        neg = mesh.volumes < 0
        if neg.any():
            tets[neg] = tets[neg][:, [0, 2, 1, 3]]
            mesh = TetMesh(pts, tets)
        check_quality(mesh)
        rel = abs(mesh.volumes.sum() - geometry.volume) / geometry.volume
        if rel > 0.01:
            raise MeshError(f"meshed volume {mesh.volumes.sum():.4g} m^3 differs from the body's "
                            f"{geometry.volume:.4g} m^3 by {rel:.1%} (bound 1%)")
        cache_save(path, key, points=pts, tets=tets)
        return TetMesh(pts, tets, info={"cache_hit": False, "key": key,
                                        "seconds": {"mesh": time.perf_counter() - t0}})
