"""``cstomo bench --scene``: the scene's stress field and the foreign-load flag (force/checks/consistency.py).

Prints and writes scene.csv: the scene field's and the EIT image's correlation with the truth's
mean stress on the published points for the paper's planar cases; the spline's error between the
calibration directions against direct solves; the flag's false-alarm rate on random socket loads and
its detection rate on foreign presses (the held-out device, 60 dB, and 40 dB with the noise given
at 40 dB); the per-frame cost of each added step on one core.
"""
from __future__ import annotations

import os
import time
from pathlib import Path

import numpy as np

from ...angles import force_from_angles
from ...force.checks.consistency import Consistency, change_noise, mismatch_allowance
from ...force.estimators.training import CalibrationSpec
from ...frame_path.config import PipelineConfig
from ...frame_path.pipeline import Pipeline
from ...model import elasticity
from ...model.material import pressure_of_theta
from ...model.mesh import MeshSpec, build_mesh
from ...model.simulate import MECHANICS_MESH_SIZE, TRUTH_MESH_SIZE, Load, Scene, Truth, add_noise, simulate
from .report import write_csv
from .scenes import SCENES, SNRS, TRUTH_SEED, random_forces

SIDE = Load.from_dict({"patches": [{"shape": "circle", "radius": 0.004, "center": [0.005, 0.010], "face": "+y"}],
                       "total_force": 10})
TOP = Load.from_dict({"patches": [{"shape": "circle", "radius": 0.004, "center": [0.018 / 2**0.5, 0.018 / 2**0.5]}],
                      "total_force": 10})


def _per_call_us(fn, n: int = 3000) -> float:
    fn()
    t = time.perf_counter()
    for _ in range(n):
        fn()
    return (time.perf_counter() - t) / n * 1e6


def _costs(p: Pipeline, v: np.ndarray) -> dict[str, float]:
    """Microseconds per call of the frame path with and without the added steps, and of each step."""
    y = (v - p.reference) / p.model.v_scale
    f = p.process(v).force
    scene_field, p.scene_field = p.scene_field, None
    cost = {"frame with image, without scene field": _per_call_us(lambda: p.process(v))}
    p.scene_field = scene_field
    cost["frame with image and scene field"] = _per_call_us(lambda: p.process(v))
    cost["frame without fields (consistency included)"] = _per_call_us(lambda: p.process(v, with_field=False))
    cost["scene field alone"] = _per_call_us(lambda: scene_field.field(f))
    cost["consistency alone"] = _per_call_us(lambda: p.consistency(y))
    return cost


