"""``cstomo bench --greit``: GREIT-style image figures for inclusions at several places."""
from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from ...inverse.reconstruction import ReconSpec
from ...model.simulate import Load, add_noise
from .models import Builder
from .report import write_csv
from .scenes import NOISE_SEED, SceneSet


def greit(out: str | os.PathLike, cache_dir=None, say=print) -> list[dict]:
    """GREIT-style figures (Adler et al. 2009) of the default model for a +20 % inclusion of radius
    3 mm at several places, simulated honestly (independent mesh, mismatch, 60 dB): amplitude
    response (image integral / true contrast integral), position error (half-maximum centroid to
    the true centre), resolution (equivalent radius of the half-maximum region, mm); greit.csv."""

    scenes_truth = SceneSet(0, cache_dir, say).truth
    builder = Builder(cache_dir, say)
    model, *_ = builder.model(ReconSpec.mesh_size, ReconSpec.grid)
    rng = np.random.default_rng(NOISE_SEED)
    ref = add_noise(scenes_truth.reference, scenes_truth.reference, 60.0, rng)
    rows = []
    r, contrast = 3e-3, 0.2
    for c in [(0, 0, 0.011), (0, 0, 0.005), (0.008, 0, 0.01), (0.014, 0.0, 0.015), (0.01, 0.01, 0.005),
              (-0.012, 0.006, 0.01)]:
        v = add_noise(scenes_truth.voltages(Load("inclusion", inclusion=(*c, r, contrast))), scenes_truth.reference,
                      60.0, rng)
        x = model.reconstruct(v, ref) / model.sigma0  # relative change per voxel
        half = x >= 0.5 * x.max()
        cen = (model.centers[half] * (x[half] * model.volumes[half])[:, None]).sum(0) / (x[half] * model.volumes[half]).sum()
        rows.append({"x_mm": c[0] * 1e3, "y_mm": c[1] * 1e3, "z_mm": c[2] * 1e3,
                     "amplitude_response": float((x * model.volumes).sum() / (contrast * 4 / 3 * np.pi * r**3)),
                     "position_error_mm": float(np.linalg.norm(cen - c) * 1e3),
                     "resolution_radius_mm": float((3 * model.volumes[half].sum() / (4 * np.pi)) ** (1 / 3) * 1e3)})
    write_csv(Path(out) / "greit.csv", rows, list(rows[0]))
    for row in rows:
        say(", ".join(f"{k} {v:.3g}" for k, v in row.items()))
    return rows
