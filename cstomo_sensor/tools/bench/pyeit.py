"""``cstomo bench --pyeit``: pyEIT on the same mesh, protocol and honest data as ours.

pyEIT (``pip install pyeit``; never a dependency of this package) is imported only here. What it
can and cannot do for ``cuboid_joint``:

- it takes a 3D tetrahedral mesh (``PyEITMesh(node, element)``, tetrahedra must be positively
  oriented in its convention: we reorder them), so it runs on our own forward mesh;
- it takes a custom protocol (``PyEITProtocol(ex_mat, meas_mat, keep_ba)``): our 16 drive pairs
  and 13 measurement pairs per drive, in the 208-value order of docs/physics.md#measurement-order;
- it has point electrodes only (one mesh node per electrode; "CEM is under development" in its
  ``Forward.solve``): no disc area, no contact impedance. We use the boundary node nearest each
  electrode's centre. Its currents are unit: we scale by the drive current;
- its Jacobian inverts the dense node stiffness matrix and loops over elements in Python, and its
  JAC solver forms the dense n_elem x n_elem matrix J^T J and inverts it: on our 4 mm mesh
  (17 k tetrahedra) that is a 2.4 GB matrix and an O(n^3) inverse, so the comparison runs on the
  6 mm mesh (both sides, same mesh).

Measured in one run: homogeneous forward voltages (ours: complete electrode model, 8 mA; pyEIT:
point electrodes) and their agreement, agreement of the relative difference signals dV/V of the
held-out loads (the quantity difference imaging uses), the Jacobians' agreement, time of forward
solve, Jacobian, reconstruction set-up and per-frame solve (both sides timed in this run, doing the
same work: set-up = forward solve + Jacobian + matrix; per frame = raw frame to image with the
normalisation, float64; ours solves for one value per basis voxel and publishes their average on
the image voxels, pyEIT solves for one per tetrahedron), and
image quality (correlation with the truth change averaged onto our voxels, distance of the
maxima; ours weighted and plain, pyEIT's JAC averaged onto the same voxels) on the bench's
held-out scenes.
"""
from __future__ import annotations

import json
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import scipy.sparse
from scipy.spatial import cKDTree

from ...inverse.reconstruction import ReconSpec, model_of_mesh, voxel_basis
from ...model.cem import ForwardModel
from ...model.geometry import load_sensor
from ...model.mesh import MeshSpec, build_mesh
from ...settings import DEFAULT_SENSOR
from .models import PLAIN
from .scenes import NOISE_SEED, SNR_DB, SceneSet, image_errors

MESH_SIZE = 6.0e-3  # m


def _pyeit_mesh(mesh, geometry, sigma0: float):
    from pyeit.mesh.wrapper import PyEITMesh  # optional: never a dependency of the package

    pts, tets = mesh.points, mesh.tets.copy()
    x = pts[tets]
    s = x[:, [2, 3, 0, 1]] - x[:, [1, 2, 3, 0]]
    neg = np.linalg.det(s[:, :3]) < 0
    tets[neg] = tets[neg][:, [1, 0, 2, 3]]  # pyEIT needs its "CCW" orientation (no abs in its volume)
    bnd = np.unique(mesh.boundary)
    el_pos = np.array([bnd[np.argmin(np.linalg.norm(pts[bnd] - np.asarray(e.center), axis=1))]
                       for e in geometry.electrodes])
    ref = int(np.argmin(np.linalg.norm(pts - [0, 0, 0], axis=1)))  # bottom centre, far from electrodes
    return PyEITMesh(node=pts, element=tets, perm=sigma0, el_pos=el_pos, ref_node=ref), el_pos


def _protocol(pattern):
    from pyeit.eit.protocol import PyEITProtocol  # optional: never a dependency of the package

    rows = pattern.rows
    drives = np.unique(rows[:, 0])
    ex = pattern.pairs[drives]
    meas = np.stack([pattern.pairs[rows[rows[:, 0] == d, 1]] for d in drives])
    order = np.concatenate([np.flatnonzero(rows[:, 0] == d) for d in drives])
    assert np.array_equal(order, np.arange(len(rows))), "our 208 values are grouped by drive"
    return PyEITProtocol(ex, meas, np.ones(meas.shape[0] * meas.shape[1], bool))


