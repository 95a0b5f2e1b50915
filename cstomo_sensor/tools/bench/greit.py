"""``cstomo bench --greit``: GREIT-style image figures for inclusions at several places, for our
image before (plain Landweber, p = 0, tau = 1.1) and after (the default weighted one) and, when pyEIT is
installed, for pyEIT's one-step JAC, all on the same honest frames in one run."""
from __future__ import annotations

import os
from dataclasses import replace
from pathlib import Path

import numpy as np

from ...inverse.reconstruction import ReconSpec, build_model
from ...model.mesh import MeshSpec, build_mesh
from ...model.pattern import pattern_for
from ...model.simulate import Load, add_noise
from .models import PLAIN
from .report import write_csv
from .scenes import NOISE_SEED, SNR_DB, SceneSet

#: Inclusion centres (m, body frame): under the socket (deep and shallow), off centre, near the
#: upper electrode layer, near a bottom corner, and on the other side.
CENTRES = [(0, 0, 0.011), (0, 0, 0.005), (0.008, 0, 0.01), (0.014, 0.0, 0.015), (0.01, 0.01, 0.005),
           (-0.012, 0.006, 0.01)]
RADIUS, CONTRAST = 3e-3, 0.2


def figures(x: np.ndarray, centers: np.ndarray, volumes: np.ndarray, c) -> dict:
    """GREIT-style figures (Adler et al. 2009) of one relative image ``x`` (n_voxels,) of an inclusion
    at ``c``: amplitude response (image integral / true contrast integral), position error (half-
    maximum centroid to the true centre, mm), resolution (equivalent radius of the half-maximum
    region, mm)."""
    half = x >= 0.5 * x.max()
    w = x[half] * volumes[half]
    cen = (centers[half] * w[:, None]).sum(0) / w.sum()
    return {"amplitude_response": float((x * volumes).sum() / (CONTRAST * 4 / 3 * np.pi * RADIUS**3)),
            "position_error_mm": float(np.linalg.norm(cen - c) * 1e3),
            "resolution_radius_mm": float((3 * volumes[half].sum() / (4 * np.pi)) ** (1 / 3) * 1e3)}


def _pyeit_imager(geometry, cache_dir, say):
    """pyEIT's JAC on the pyEIT comparison's mesh, or None when pyEIT is not installed."""
    try:
        import pyeit  # noqa: F401  (optional; never a dependency of the package)

        from .pyeit import MESH_SIZE, PyeitJac
    except ImportError:
        say("pyEIT is not installed: its JAC column is left out (.venv/bin/pip install pyeit)")
        return None
    mesh = build_mesh(geometry, MeshSpec(h=MESH_SIZE), cache_dir)
    return PyeitJac(geometry, mesh, pattern_for(geometry), ReconSpec.grid)


def greit(out: str | os.PathLike, cache_dir=None, say=print) -> list[dict]:
    """The figures of every imager at every centre, simulated honestly (independent mesh, mismatch,
    60 dB; the same noisy frames for every imager); greit.csv."""
    truth = SceneSet(0, cache_dir, say).truth
    geometry = truth.geometry
    after = build_model(geometry, ReconSpec(), cache_dir)
    before = build_model(geometry, replace(ReconSpec(), **PLAIN), cache_dir)
    jac = _pyeit_imager(geometry, cache_dir, say)
    rng = np.random.default_rng(NOISE_SEED)
    ref = add_noise(truth.reference, truth.reference, SNR_DB, rng)
    rows = []
    for c in CENTRES:
        v = add_noise(truth.voltages(Load("inclusion", inclusion=(*c, RADIUS, CONTRAST))), truth.reference, SNR_DB, rng)
        images = [(f"ours p={m.weight_power:g} k={m.iterations}", m.reconstruct(v, ref) / m.sigma0, m.centers, m.volumes)
                  for m in (before, after)]
        if jac is not None:
            images.append(("pyEIT JAC", jac.voxels(jac.solve(v[None], ref))[0] / geometry.material.sigma0,
                           jac.centers, jac.volumes))
        for name, x, centers, volumes in images:
            rows.append({"imager": name, "x_mm": c[0] * 1e3, "y_mm": c[1] * 1e3, "z_mm": c[2] * 1e3,
                         **figures(x, centers, volumes, c)})
    write_csv(Path(out) / "greit.csv", rows, list(rows[0]))
    for row in rows:
        say(", ".join(f"{k} {v:.3g}" if isinstance(v, float) else f"{k} {v}" for k, v in row.items()))
    return rows
