"""``cstomo bench --heldout N``: both estimators on N held-out forces at 60 and 40 dB, after a tare of
``TARE_FRAMES`` frames (its mean the reference, its spread the noise the estimators use)."""
from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from ...angles import force_angles
from ...force.calibration import DeviceCalibration
from ...force.device import reference_of
from .models import Builder, Setting
from .report import write_rows
from .scenes import NOISE_SEED, SceneSet, errors, quantile
from .timing import run_frames, time_frames

TARE_FRAMES = 50


def heldout(n: int, out: str | os.PathLike, cache_dir=None, say=print, calibration: str = "") -> list[dict]:
    """Both estimators on ``n`` held-out random socket forces at 60 and 40 dB (one noise draw each),
    elevations under 32 deg reported separately (docs/physics.md#socket-contact); writes heldout.csv.
    ``calibration``: a device calibration file applied to both (fitted on this held-out device)."""

    scenes = SceneSet(n, cache_dir, say)
    builder = Builder(cache_dir, say)
    _, el, _ = force_angles(scenes.forces)
    low = np.degrees(el) < 32.0
    rows = []
    for snr in (60.0, 40.0):
        _, frames = scenes.noisy(scenes.clean, 1, snr, NOISE_SEED + int(snr))
        _, tare = scenes.noisy(scenes.ref_clean, TARE_FRAMES, snr, NOISE_SEED + 1000 + int(snr))
        ref, noise = reference_of(tare)
        for name in ("linear", "model"):
            pipe, *_ = builder.pipeline(Setting(name, "estimator", estimator=name))
            pipe.set_calibration(DeviceCalibration.load(calibration) if calibration else None)
            est, *_ = run_frames(pipe, ref, frames, with_field=False, noise=noise, n_frames=TARE_FRAMES)
            ang, mag = errors(est, scenes.forces)
            rel = 100 * mag / np.linalg.norm(scenes.forces, axis=1)
            t = time_frames(pipe, frames, 2000)[1]
            for part, sel in (("all", np.ones(n, bool)), ("elevation >= 32", ~low), ("elevation < 32", low)):
                if not sel.any():
                    continue
                a, r = ang[sel], rel[sel]
                rows.append({"snr_db": snr, "estimator": name, "subset": part, "n": int(sel.sum()),
                             "angle_med": quantile(a, 0.5), "angle_p90": quantile(a, 0.9), "angle_max": float(np.max(a)),
                             "mag_pct_med": quantile(r, 0.5), "mag_pct_p90": quantile(r, 0.9),
                             "estimator_ms_med": float(np.median(t)) * 1e3})
    return write_rows(Path(out) / "heldout.csv", rows, say)