class PyeitJac:
    """pyEIT's one-step JAC on our mesh and protocol, its per-tetrahedron images averaged (by volume)
    onto our voxels; ``setup_s`` is its set-up time (Jacobian and H), measured here."""

    LABEL = "JAC kotre p=0.5 lamb=0.01, normalised Jacobian and data"

    def __init__(self, geometry, mesh, pattern, grid) -> None:
        from pyeit.eit.fem import EITForward  # optional: never a dependency of the package
        from pyeit.eit.jac import JAC  # optional: never a dependency of the package

        sigma0 = geometry.material.sigma0
        self.pmesh, _ = _pyeit_mesh(mesh, geometry, sigma0)
        self.fwd = EITForward(self.pmesh, _protocol(pattern))
        self.solver = JAC(self.pmesh, self.fwd.protocol)
        _, self.setup_s = _timed(lambda: self.solver.setup(p=0.5, lamb=0.01, method="kotre", jac_normalized=True,
                                                           perm=np.full(mesh.n_cells, sigma0)))
        cell_voxel, self.centers, self.volumes = voxel_basis(geometry, mesh, grid)
        n_vox = len(self.volumes)
        w = mesh.volumes / np.bincount(cell_voxel, weights=mesh.volumes, minlength=n_vox)[cell_voxel]
        self._avg = scipy.sparse.csr_matrix((w, (cell_voxel, np.arange(mesh.n_cells))), shape=(n_vox, mesh.n_cells))

    def solve(self, frames: np.ndarray, ref: np.ndarray) -> list:
        """Per-tetrahedron conductivity change (S/m) of each frame."""
        return [self.solver.solve(f, ref, normalize=True) for f in frames]

    def voxels(self, ds) -> np.ndarray:
        """(n_frames, n_voxels) volume averages of :meth:`solve`'s images."""
        return np.array([self._avg @ np.real(d) for d in ds])


def _timed(fn, repeat: int = 1):
    best, out = np.inf, None
    for _ in range(repeat):
        t = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - t)
    return out, best


def _agree(a, b) -> dict:
    a, b = np.ravel(a), np.ravel(b)
    scale = float(a @ b / (b @ b))
    return {"corr": float(np.corrcoef(a, b)[0, 1]),
            "rel_rms_diff": float(np.linalg.norm(a - b) / np.linalg.norm(a)),
            "best_scale_b_to_a": scale,
            "rel_rms_diff_after_scale": float(np.linalg.norm(a - scale * b) / np.linalg.norm(a))}


