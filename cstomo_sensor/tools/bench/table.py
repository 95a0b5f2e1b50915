"""``cstomo bench``: speed and accuracy of every knob, measured on the same honest scenes.

One table (docs/benchmark.md). The held-out scenes are simulated once
per run and kept in memory: a :class:`~cstomo_sensor.model.simulate.Truth` on an independent 3 mm mesh
with a seed no calibration uses (:data:`TRUTH_SEED`), random socket forces (magnitude 5-40 N,
elevation 20-90 deg, any azimuth; seeded), 60 dB noise (docs/physics.md#noise, #honest-simulation).
Frames are rounded to the precision of the frames file (``%.9e``), so ``cstomo estimate`` on the
written ``frames.csv`` gives exactly the numbers of the table's default row.

Knobs are varied one at a time around the default (mesh 4 mm, grid 8x8x4, Landweber k by the
discrepancy rule, no damping, float32 image product, the default estimator ``model``):

- forward mesh size (6 mm; a model and a calibration of their own),
- reconstruction basis (16x16x8; 8x8x4, the image grid itself, as before the basis existed),
- image grid (6x6x3, 10x10x5; the estimator of the same mesh is reused: the
  calibration data depend only on the mesh, so a separate calibration would give the same numbers),
- Landweber iterations (few = k/4, many = 4k) and damping (``model.with_settings``: one SVD),
- float64 instead of float32 for the per-frame image product,
- estimator ``linear`` instead of ``model`` (before issue 20 the default).

Measured per setting: offline build seconds (the model's recorded cold-build ``meta['seconds']``
plus what this run spent on derived matrices and the estimator), peak traced memory of building
or loading it (tracemalloc) and the process's peak RSS, per-frame time of
``pipe.process(frame, with_field=True)`` and of the estimator alone (median, p99, pinned to one
core), frames per second, force angle and magnitude errors (median, p90), image error (correlation
of the reconstructed conductivity change with the truth's change averaged onto the voxels, truth
cells assigned to the nearest voxel centre; distance between their maxima).

Stability (default setting, and the linear estimator outside ``--smoke``): force 0 (noise-free frame
equal to the reference, and at 60 dB) to 40 N, elevation 15-90 deg, SNR 80-30 dB, a dead electrode
masked with ``set_bad_channels`` (and, for contrast, unmasked).

Outputs in ``--out``: ``table.csv``, ``stability.csv``, ``tradeoff.png``, the markdown table on
stdout and in ``table.md``, and the default scenes as ``reference.csv``, ``frames.csv``,
``truth.csv`` (docs/formats.md).
"""
from __future__ import annotations

import os
import resource
import time
from pathlib import Path

import numpy as np

from ...angles import force_from_angles
from ...frames_io import write_forces, write_frames
from ...model.pattern import MeasurementPattern
from .models import Builder, Setting, settings_for
from .report import markdown, plot_tradeoff, write_csv
from .scenes import BOUND_N, FORCE_SEED, NOISE_SEED, SNR_DB, TRUTH_SEED, SceneSet, errors, image_errors, quantile
from .timing import run_frames, time_frames

MODES = {
    #        scenes, noisy frames per scene, timing frames
    "smoke": (2, 2, 60),
    "quick": (8, 4, 300),
    "full": (24, 8, 2000),
}


TABLE_COLS = ["setting", "varied", "mesh_mm", "grid", "basis", "iterations", "damping", "dtype", "estimator", "weight_power",
              "n_voxels", "build_s", "build_mem_mb", "peak_rss_mb", "frame_med_ms", "frame_p99_ms",
              "estimator_med_ms", "estimator_p99_ms", "fps", "angle_med_deg", "angle_p90_deg",
              "mag_err_med_n", "mag_err_p90_n", "img_corr_med", "peak_dist_med_mm", "n_frames"]
STAB_COLS = ["setting", "case", "value", "n_frames", "finite", "bounded", "max_force_n", "angle_med_deg",
             "angle_p90_deg", "mag_err_med_n", "mag_err_p90_n", "residual_med", "max_abs_dsigma", "implausible"]


