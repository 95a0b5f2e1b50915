"""``cstomo bench``: speed and accuracy of every knob, measured on the same honest scenes.

One table (DESIGN.md, "Speed and accuracy are one table"). The held-out scenes are simulated once
per run and kept in memory: a :class:`~cstomo_sensor.simulate.Truth` on an independent 3 mm mesh
with a seed no calibration uses (:data:`TRUTH_SEED`), random socket forces (magnitude 5-40 N,
elevation 20-90 deg, any azimuth; seeded), 60 dB noise (REFERENCE_SENSOR.md sections 5, 7).
Frames are rounded to the precision of the frames file (``%.9e``), so ``cstomo estimate`` on the
written ``frames.csv`` gives exactly the numbers of the table's default row.

Knobs are varied one at a time around the default (mesh 4 mm, grid 8x8x4, Landweber k by the
discrepancy rule, no damping, float32 image product, linear estimator):

- forward mesh size (6 mm; a model and a calibration of their own),
- reconstruction grid (6x6x3, 10x10x5; the linear estimator of the same mesh is reused: the
  calibration data depend only on the mesh, so a separate calibration would give the same numbers),
- Landweber iterations (few = k/4, many = 4k) and damping (``model.with_settings``: one SVD),
- float64 instead of float32 for the per-frame image product,
- estimator ``model`` instead of ``linear``.

Measured per setting: offline build seconds (the model's recorded cold-build ``meta['seconds']``
plus what this run spent on derived matrices and the estimator), peak traced memory of building
or loading it (tracemalloc) and the process's peak RSS, per-frame time of
``pipe.process(frame, with_field=True)`` and of the estimator alone (median, p99, pinned to one
core), frames per second, force angle and magnitude errors (median, p90), image error (correlation
of the reconstructed conductivity change with the truth's change averaged onto the voxels, truth
cells assigned to the nearest voxel centre; distance between their maxima).

Stability (default setting, and the model estimator outside ``--smoke``): force 0 (noise-free frame
equal to the reference, and at 60 dB) to 40 N, elevation 15-90 deg, SNR 80-30 dB, a dead electrode
masked with ``set_bad_channels`` (and, for contrast, unmasked).

Outputs in ``--out``: ``table.csv``, ``stability.csv``, ``tradeoff.png``, the markdown table on
stdout and in ``table.md``, and the default scenes as ``reference.csv``, ``frames.csv``,
``truth.csv`` (section 6 formats).
"""
from __future__ import annotations

import argparse
import csv
import io
import os
import resource
import sys
import time
import tracemalloc
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

TRUTH_SEED = 9001  # the simulated device of the held-out scenes; no calibration or test uses it
FORCE_SEED = 20261121
NOISE_SEED = 4242
BOUND_N = 400.0  # an estimate above this (10x the range) counts as unbounded

MODES = {
    #        scenes, noisy frames per scene, timing frames
    "smoke": (2, 2, 60),
    "quick": (8, 4, 300),
    "full": (24, 8, 2000),
}


# ---------------------------------------------------------------------------------------------
# scenes (simulated once)
# ---------------------------------------------------------------------------------------------
def as_written(frames: np.ndarray) -> np.ndarray:
    """Frames rounded as the frames file writes them (``%.9e``)."""
    buf = io.StringIO()
    np.savetxt(buf, np.atleast_2d(frames), delimiter=",", fmt="%.9e")
    return np.loadtxt(io.StringIO(buf.getvalue()), delimiter=",", ndmin=2)


def random_forces(n: int, seed: int = FORCE_SEED) -> np.ndarray:
    from .angles import force_from_angles

    rng = np.random.default_rng(seed)
    mag = rng.uniform(5.0, 40.0, n)
    el = np.radians(rng.uniform(20.0, 90.0, n))
    az = rng.uniform(-np.pi, np.pi, n)
    f = np.array([force_from_angles(m, e, a) for m, e, a in zip(mag, el, az)])
    return np.array([[float(f"{v:.9g}") for v in row] for row in f])  # as the forces file holds them