def run_scene(out: str | os.PathLike, cache_dir=None, n_loads: int = 300, say=print) -> list[dict]:
    rows: list[dict] = []
    pipe = Pipeline.build(PipelineConfig(estimator="model", cache_dir=cache_dir or ""))
    sf = pipe.scene_field

    # 1. the paper's planar cases (the scene file's own device and noise)
    scene = Scene.load(SCENES / "cuboid_planar_60db.yaml")
    ref, frames, forces = simulate(scene, cache_dir)
    truth = scene.truth(cache_dir)
    m = truth.mechanics_mesh
    sample = elasticity.point_sampler(m.points, m.tets, pipe.model.centers)
    pipe.set_reference(ref)
    for gamma, v, f in zip((30, 90, 120), frames, forces):
        r = pipe.process(v)
        true_p = pressure_of_theta(sample(elasticity.solve_socket_load(m.points, m.tets, truth.geometry, f)
                                          .theta_vertices), truth.geometry.material)
        row = {"what": f"planar {gamma} deg", "scene_corr": np.corrcoef(r.scene_field.pressure, true_p)[0, 1],
               "image_corr": np.corrcoef(r.field.pressure, true_p)[0, 1],
               "scene_peak_kpa": r.scene_field.pressure.max() / 1e3, "truth_peak_kpa": true_p.max() / 1e3}
        rows.append(row)
        say(f"{row['what']}: correlation with the truth's mean stress: scene field {row['scene_corr']:.3f}, "
            f"EIT image {row['image_corr']:.3f}; peak {row['scene_peak_kpa']:.1f} kPa (truth {row['truth_peak_kpa']:.1f})")

    # 2. the spline between directions against direct solves on its own mesh
    h = CalibrationSpec.mechanics_mesh_size
    mech = build_mesh(pipe.geometry, MeshSpec(h=h, h_electrode=h), cache_dir)
    at = elasticity.point_sampler(mech.points, mech.tets, pipe.model.centers)
    rng = np.random.default_rng(606)
    errs = []
    for _ in range(20):
        d = force_from_angles(1.0, np.radians(rng.uniform(20, 90)), rng.uniform(-np.pi, np.pi))
        t = at(elasticity.solve_socket_load(mech.points, mech.tets, pipe.geometry, d).theta_vertices)
        errs.append(np.linalg.norm(sf.theta(d) - t) / np.linalg.norm(t))
    elasticity.release()
    rows.append({"what": "spline error (20 directions)", "median": float(np.median(errs)), "max": float(np.max(errs))})
    say(f"scene field between directions (20 new directions, elevation 20-90 deg): relative L2 error "
        f"median {np.median(errs):.3f}, max {np.max(errs):.3f}")

    # 3. the flag: the held-out device, a tare of 20 frames, 3 frames per socket load; the statistic's
    # noise is the change's, the frame's and the tare's (as Pipeline._update_consistency forms it)
    n_tare = 20
    dev = Truth(pipe.geometry, truth_h=TRUTH_MESH_SIZE, mechanics_h=MECHANICS_MESH_SIZE, seed=TRUTH_SEED, cache_dir=cache_dir)
    socket = [Load("socket", force=tuple(f)) for f in random_forces(n_loads // 3 + 1)]
    clean = {"socket": [dev.voltages(ld) for ld in socket], "side": [dev.voltages(SIDE)],
             "top + socket": [dev.voltages((ld, TOP)) for ld in socket]}
    elasticity.release()
    for snr in SNRS:
        noise = change_noise(pipe.model.snr_noise(snr), n_tare)
        check = Consistency(np.asarray(pipe.estimator.y), noise, mismatch_allowance(pipe.model))
        rng = np.random.default_rng(int(snr))
        tare = np.mean([add_noise(dev.reference, dev.reference, snr, rng) for _ in range(n_tare)], axis=0)
        for what, vs in clean.items():
            reps = 3 if what == "socket" else max(1, 60 // len(vs))
            stats = [check((add_noise(v, dev.reference, snr, rng) - tare) / pipe.model.v_scale)
                     for v in vs for _ in range(reps)]
            rate = float(np.mean(np.array(stats) > check.threshold))
            rows.append({"what": f"flag {what} {snr:g} dB", "frames": len(stats), "tripped": rate,
                         "stat_median": float(np.median(stats)), "stat_p98": float(np.quantile(stats, 0.98)),
                         "stat_max": float(np.max(stats)), "threshold": check.threshold})
            say(f"flag at {snr:g} dB (noise given at {snr:g} dB), {what}: tripped on {100 * rate:.1f} % of "
                f"{len(stats)} frames (statistic median {np.median(stats):.2f}, 98th percentile "
                f"{np.quantile(stats, 0.98):.2f}, max {np.max(stats):.2f}, threshold {check.threshold:.2f})")

    # 4. per-frame cost on one core, the linear estimator and the model one (the default)
    aff = os.sched_getaffinity(0) if hasattr(os, "sched_getaffinity") else None
    if aff:
        os.sched_setaffinity(0, {min(aff)})
    try:
        for p in (Pipeline.build(PipelineConfig(estimator="linear", cache_dir=cache_dir or "")), pipe):
            p.set_reference(ref)
            name = p.estimator.__class__.__name__
            for what, us in _costs(p, frames[0]).items():
                rows.append({"what": f"cost {name}: {what}", "us": us})
                say(f"per frame ({name}): {what}: {us:.1f} us")
    finally:
        if aff:
            os.sched_setaffinity(0, aff)
    Path(out).mkdir(parents=True, exist_ok=True)
    write_csv(Path(out) / "scene.csv", rows, list(dict.fromkeys(k for r in rows for k in r)))
    return rows