def measure(s: Setting, builder: Builder, scenes: SceneSet, ref, frames, true, n_time: int) -> dict:
    pipe, build_s, mb = builder.pipeline(s)
    forces, images, *_ = run_frames(pipe, ref, frames)
    s.row["forces"] = forces
    ang, mag = errors(forces, true)
    reps = len(frames) // len(scenes.forces)
    tv = np.repeat(scenes.truth_on_voxels(pipe.model.centers), reps, axis=0)
    corr, dist = image_errors(images, tv, pipe.model.centers)
    tp, te = time_frames(pipe, frames, n_time)
    return {"setting": s.name, "varied": s.varied, "mesh_mm": s.mesh_size * 1e3, "grid": "x".join(map(str, s.grid)),
            "basis": "x".join(map(str, s.basis_grid)),
            "iterations": pipe.model.iterations, "damping": s.damping, "weight_power": pipe.model.weight_power,
            "dtype": s.dtype, "estimator": s.estimator,
            "n_voxels": pipe.model.n_cells, "build_s": build_s, "build_mem_mb": mb,
            "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0,
            "frame_med_ms": 1e3 * float(np.median(tp)), "frame_p99_ms": 1e3 * quantile(tp, 0.99),
            "estimator_med_ms": 1e3 * float(np.median(te)), "estimator_p99_ms": 1e3 * quantile(te, 0.99),
            "fps": 1.0 / float(np.median(tp)),
            "angle_med_deg": quantile(ang, 0.5), "angle_p90_deg": quantile(ang, 0.9),
            "mag_err_med_n": quantile(mag, 0.5), "mag_err_p90_n": quantile(mag, 0.9),
            "img_corr_med": quantile(corr, 0.5), "peak_dist_med_mm": quantile(dist, 0.5), "n_frames": len(frames)}


def stability(s: Setting, builder: Builder, scenes: SceneSet, mode: str, say=print) -> list[dict]:

    pipe, *_ = builder.pipeline(s)
    rows = []
    reps = 2 if mode == "smoke" else 4

    def record(case, value, ref, frames, true, bad=None):
        pipe.set_bad_channels(np.zeros(pipe.n_meas, bool) if bad is None else bad)
        try:
            forces, images, resid, implausible = run_frames(pipe, ref, frames)
        finally:
            pipe.set_bad_channels(np.zeros(pipe.n_meas, bool))
        finite = bool(np.all(np.isfinite(forces)) and np.all(np.isfinite(images)))
        ang, mag = errors(forces, true)
        fmax = float(np.max(np.linalg.norm(forces, axis=1)))
        rows.append({"setting": s.name, "case": case, "value": value, "n_frames": len(frames), "finite": finite,
                     "bounded": finite and fmax <= BOUND_N, "max_force_n": fmax,
                     "angle_med_deg": quantile(ang, 0.5), "angle_p90_deg": quantile(ang, 0.9),
                     "mag_err_med_n": quantile(mag, 0.5), "mag_err_p90_n": quantile(mag, 0.9),
                     "residual_med": quantile(resid, 0.5), "max_abs_dsigma": float(np.max(np.abs(images))),
                     "implausible": implausible})

    # force magnitude, one direction (elevation 60 deg, azimuth 30 deg)
    # (smoke: the vertical, shared with the elevation sweep, to save a mechanics solve)
    d = force_from_angles(1.0, np.radians(90 if mode == "smoke" else 60), np.radians(0 if mode == "smoke" else 30))
    mags = [0.0, 5.0, 40.0] if mode == "smoke" else [0.0, 1.0, 5.0, 10.0, 20.0, 30.0, 40.0]
    ref, _ = scenes.noisy(scenes.ref_clean, 1, None, 0)
    record("force_N noise-free (frame == reference)", 0.0, ref, ref[None].copy(), np.zeros((1, 3)))
    for m in mags:
        v, _ = scenes.frame_of(m * d)
        ref, fr = scenes.noisy(v, reps, SNR_DB, NOISE_SEED + 10 + int(m))
        record("force_N (60 dB)", m, ref, fr, np.repeat((m * d)[None], len(fr), 0))
    # elevation at 20 N, azimuth 0
    els = [15.0, 90.0] if mode == "smoke" else [15.0, 20.0, 25.0, 32.0, 45.0, 60.0, 75.0, 90.0]
    for e in els:
        f = force_from_angles(20.0, np.radians(e), 0.0)
        v, _ = scenes.frame_of(f)
        ref, fr = scenes.noisy(v, reps, SNR_DB, NOISE_SEED + 100 + int(e))
        record("elevation_deg (20 N)", e, ref, fr, np.repeat(f[None], len(fr), 0))
    # SNR on the held-out scenes
    true = np.repeat(scenes.forces, reps, 0)
    for snr in ([80.0, 30.0] if mode == "smoke" else [80.0, 70.0, 60.0, 50.0, 40.0, 30.0]):
        ref, fr = scenes.noisy(scenes.clean, reps, snr, NOISE_SEED + 200 + int(snr))
        record("snr_db", snr, ref, fr, true)
    # dead electrode: its values read 0 V in the loaded frames
    pat = MeasurementPattern(16, 2)
    ref, fr = scenes.noisy(scenes.clean, reps, SNR_DB, NOISE_SEED)
    for e in ([0] if mode == "smoke" else [0, 5, 10]):
        bad = pat.electrode_rows(e)
        dead = fr.copy()
        dead[:, bad] = 0.0
        record("dead electrode masked", e + 1, ref, dead, true, bad=bad)
        record("dead electrode unmasked", e + 1, ref, dead, true)
    say(f"stability ({s.name}): {len(rows)} cases")
    return rows


