"""``cstomo bench --filter``: delay and noise reduction of ``~/wrench_filtered`` (frame_path/filter.py) on
held-out loads at 60 and 40 dB.

For each of a few held-out socket loads (the benchmark's honestly simulated device), a stream of
noisy frames at ``fs`` frames/s: 0.5 s unloaded, then the load held for 2 s. Each estimator's raw
forces go through the low-pass at several cutoffs, as the node does (on the frames' times). Reported
per SNR, estimator, frame rate and cutoff: the stated delay ``tau = 1 / (2 pi f_c)``; the measured
time from the load step to 63 % and to 95 % of the held mean force (median over the loads); the
spread (rms over the three axes of the per-axis standard deviation) of the raw and of the filtered
force over the held part after 5 tau; and their ratio. Writes filter.csv.
"""
from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from ...frame_path.filter import LowPass
from .models import Builder, Setting
from .report import write_rows
from .scenes import NOISE_SEED, SNRS, SceneSet
from .timing import run_frames

CUTOFFS_HZ = (5.0, 20.0, 50.0)
RATES_HZ = (100.0, 1000.0)
N_LOADS = 4
UNLOADED_S, HELD_S = 0.5, 2.0


def _spread(f: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.var(f, axis=0))))


def filter_bench(out: str | os.PathLike, cache_dir=None, say=print) -> list[dict]:
    scenes = SceneSet(N_LOADS, cache_dir, say)
    builder = Builder(cache_dir, say)
    rows = []
    for snr in SNRS:
        for name in ("linear", "model"):
            pipe, *_ = builder.pipeline(Setting(name, "estimator", estimator=name))
            for fs in RATES_HZ:
                n0, n1 = int(UNLOADED_S * fs), int(HELD_S * fs)
                t = np.arange(n0 + n1) / fs
                per = {fc: {"t63": [], "t95": [], "raw": [], "filt": []} for fc in CUTOFFS_HZ}
                for k, clean in enumerate(scenes.clean):
                    seed = NOISE_SEED + int(snr) + 1000 * k + int(fs)
                    ref, unloaded = scenes.noisy(scenes.ref_clean, n0, snr, seed)
                    _, loaded = scenes.noisy(clean, n1, snr, seed + 1)
                    raw = run_frames(pipe, ref, np.vstack([unloaded, loaded]), with_field=False)[0]
                    held = raw[n0:].mean(axis=0)
                    for fc in CUTOFFS_HZ:
                        lp = LowPass(fc, max_gap=1.0)
                        filt = np.array([lp(f, ti) for f, ti in zip(raw, t)])
                        # progress along the step: projection onto the held force, 0 before, 1 held
                        prog = (filt[n0:] @ held) / (held @ held)
                        step_t = t[n0 - 1]  # the filter sees the load from the last unloaded frame on
                        per[fc]["t63"].append(t[n0 + int(np.argmax(prog >= 0.632))] - step_t)
                        per[fc]["t95"].append(t[n0 + int(np.argmax(prog >= 0.95))] - step_t)
                        settled = t[n0:] > t[n0] + 5 / (2 * np.pi * fc)
                        per[fc]["raw"].append(_spread(raw[n0:][settled]))
                        per[fc]["filt"].append(_spread(filt[n0:][settled]))
                for fc in CUTOFFS_HZ:
                    p = per[fc]
                    raw_sd, filt_sd = float(np.median(p["raw"])), float(np.median(p["filt"]))
                    rows.append({"snr_db": snr, "estimator": name, "fs_hz": fs, "cutoff_hz": fc,
                                 "tau_ms": 1e3 / (2 * np.pi * fc), "t63_ms": 1e3 * float(np.median(p["t63"])),
                                 "t95_ms": 1e3 * float(np.median(p["t95"])), "raw_sd_n": raw_sd,
                                 "filtered_sd_n": filt_sd, "sd_ratio": filt_sd / raw_sd})
    return write_rows(Path(out) / "filter.csv", rows, say)