class SceneSet:
    """The held-out device and its clean loaded frames, truth conductivity changes and noise."""

    def __init__(self, n_scenes: int, cache_dir=None, say=print) -> None:
        from .geometry import load_sensor
        from .simulate import Truth

        self.geometry = load_sensor("cuboid_joint")
        self.truth = Truth(self.geometry, truth_h=3e-3, mechanics_h=4e-3, seed=TRUTH_SEED, cache_dir=cache_dir)
        t = time.perf_counter()
        self.ref_clean = self.truth.reference
        self.forces = random_forces(n_scenes)
        self._theta: dict[tuple, tuple[np.ndarray, float]] = {}
        self.clean, self.dsigma = [], []
        for i, f in enumerate(self.forces):
            v, ds = self.frame_of(f)
            self.clean.append(v)
            self.dsigma.append(ds)
        self.clean = np.array(self.clean)
        self.seconds = time.perf_counter() - t
        say(f"scenes: {n_scenes} socket loads simulated on the truth mesh "
            f"({self.truth.forward.mesh.n_cells} cells) in {self.seconds:.1f} s")

    @property
    def rms(self) -> float:
        return float(np.sqrt(np.mean(self.ref_clean**2)))

    def frame_of(self, force: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(clean frame, truth dsigma per truth cell) of a socket force; one mechanics solve per
        direction (the frictionless contact problem is positively homogeneous in the force)."""
        from .material import conductivity_of_theta
        from .simulate import Load

        f = np.asarray(force, float)
        m = float(np.linalg.norm(f))
        fwd = self.truth.forward
        if m == 0.0:
            return self.ref_clean.copy(), np.zeros(fwd.mesh.n_cells)
        d = tuple(np.round(f / m, 12))
        if d not in self._theta:
            self._theta[d] = (self.truth.theta(Load("socket", force=tuple(f))), m)
        th, m0 = self._theta[d]
        sigma, _ = conductivity_of_theta(th * (m / m0), self.geometry.material)
        return fwd.voltages(sigma), sigma - fwd.sigma0

    def noisy(self, clean: np.ndarray, reps: int, snr_db: float | None, seed: int) -> tuple[np.ndarray, np.ndarray]:
        """(noisy reference, (len(clean) * reps, n_meas) noisy frames), rounded as written."""
        rng = np.random.default_rng(seed)
        std = 0.0 if snr_db is None else self.rms * 10 ** (-snr_db / 20)
        ref = self.ref_clean + rng.normal(0, std, self.ref_clean.shape)
        frames = np.repeat(np.atleast_2d(clean), reps, axis=0)
        frames = frames + rng.normal(0, std, frames.shape)
        return as_written(ref)[0], as_written(frames)

    def truth_on_voxels(self, centers: np.ndarray) -> np.ndarray:
        """(n_scenes, n_voxels) truth dsigma averaged onto voxels (nearest voxel centre, by volume)."""
        from scipy.spatial import cKDTree

        mesh = self.truth.forward.mesh
        _, vox = cKDTree(centers).query(mesh.centers)
        w = np.bincount(vox, weights=mesh.volumes, minlength=len(centers))
        out = np.array([np.bincount(vox, weights=mesh.volumes * ds, minlength=len(centers)) for ds in self.dsigma])
        return out / np.maximum(w, 1e-300)


# ---------------------------------------------------------------------------------------------
# settings
# ---------------------------------------------------------------------------------------------
@dataclass
class Setting:
    name: str
    varied: str
    mesh_mm: float = 4.0
    grid: tuple = (8, 8, 4)
    iterations: str | int = "auto"  # "auto", "few", "many" or a count
    damping: float = 0.0
    dtype: str = "float32"
    estimator: str = "linear"
    row: dict = field(default_factory=dict)


def settings_for(mode: str) -> list[Setting]:
    s = [Setting("default", "-")]
    if mode == "smoke":
        return s
    s += [Setting("grid 6x6x3", "grid", grid=(6, 6, 3)),
          Setting("grid 10x10x5", "grid", grid=(10, 10, 5)),
          Setting("iterations few", "iterations", iterations="few"),
          Setting("iterations many", "iterations", iterations="many"),
          Setting("damping 0.1", "damping", damping=0.1),
          Setting("float64", "dtype", dtype="float64"),
          Setting("estimator model", "estimator", estimator="model"),
          Setting("mesh 6 mm", "mesh", mesh_mm=6.0)]
    return s


class Builder:
    """Models and estimators, built (or loaded) once per mesh / grid and shared by settings."""

    def __init__(self, cache_dir, say=print) -> None:
        from .geometry import load_sensor

        self.cache_dir = cache_dir or None
        self.geometry = load_sensor("cuboid_joint")
        self.say = say
        self._models: dict = {}
        self._est: dict = {}

    @staticmethod
    def _traced(fn):
        tracemalloc.start()
        t = time.perf_counter()
        try:
            out = fn()
        finally:
            dt = time.perf_counter() - t
            _, peak = tracemalloc.get_traced_memory()
            tracemalloc.stop()
        return out, dt, peak / 2**20

    def model(self, h_mm: float, grid: tuple):
        from .reconstruction import ReconSpec, build_model

        key = (h_mm, tuple(grid))
        if key not in self._models:
            spec = ReconSpec(mesh_size=h_mm * 1e-3, grid=tuple(grid))
            self._models[key] = self._traced(lambda: build_model(self.geometry, spec, self.cache_dir))
        return self._models[key]

    def estimator(self, h_mm: float, name: str):
        from .estimate import build_estimator

        key = (h_mm, name)
        if key not in self._est:
            base, *_ = self.model(h_mm, (8, 8, 4))  # the calibration depends on the mesh only
            self._est[key] = self._traced(lambda: build_estimator(name, self.geometry, base, self.cache_dir))
        return self._est[key]

    def pipeline(self, s: Setting):
        """(pipeline, build seconds, build MB) for a setting."""
        from .pipeline import Pipeline

        model, t_load, mb = self.model(s.mesh_mm, s.grid)
        build_s = float(sum(model.meta.get("seconds", {}).values()))
        est, t_est, mb_est = self.estimator(s.mesh_mm, s.estimator)
        extra = 0.0
        if s.iterations != "auto" or s.damping:
            k0 = model.iterations
            k = {"auto": k0, "few": max(1, k0 // 4), "many": 4 * k0}.get(s.iterations, s.iterations)
            model, extra, mb2 = self._traced(lambda: model.with_settings(int(k), s.damping))
            mb = max(mb, mb2)
        pipe = Pipeline(self.geometry, model, est)
        if s.dtype == "float64":  # the image product in double precision (same R, widened)
            pipe._R = model.R.astype(np.float64)
            pipe._y32 = np.empty(pipe.n_meas, np.float64)
            pipe._x = np.empty(model.n_cells, np.float64)
        return pipe, build_s + extra + t_est, max(mb, mb_est)


# ---------------------------------------------------------------------------------------------
# measurements
# ---------------------------------------------------------------------------------------------
def errors(est: np.ndarray, true: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(angle error deg (NaN for a zero true force), |magnitude error| N) per frame."""
    from .angles import angle_between

    est, true = np.atleast_2d(est), np.atleast_2d(true)
    ang = np.degrees(angle_between(est, true))
    ang = np.where(np.linalg.norm(true, axis=1) > 0, ang, np.nan)
    return ang, np.abs(np.linalg.norm(est, axis=1) - np.linalg.norm(true, axis=1))


def _q(a, q):
    a = np.asarray(a, float)
    a = a[np.isfinite(a)]
    return float(np.quantile(a, q)) if a.size else float("nan")


def run_frames(pipe, ref: np.ndarray, frames: np.ndarray, with_field: bool = True):
    pipe.set_reference(ref)
    out = [pipe.process(f, with_field=with_field) for f in frames]
    forces = np.array([r.force for r in out])
    images = np.array([r.field.conductivity_change for r in out]) if with_field else None
    return forces, images, np.array([r.residual for r in out])


def image_errors(images: np.ndarray, truth_vox: np.ndarray, centers: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(correlation, peak distance mm) per frame; ``truth_vox`` row per frame."""
    corr, dist = [], []
    for x, t in zip(images, truth_vox):
        ok = np.std(x) > 0 and np.std(t) > 0
        corr.append(float(np.corrcoef(x, t)[0, 1]) if ok else float("nan"))
        dist.append(float(np.linalg.norm(centers[np.argmax(x)] - centers[np.argmax(t)]) * 1e3))
    return np.array(corr), np.array(dist)


def time_frames(pipe, frames: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Seconds per ``process(frame, with_field=True)`` and per estimator call, n frames, one core."""
    aff = os.sched_getaffinity(0) if hasattr(os, "sched_getaffinity") else None
    if aff:
        os.sched_setaffinity(0, {min(aff)})
    try:
        idx = np.arange(n) % len(frames)
        for f in frames[:3]:
            pipe.process(f, with_field=True)  # warm-up
        tp = np.empty(n)
        for j, i in enumerate(idx):
            t = time.perf_counter()
            pipe.process(frames[i], with_field=True)
            tp[j] = time.perf_counter() - t
        ys = [pipe.model.normalise(f, pipe.reference) for f in frames]
        for y in ys:
            y[pipe.bad_channels] = 0.0
        te = np.empty(n)
        for j, i in enumerate(idx):
            y = ys[i]
            t = time.perf_counter()
            pipe.estimator.estimate(y)
            te[j] = time.perf_counter() - t
    finally:
        if aff:
            os.sched_setaffinity(0, aff)
    return tp, te


TABLE_COLS = ["setting", "varied", "mesh_mm", "grid", "iterations", "damping", "dtype", "estimator",
              "n_voxels", "build_s", "build_mem_mb", "peak_rss_mb", "frame_med_ms", "frame_p99_ms",
              "estimator_med_ms", "estimator_p99_ms", "fps", "angle_med_deg", "angle_p90_deg",
              "mag_err_med_n", "mag_err_p90_n", "img_corr_med", "peak_dist_med_mm", "n_frames"]
STAB_COLS = ["setting", "case", "value", "n_frames", "finite", "bounded", "max_force_n", "angle_med_deg",
             "angle_p90_deg", "mag_err_med_n", "mag_err_p90_n", "residual_med", "max_abs_dsigma"]


def measure(s: Setting, builder: Builder, scenes: SceneSet, ref, frames, true, n_time: int) -> dict:
    pipe, build_s, mb = builder.pipeline(s)
    forces, images, _ = run_frames(pipe, ref, frames)
    s.row["forces"] = forces
    ang, mag = errors(forces, true)
    reps = len(frames) // len(scenes.forces)
    tv = np.repeat(scenes.truth_on_voxels(pipe.model.centers), reps, axis=0)
    corr, dist = image_errors(images, tv, pipe.model.centers)
    tp, te = time_frames(pipe, frames, n_time)
    return {"setting": s.name, "varied": s.varied, "mesh_mm": s.mesh_mm, "grid": "x".join(map(str, s.grid)),
            "iterations": pipe.model.iterations, "damping": s.damping, "dtype": s.dtype, "estimator": s.estimator,
            "n_voxels": pipe.model.n_cells, "build_s": build_s, "build_mem_mb": mb,
            "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0,
            "frame_med_ms": 1e3 * float(np.median(tp)), "frame_p99_ms": 1e3 * _q(tp, 0.99),
            "estimator_med_ms": 1e3 * float(np.median(te)), "estimator_p99_ms": 1e3 * _q(te, 0.99),
            "fps": 1.0 / float(np.median(tp)),
            "angle_med_deg": _q(ang, 0.5), "angle_p90_deg": _q(ang, 0.9),
            "mag_err_med_n": _q(mag, 0.5), "mag_err_p90_n": _q(mag, 0.9),
            "img_corr_med": _q(corr, 0.5), "peak_dist_med_mm": _q(dist, 0.5), "n_frames": len(frames)}


def stability(s: Setting, builder: Builder, scenes: SceneSet, mode: str, say=print) -> list[dict]:
    from .angles import force_from_angles
    from .pattern import MeasurementPattern

    pipe, *_ = builder.pipeline(s)
    rows = []
    reps = 2 if mode == "smoke" else 4

    def record(case, value, ref, frames, true, bad=None):
        pipe.set_bad_channels(np.zeros(pipe.n_meas, bool) if bad is None else bad)
        try:
            forces, images, resid = run_frames(pipe, ref, frames)
        finally:
            pipe.set_bad_channels(np.zeros(pipe.n_meas, bool))
        finite = bool(np.all(np.isfinite(forces)) and np.all(np.isfinite(images)))
        ang, mag = errors(forces, true)
        fmax = float(np.max(np.linalg.norm(forces, axis=1)))
        rows.append({"setting": s.name, "case": case, "value": value, "n_frames": len(frames), "finite": finite,
                     "bounded": finite and fmax <= BOUND_N, "max_force_n": fmax,
                     "angle_med_deg": _q(ang, 0.5), "angle_p90_deg": _q(ang, 0.9),
                     "mag_err_med_n": _q(mag, 0.5), "mag_err_p90_n": _q(mag, 0.9),
                     "residual_med": _q(resid, 0.5), "max_abs_dsigma": float(np.max(np.abs(images)))})

    # force magnitude, one direction (elevation 60 deg, azimuth 30 deg)
    # (smoke: the vertical, shared with the elevation sweep, to save a mechanics solve)
    d = force_from_angles(1.0, np.radians(90 if mode == "smoke" else 60), np.radians(0 if mode == "smoke" else 30))
    mags = [0.0, 5.0, 40.0] if mode == "smoke" else [0.0, 1.0, 5.0, 10.0, 20.0, 30.0, 40.0]
    ref, _ = scenes.noisy(scenes.ref_clean, 1, None, 0)
    record("force_N noise-free (frame == reference)", 0.0, ref, ref[None].copy(), np.zeros((1, 3)))
    for m in mags:
        v, _ = scenes.frame_of(m * d)
        ref, fr = scenes.noisy(v, reps, 60.0, NOISE_SEED + 10 + int(m))
        record("force_N (60 dB)", m, ref, fr, np.repeat((m * d)[None], len(fr), 0))
    # elevation at 20 N, azimuth 0
    els = [15.0, 90.0] if mode == "smoke" else [15.0, 20.0, 25.0, 32.0, 45.0, 60.0, 75.0, 90.0]
    for e in els:
        f = force_from_angles(20.0, np.radians(e), 0.0)
        v, _ = scenes.frame_of(f)
        ref, fr = scenes.noisy(v, reps, 60.0, NOISE_SEED + 100 + int(e))
        record("elevation_deg (20 N)", e, ref, fr, np.repeat(f[None], len(fr), 0))
    # SNR on the held-out scenes
    true = np.repeat(scenes.forces, reps, 0)
    for snr in ([80.0, 30.0] if mode == "smoke" else [80.0, 70.0, 60.0, 50.0, 40.0, 30.0]):
        ref, fr = scenes.noisy(scenes.clean, reps, snr, NOISE_SEED + 200 + int(snr))
        record("snr_db", snr, ref, fr, true)
    # dead electrode: its values read 0 V in the loaded frames
    pat = MeasurementPattern(16, 2)
    ref, fr = scenes.noisy(scenes.clean, reps, 60.0, NOISE_SEED)
    for e in ([0] if mode == "smoke" else [0, 5, 10]):
        bad = pat.electrode_rows(e)
        dead = fr.copy()
        dead[:, bad] = 0.0
        record("dead electrode masked", e + 1, ref, dead, true, bad=bad)
        record("dead electrode unmasked", e + 1, ref, dead, true)
    say(f"stability ({s.name}): {len(rows)} cases")
    return rows


# ---------------------------------------------------------------------------------------------
# output
# ---------------------------------------------------------------------------------------------
def pareto(times: np.ndarray, errs: np.ndarray) -> np.ndarray:
    """Boolean mask of the settings no other setting beats on both time and error."""
    n = len(times)
    front = np.ones(n, bool)
    for i in range(n):
        for j in range(n):
            if j != i and times[j] <= times[i] and errs[j] <= errs[i] and (times[j] < times[i] or errs[j] < errs[i]):
                front[i] = False
    return front


def write_csv(path: Path, rows: list[dict], cols: list[str]) -> None:
    with open(path, "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=cols)
        w.writeheader()
        for r in rows:
            w.writerow({k: (repr(v) if isinstance(v, float) else v) for k, v in r.items()})


MD_COLS = [("setting", "setting", "{}"), ("grid", "grid", "{}"), ("k", "iterations", "{}"),
           ("n_vox", "n_voxels", "{}"), ("build s", "build_s", "{:.1f}"), ("build MB", "build_mem_mb", "{:.0f}"),
           ("frame ms (med/p99)", None, None), ("estimator ms (med/p99)", None, None), ("fps", "fps", "{:.0f}"),
           ("angle deg (med/p90)", None, None), ("|F| err N (med/p90)", None, None),
           ("image corr", "img_corr_med", "{:.2f}"), ("peak dist mm", "peak_dist_med_mm", "{:.1f}")]


def markdown(rows: list[dict]) -> str:
    head = "| " + " | ".join(c[0] for c in MD_COLS) + " |"
    lines = [head, "|" + "---|" * len(MD_COLS)]
    for r in rows:
        cells = []
        for title, key, fmt in MD_COLS:
            if key:
                cells.append(fmt.format(r[key]))
            elif title.startswith("frame"):
                cells.append(f"{r['frame_med_ms']:.3f} / {r['frame_p99_ms']:.3f}")
            elif title.startswith("estimator"):
                cells.append(f"{r['estimator_med_ms']:.3f} / {r['estimator_p99_ms']:.3f}")
            elif title.startswith("angle"):
                cells.append(f"{r['angle_med_deg']:.2f} / {r['angle_p90_deg']:.2f}")
            else:
                cells.append(f"{r['mag_err_med_n']:.2f} / {r['mag_err_p90_n']:.2f}")
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def _labels(ax, rows, x, y) -> None:
    """Annotate points; labels of points that sit on top of each other are stacked."""
    placed: list[tuple[float, float, int]] = []
    lx, ly = np.log10(x), np.asarray(y, float)
    span = max(float(np.ptp(ly[np.isfinite(ly)])) if np.isfinite(ly).any() else 1.0, 1e-9)
    for r, a, b, xa, yb in zip(rows, lx, ly, x, y):
        n = sum(1 for (pa, pb, _) in placed if abs(pa - a) < 0.12 and abs(pb - b) < 0.04 * span)
        placed.append((a, b, n))
        ax.annotate(r["setting"], (xa, yb), textcoords="offset points", xytext=(6, 4 - 10 * n), fontsize=7)


def plot_tradeoff(rows: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    t = np.array([r["frame_med_ms"] for r in rows])
    fig, axes = plt.subplots(1, 2, figsize=(12, 4.8), dpi=90)
    for ax, key, label in ((axes[0], "angle_med_deg", "force angle error, median deg"),
                           (axes[1], "img_corr_med", "image error: 1 - correlation with truth, median")):
        e = np.array([r[key] for r in rows], float)
        if key == "img_corr_med":
            e = 1.0 - e
        front = pareto(t, e)
        ax.scatter(t, e, c="tab:blue", zorder=3, label="setting (one knob varied)")
        o = np.argsort(t[front])
        ax.step(t[front][o], e[front][o], where="post", c="tab:red", lw=1.5, zorder=2, label="Pareto front")
        ax.scatter(t[front], e[front], facecolors="none", edgecolors="tab:red", s=120, zorder=4)
        d = [i for i, r in enumerate(rows) if r["setting"] == "default"]
        ax.scatter(t[d], e[d], marker="*", s=260, c="gold", edgecolors="k", zorder=5, label="default")
        _labels(ax, rows, t, e)
        ax.set_xscale("log")
        ax.set_xlabel("per-frame time: process(frame, with_field=True), median ms, one core")
        ax.set_ylabel(label)
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(loc="upper right", fontsize=7)
    fig.suptitle("cuboid_joint: accuracy against speed (held-out honest scenes, 60 dB)")
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def run(mode: str, out: str | os.PathLike, cache_dir=None, say=print) -> dict:
    """Run the benchmark; returns {"table": rows, "stability": rows, "paths": {...}}."""
    from .frames_io import write_forces, write_frames

    n_scenes, reps, n_time = MODES[mode]
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    scenes = SceneSet(n_scenes, cache_dir, say)
    ref, frames = scenes.noisy(scenes.clean, reps, 60.0, NOISE_SEED)
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
        if s.name == "default" or (mode != "smoke" and s.name == "estimator model"):
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


def heldout(n: int, out: str | os.PathLike, cache_dir=None, say=print) -> list[dict]:
    """Both estimators on ``n`` held-out random socket forces at 60 and 40 dB (one noise draw each),
    elevations under 32 deg reported separately (REFERENCE_SENSOR.md s.4); writes heldout.csv."""
    from .angles import force_angles

    scenes = SceneSet(n, cache_dir, say)
    builder = Builder(cache_dir, say)
    _, el, _ = force_angles(scenes.forces)
    low = np.degrees(el) < 32.0
    rows = []
    for snr in (60.0, 40.0):
        ref, frames = scenes.noisy(scenes.clean, 1, snr, NOISE_SEED + int(snr))
        for name in ("linear", "model"):
            pipe, *_ = builder.pipeline(Setting(name, "estimator", estimator=name))
            est, *_ = run_frames(pipe, ref, frames, with_field=False)
            ang, mag = errors(est, scenes.forces)
            rel = 100 * mag / np.linalg.norm(scenes.forces, axis=1)
            t = time_frames(pipe, frames, 2000)[1]
            for part, sel in (("all", np.ones(n, bool)), ("elevation >= 32", ~low), ("elevation < 32", low)):
                if not sel.any():
                    continue
                a, r = ang[sel], rel[sel]
                rows.append({"snr_db": snr, "estimator": name, "subset": part, "n": int(sel.sum()),
                             "angle_med": _q(a, 0.5), "angle_p90": _q(a, 0.9), "angle_max": float(np.max(a)),
                             "mag_pct_med": _q(r, 0.5), "mag_pct_p90": _q(r, 0.9),
                             "estimator_ms_med": float(np.median(t)) * 1e3})
    cols = list(rows[0])
    write_csv(Path(out) / "heldout.csv", rows, cols)
    say("| " + " | ".join(cols) + " |\n|" + "---|" * len(cols))
    for r in rows:
        say("| " + " | ".join(f"{v:.3g}" if isinstance(v, float) else str(v) for v in r.values()) + " |")
    return rows


def greit(out: str | os.PathLike, cache_dir=None, say=print) -> list[dict]:
    """GREIT-style figures (Adler et al. 2009) of the default model for a +20 % inclusion of radius
    3 mm at several places, simulated honestly (independent mesh, mismatch, 60 dB): amplitude
    response (image integral / true contrast integral), position error (half-maximum centroid to
    the true centre), resolution (equivalent radius of the half-maximum region, mm); greit.csv."""
    from .simulate import Load, add_noise

    scenes_truth = SceneSet(0, cache_dir, say).truth
    builder = Builder(cache_dir, say)
    model, *_ = builder.model(4.0, (8, 8, 4))
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


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="cstomo bench", description=__doc__.splitlines()[0])
    g = p.add_mutually_exclusive_group()
    g.add_argument("--smoke", action="store_true", help="default setting only, 2 scenes (under a minute, warm caches)")
    g.add_argument("--quick", action="store_true", help="every knob, 8 scenes (a few minutes)")
    g.add_argument("--pyeit", action="store_true", help="comparison with pyEIT (needs `pip install pyeit`)")
    g.add_argument("--heldout", type=int, metavar="N", help="both estimators on N held-out forces at 60 and 40 dB")
    g.add_argument("--greit", action="store_true", help="GREIT-style figures for inclusions at several places")
    p.add_argument("--out", required=True, help="output directory")
    p.add_argument("--cache-dir", default="", help="cache directory (default: the user's cache)")
    a = p.parse_args(sys.argv[1:] if argv is None else argv)
    if os.environ.get("OPENBLAS_NUM_THREADS") != "1":
        print("cstomo bench: note: OPENBLAS_NUM_THREADS is not 1; timings are pinned to one core anyway",
              file=sys.stderr)
    if a.pyeit:
        try:
            import pyeit  # noqa: F401  (optional; never a dependency of the package)
        except ImportError:
            print("cstomo bench --pyeit: pyEIT is not installed (.venv/bin/pip install pyeit)", file=sys.stderr)
            return 2
        from .bench_pyeit import run as run_pyeit

        run_pyeit(a.out, a.cache_dir or None)
        return 0
    if a.heldout or a.greit:
        Path(a.out).mkdir(parents=True, exist_ok=True)
        (heldout(a.heldout, a.out, a.cache_dir or None) if a.heldout else greit(a.out, a.cache_dir or None))
        return 0
    run("smoke" if a.smoke else "quick" if a.quick else "full", a.out, a.cache_dir or None)
    return 0


if __name__ == "__main__":
    sys.exit(main())
