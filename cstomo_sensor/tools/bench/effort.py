"""``cstomo bench --calibration-effort``: the user's trade of calibration effort for accuracy.

A simulated non-nominal device (a scene file; default ``scenes/cuboid_device_a_60db.yaml``: material
and electrode placement inside docs/physics.md#real-devices, honest simulation) is tared (50 frames),
calibrated on the first N of 40 random known loads (N = 0, 3, 5, 10, 20, 40; each load held for
``FRAMES_PER_LOAD`` frames), and judged on held-out loads of the same device (new forces, new noise),
for both estimators at 60 and 40 dB. Writes calibration_effort.csv, .md and calibration_effort.png.
"""
from __future__ import annotations

import os
import time
from pathlib import Path

import numpy as np

from ...force.reference.calibration import calibrate, errors
from ...force.reference.files import reference_of
from ...frame_path.config import PipelineConfig
from ...frame_path.pipeline import Pipeline
from ...model.simulate import Load, Scene, add_noise
from .report import write_csv
from .scenes import SCENES, SNRS, quantile, random_forces

DEFAULT_SCENE = SCENES / "cuboid_device_a_60db.yaml"
COUNTS = (0, 3, 5, 10, 20, 40)
FRAMES_PER_LOAD = 5
CAL_SEED, HELD_SEED = 515, 616


def calibration_effort(out: str | os.PathLike, n_held: int = 40, scene: str | os.PathLike = DEFAULT_SCENE,
                       cache_dir=None, say=print) -> list[dict]:
    t = time.perf_counter()
    sc = Scene.load(scene)
    truth = sc.truth(cache_dir)
    F_cal, F_held = random_forces(max(COUNTS), CAL_SEED), random_forces(n_held, HELD_SEED)
    clean_cal = np.array([truth.voltages(Load("socket", force=tuple(f))) for f in F_cal])
    clean_held = np.array([truth.voltages(Load("socket", force=tuple(f))) for f in F_held])
    ref = truth.reference
    say(f"device {truth.geometry.name}: {len(F_cal)} calibration + {n_held} held-out loads simulated in "
        f"{time.perf_counter() - t:.0f} s")
    rows = []
    for snr in SNRS:
        rng = np.random.default_rng(int(snr))
        tare = add_noise(np.repeat(ref[None], 50, 0), ref, snr, rng)
        cal_frames = add_noise(np.repeat(clean_cal, FRAMES_PER_LOAD, 0), ref, snr, rng)
        cal_forces = np.repeat(F_cal, FRAMES_PER_LOAD, 0)
        held = add_noise(clean_held, ref, snr, rng)
        for name in ("linear", "model"):
            pipe = Pipeline.build(PipelineConfig(estimator=name, cache_dir=str(cache_dir or "")))
            report = pipe.set_reference(*reference_of(tare), n_frames=len(tare))
            for n in COUNTS:
                t = time.perf_counter()
                if n:
                    pipe.set_calibration(calibrate(pipe, cal_frames[: n * FRAMES_PER_LOAD], cal_forces[: n * FRAMES_PER_LOAD]))
                else:
                    pipe.set_calibration(None)
                seconds = time.perf_counter() - t
                est = np.array([pipe.process(v, with_field=False, gate=False).force for v in held])
                ang, mag = errors(est, F_held)
                rows.append({"snr_db": snr, "estimator": name, "loads": n, "angle_med": quantile(ang, 0.5),
                             "angle_p90": quantile(ang, 0.9), "mag_pct_med": quantile(mag, 0.5),
                             "mag_pct_p90": quantile(mag, 0.9), "calibrate_s": seconds,
                             "reference_scale": report.factor})
                r = rows[-1]
                say(f"{snr:.0f} dB {name:6s} {n:2d} loads: angle {r['angle_med']:.2f}/{r['angle_p90']:.2f} deg, "
                    f"magnitude {r['mag_pct_med']:.2f}/{r['mag_pct_p90']:.2f} % ({seconds:.2f} s)")
    out = Path(out)
    write_csv(out / "calibration_effort.csv", rows, list(rows[0]))
    lines = ["| SNR dB | estimator | loads | angle deg med/p90 | magnitude % med/p90 | calibrate s |", "|---" * 6 + "|"]
    lines += [f"| {r['snr_db']:.0f} | {r['estimator']} | {r['loads']} | {r['angle_med']:.2f} / {r['angle_p90']:.2f} | "
              f"{r['mag_pct_med']:.2f} / {r['mag_pct_p90']:.2f} | {r['calibrate_s']:.2f} |" for r in rows]
    (out / "calibration_effort.md").write_text("\n".join(lines) + "\n")
    plot(rows, out / "calibration_effort.png", truth.geometry.name, n_held)
    return rows


def plot(rows: list[dict], path: Path, device: str, n_held: int) -> None:
    import matplotlib
    import matplotlib.ticker

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(10, 4))
    x = np.arange(len(COUNTS))
    for snr, ls in zip(SNRS, ("-", "--")):
        for name, color in (("linear", "C0"), ("model", "C1")):
            rs = [r for r in rows if r["snr_db"] == snr and r["estimator"] == name]
            for ax, key in zip(axes, ("angle_med", "mag_pct_med")):
                ax.plot(x, [r[key] for r in rs], ls, color=color, marker="o", label=f"{name}, {snr:.0f} dB")
    for ax, label in zip(axes, ("median angle error, deg", "median magnitude error, %")):
        ax.set_xticks(x, [str(c) for c in COUNTS])
        ax.set_xlabel("calibration loads")
        ax.set_ylabel(label)
        ax.set_yscale("log")
        ax.yaxis.set_major_formatter(matplotlib.ticker.FormatStrFormatter("%g"))
        ax.yaxis.set_minor_formatter(matplotlib.ticker.FormatStrFormatter("%g"))
        ax.grid(True, which="both", alpha=0.3)
    axes[0].legend()
    fig.suptitle(f"{device}: held-out accuracy ({n_held} loads) against calibration effort")
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)