def run(out, cache_dir=None, n_scenes: int = 8, reps: int = 2, say=print) -> dict:
    import pyeit  # optional: never a dependency of the package
    from pyeit.eit.fem import EITForward  # optional: never a dependency of the package

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    g = load_sensor(DEFAULT_SENSOR)
    sigma0 = g.material.sigma0
    I = g.drive_current
    mesh = build_mesh(g, MeshSpec(h=MESH_SIZE), cache_dir)
    fm = ForwardModel(g, mesh)
    pmesh, el_pos = _pyeit_mesh(mesh, g, sigma0)
    fwd = EITForward(pmesh, _protocol(fm.pattern))
    say(f"pyEIT {pyeit.__version__ if hasattr(pyeit, '__version__') else ''} on our {MESH_SIZE * 1e3:g} mm mesh: "
        f"{mesh.n_nodes} nodes, {mesh.n_cells} tetrahedra")
    r: dict = {"mesh_mm": MESH_SIZE * 1e3, "nodes": mesh.n_nodes, "cells": mesh.n_cells}

    # forward voltages, homogeneous
    v_ours, t_ours = _timed(lambda: fm.voltages(), 3)
    v_py, t_py = _timed(lambda: fwd.solve_eit(np.full(mesh.n_cells, sigma0)) * I, 3)
    r["forward"] = {"ours_s": t_ours, "pyeit_s": t_py, "ratio_pyeit_over_ours": t_py / t_ours,
                    **_agree(v_ours, v_py)}
    say(f"forward: ours {t_ours * 1e3:.0f} ms, pyEIT {t_py * 1e3:.0f} ms; agreement {r['forward']}")

    # Jacobians (dV/dsigma per cell), homogeneous
    J_ours, tj_ours = _timed(lambda: fm.jacobian())
    (J_py, _), tj_py = _timed(lambda: fwd.compute_jac(perm=np.full(mesh.n_cells, sigma0)))
    J_py = -J_py * I  # pyEIT's Jacobian is -dV/dsigma (its solve returns -H dv)
    r["jacobian"] = {"ours_s": tj_ours, "pyeit_s": tj_py, "ratio_pyeit_over_ours": tj_py / tj_ours,
                     **_agree(J_ours, J_py),
                     "row_corr_median": float(np.median([np.corrcoef(a, b)[0, 1] for a, b in zip(J_ours, J_py)]))}
    say(f"jacobian: ours {tj_ours:.2f} s, pyEIT {tj_py:.2f} s; corr {r['jacobian']['corr']:.3f}")

    # honest data (the bench's held-out device and loads)
    scenes = SceneSet(n_scenes, cache_dir, say)
    ref, frames = scenes.noisy(scenes.clean, reps, SNR_DB, NOISE_SEED)
    # relative difference signals of the truth loads' conductivity, on this mesh, both solvers

    _, near = cKDTree(scenes.truth.forward.mesh.centers).query(mesh.centers)
    dvs_ours, dvs_py = [], []
    for ds in scenes.dsigma:
        sig = sigma0 + ds[near]
        dvs_ours.append(fm.voltages(sig) / v_ours - 1)
        dvs_py.append(fwd.solve_eit(sig) * I / v_py - 1)
    r["difference_signal"] = _agree(np.array(dvs_ours), np.array(dvs_py))
    say(f"relative difference signals dV/V: {r['difference_signal']}")

    # reconstruction set-up and per-frame solve, both timed here on this mesh, doing the same work:
    # set-up = forward solve + Jacobian + reconstruction matrix (ours: voxel sums, weighted SVD, k, R;
    # pyEIT: its Jacobian, then H = (J^T J + lamb diag(J^T J)^p)^-1 J^T); per frame = from the raw
    # frame and reference to the image, normalisation included, float64 on both sides (our float32
    # product, what the node runs, beside it).
    spec = ReconSpec(mesh_size=MESH_SIZE)
    model, t_model = _timed(lambda: model_of_mesh(g, spec, mesh))
    plain = model_of_mesh(g, replace(spec, **PLAIN), mesh)
    jac = PyeitJac(g, mesh, fm.pattern, spec.grid)
    R64, R32, vs = model.R.astype(np.float64), model.R, model.v_scale
    x_ours, tf_ours = _timed(lambda: [R64 @ ((f - ref) / vs) for f in frames], 3)
    _, tf_ours32 = _timed(lambda: [R32 @ ((f - ref) / vs).astype(np.float32) for f in frames], 3)
    ds_py, tf_py = _timed(lambda: jac.solve(frames, ref), 3)
    n = len(frames)
    r["reconstruction"] = {"ours_setup_s": t_model, "pyeit_setup_s": jac.setup_s,
                           "setup_ratio_pyeit_over_ours": jac.setup_s / t_model,
                           "ours_frame_ms_float64": 1e3 * tf_ours / n, "ours_frame_ms_float32": 1e3 * tf_ours32 / n,
                           "pyeit_frame_ms_float64": 1e3 * tf_py / n,
                           "frame_ratio_pyeit_over_ours_float64": tf_py / tf_ours,
                           "pyeit_unknowns": mesh.n_cells, "ours_unknowns": model.S.shape[1],  # the basis voxels
                           "ours_image_voxels": model.n_cells,
                           "ours_params": f"weighted Landweber p={model.weight_power:g} k={model.iterations}",
                           "pyeit_params": PyeitJac.LABEL}
    # image quality on our voxels of this mesh (every image averaged onto the same voxels)
    centers = model.centers
    truth_vox = np.repeat(scenes.truth_on_voxels(centers), reps, axis=0)
    r["image"] = {"n_frames": n}
    for name, images in (("ours", np.array(x_ours) * sigma0), ("ours_plain_p0", model.sigma0 * plain.normalise(
            frames, ref) @ plain.R.T.astype(float)), ("pyeit", jac.voxels(ds_py))):
        c, d = image_errors(images, truth_vox, centers)
        r["image"] |= {f"{name}_corr_median": float(np.median(c)), f"{name}_peak_dist_mm_median": float(np.median(d))}
    say(f"reconstruction: {r['reconstruction']}\nimage: {r['image']}")
    (out / "pyeit.json").write_text(json.dumps(r, indent=2))
    say(f"wrote {out / 'pyeit.json'}")
    return r