def run(mode: str, out: str | os.PathLike, cache_dir=None, say=print) -> dict:
    """Run the benchmark; returns {"table": rows, "stability": rows, "paths": {...}}."""

    n_scenes, reps, n_time = MODES[mode]
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    scenes = SceneSet(n_scenes, cache_dir, say)
    ref, frames = scenes.noisy(scenes.clean, reps, SNR_DB, NOISE_SEED)
    true = np.repeat(scenes.forces, reps, axis=0)
    note = (f"cstomo bench --{mode}: held-out scenes, truth seed {TRUTH_SEED}, forces seed {FORCE_SEED}, "
            f"noise seed {NOISE_SEED}, 60 dB")
    write_frames(out / "reference.csv", ref[None], comment=note + ", unloaded")
    write_frames(out / "frames.csv", frames, comment=note)
    write_forces(out / "truth.csv", true)
    builder = Builder(cache_dir, say)
    rows = []
    settings = settings_for(mode)
    for s in settings:
        say(f"setting {s.name} ...")
        rows.append(measure(s, builder, scenes, ref, frames, true, n_time))
    stab = []
    for s in settings:
        if s.name == "default" or (mode != "smoke" and s.name == "estimator linear"):
            stab += stability(s, builder, scenes, mode, say)
    write_csv(out / "table.csv", rows, TABLE_COLS)
    write_csv(out / "stability.csv", stab, STAB_COLS)
    plot_tradeoff(rows, out / "tradeoff.png")
    md = markdown(rows)
    threads = os.environ.get("OPENBLAS_NUM_THREADS", "unset")
    header = (f"cstomo bench --{mode}: {len(frames)} frames ({n_scenes} scenes x {reps} noise draws, 60 dB), "
              f"timing over {n_time} frames pinned to one core, OPENBLAS_NUM_THREADS={threads}, "
              f"total {time.perf_counter() - t0:.0f} s")
    (out / "table.md").write_text(header + "\n\n" + md + "\n")
    say(header)
    say(md)
    return {"table": rows, "stability": stab, "default_forces": settings[0].row["forces"], "paths": {k: out / v for k, v in (
        ("table", "table.csv"), ("stability", "stability.csv"), ("plot", "tradeoff.png"),
        ("frames", "frames.csv"), ("reference", "reference.csv"), ("truth", "truth.csv"))}}
