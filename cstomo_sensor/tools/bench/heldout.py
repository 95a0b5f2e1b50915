"""``cstomo bench --heldout N``: both estimators on N held-out forces at 60 and 40 dB, after a tare of
``TARE_FRAMES`` frames (its mean the reference, its spread the noise the estimators use)."""
from __future__ import annotations

import itertools
import os
import time
from pathlib import Path

import numpy as np

from ...angles import force_angles
from ...force.reference.calibration import DeviceCalibration
from ...force.reference.files import reference_of
from ...settings import default
from .models import Builder, Setting
from .report import write_rows
from .scenes import NOISE_SEED, SNR_DB, SNRS, SceneSet, errors, quantile
from .timing import run_frames, time_frames

#: Frames of each tare: the node's default (``tare_frames``).
TARE_FRAMES = default("tare_frames")


def heldout(n: int, out: str | os.PathLike, cache_dir=None, say=print, calibration: str = "") -> list[dict]:
    """Both estimators on ``n`` held-out random socket forces at 60 and 40 dB (one noise draw each),
    elevations under 32 deg reported separately (docs/physics.md#socket-contact); writes heldout.csv.
    ``calibration``: a device calibration file applied to both (fitted on this held-out device)."""

    scenes = SceneSet(n, cache_dir, say)
    builder = Builder(cache_dir, say)
    _, el, _ = force_angles(scenes.forces)
    low = np.degrees(el) < 32.0
    rows = []
    for snr in SNRS:
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


#: The one-frame reference study: each held-out load is held this many frames (0.1 s at 100 frames/s,
#: new noise on each), the loads following one another without rest (a step at each change).
HOLD_FRAMES = 10
RATE_HZ = 100.0
#: The cases of the study: (name, reference frames, the noise given with the reference, the stream's
#: noise estimation). "measured" is the tare of :func:`heldout` (TARE_FRAMES); "given" a one-frame
#: reference with the noise measured apart (the best a one-frame reference can do); "assumed" the
#: one-frame reference before the noise estimation; "estimated" the same with it.
ONE_FRAME_CASES = ((f"tare {TARE_FRAMES}, noise measured", TARE_FRAMES, True, False),
                   ("1 frame, noise given", 1, True, False),
                   ("1 frame, assumed 60 dB", 1, False, False),
                   ("1 frame, estimated", 1, False, True))


def _observe_us(frames: np.ndarray) -> float:
    """Microseconds per frame pair of the running noise estimate (:class:`~cstomo_sensor.force.reference.noise_estimate.NoiseEstimate`)."""
    from ...force.reference.noise_estimate import NoiseEstimate

    est = NoiseEstimate(frames.shape[1])
    f32 = frames.astype(np.float32)  # as the node receives them
    t = time.perf_counter()
    for f in f32:
        est.observe(f)
    return 1e6 * (time.perf_counter() - t) / len(f32)


def one_frame_reference(n: int, out: str | os.PathLike, cache_dir=None, say=print, calibration: str = "") -> list[dict]:
    """Both estimators through the node's frame stream (drift tracking on, as the node) on ``n``
    held-out loads held :data:`HOLD_FRAMES` frames each, at 60 and 40 dB, for the references of
    :data:`ONE_FRAME_CASES`: foreign-load flags (every load is on the socket: each flag is a false
    alarm), median angle and magnitude errors over every frame (the first ones, before an estimate
    is in use, included), the noise the stream ended with, and the stream's mean time per frame (its
    noise updates, milliseconds each, included), with the drift tracking on (the node's default) and off.
    Writes heldout_one_frame.csv."""
    from ...frame_path.config import StreamConfig
    from ...frame_path.loop import Results, run
    from ...frame_path.sources import ArraySource
    from ...frame_path.stream import FrameStream

    scenes = SceneSet(n, cache_dir, say)
    builder = Builder(cache_dir, say)
    forces = np.repeat(scenes.forces, HOLD_FRAMES, axis=0)
    true_mag = np.linalg.norm(forces, axis=1)
    rows = []
    for snr in SNRS:
        ref1, frames = scenes.noisy(scenes.clean, HOLD_FRAMES, snr, NOISE_SEED + int(snr))
        _, tare = scenes.noisy(scenes.ref_clean, TARE_FRAMES, snr, NOISE_SEED + 1000 + int(snr))
        ref50, noise50 = reference_of(tare)
        for name in ("linear", "model"):
            pipe, *_ = builder.pipeline(Setting(name, "estimator", estimator=name))
            pipe.set_calibration(DeviceCalibration.load(calibration) if calibration else None)
            for (case, n_ref, given, estimation), tracking in itertools.product(ONE_FRAME_CASES, (True, False)):
                # the held-out truth does not creep: neither does the stream
                stream = FrameStream(pipe, StreamConfig.offline(wrench_filter_hz=0.0, creep_per_decade=0.0,
                                                                noise_estimation=estimation, drift_tracking=tracking))
                stream.set_reference(ref50 if n_ref > 1 else ref1, noise50 if given else None, n_ref, case)
                got = Results()
                run(ArraySource(frames, rate_hz=RATE_HZ), stream, [got])
                res = got.results
                valid = np.array([r.valid for r in res])
                est = np.array([r.force for r in res])
                ang, mag = errors(est, forces)
                rel = 100 * mag / true_mag
                c = stream.counter.counts
                rows.append({"snr_db": snr, "estimator": name, "reference": case, "drift_tracking": tracking,
                             "frames": len(frames),
                             "foreign_pct": 100.0 * sum(r.foreign_load for r in res) / len(frames),
                             "implausible": int((~valid).sum()),
                             "angle_med": quantile(ang, 0.5), "angle_p90": quantile(ang, 0.9),
                             "mag_pct_med": quantile(rel, 0.5), "mag_pct_p90": quantile(rel, 0.9),
                             "noise": stream.noise_text, "frame_us_mean": 1e6 * c.proc_sum / max(c.proc_n, 1)})
    say(f"{HOLD_FRAMES} frames per load at {RATE_HZ:g} frames/s; foreign_pct: frames flagged as a foreign load "
        f"(all loads are on the socket); the noise estimate: {_observe_us(frames):.1f} us per measured frame pair")
    return write_rows(Path(out) / "heldout_one_frame.csv", rows, say)


#: The elevation bins (deg) of :func:`sigma_table`'s rows.
SIGMA_BINS = (20, 30, 40, 50, 60, 70, 80, 90.01)


def sigma_table(n: int, out: str | os.PathLike, cache_dir=None, say=print) -> list[dict]:
    """``cstomo bench --sigma-table N``: the nominal model's error by the load's direction, which the force's
    sigma takes as its calibration residual without a calibration (force/slow_states/sigma.py ``NOMINAL_ERROR``): both
    estimators on ``n`` random socket loads of the training side's simulated device (truth seed
    :data:`~.scenes.TRAIN_TRUTH_SEED`, forces :data:`~.scenes.TRAIN_FORCE_SEED`), noise-free frames against
    the noise-free reference (the estimators weighted by a 50-frame tare's noise at 60 dB): the relative
    error of the force's norm ``|F_err| / |F|``, its rms by elevation, and ``k(el)^2 = k_v^2 + k_l^2 cos^2(el)``
    fitted (``k_v^2`` the mean square over 80..90 deg, ``k_l^2`` least squares of the rest). Then the same
    loads' errors on the held-out device (truth seed :data:`~.scenes.TRUTH_SEED`), judged against the fit
    in use: ``over3sigma_pct`` of its errors beyond 3 k(el). Writes sigma_table.csv."""
    from ...force.slow_states.sigma import NOMINAL_ERROR
    from .scenes import TRAIN_FORCE_SEED, TRAIN_TRUTH_SEED, TRUTH_SEED

    builder = Builder(cache_dir, say)
    rows = []
    for side, truth_seed in (("training", TRAIN_TRUTH_SEED), ("held-out", TRUTH_SEED)):
        scenes = SceneSet(n, cache_dir, say, truth_seed=truth_seed, force_seed=TRAIN_FORCE_SEED)
        _, tare = scenes.noisy(scenes.ref_clean, TARE_FRAMES, SNR_DB, NOISE_SEED + 1060)
        noise = reference_of(tare)[1]
        f = scenes.forces
        el = np.degrees(force_angles(f)[1])
        cos2 = np.cos(np.radians(el)) ** 2
        for name in ("model", "linear"):
            pipe, *_ = builder.pipeline(Setting(name, "estimator", estimator=name))
            est, *_ = run_frames(pipe, scenes.ref_clean, scenes.clean, with_field=False, noise=noise, n_frames=TARE_FRAMES)
            rel2 = (np.linalg.norm(est - f, axis=1) / np.linalg.norm(f, axis=1)) ** 2
            kv2 = float(np.mean(rel2[el >= 80.0]))
            kl2 = max(float(np.sum((rel2 - kv2) * cos2) / np.sum(cos2 * cos2)), 0.0)
            kv, kl = NOMINAL_ERROR[name]
            used = kv * kv + kl * kl * cos2
            for lo, hi in zip(SIGMA_BINS[:-1], SIGMA_BINS[1:]):
                sel = (el >= lo) & (el < hi)
                if sel.any():
                    rows.append({"device": side, "estimator": name, "elevation": f"{lo:g}-{min(hi, 90):g}", "n": int(sel.sum()),
                                 "rms_pct": 100 * float(np.sqrt(np.mean(rel2[sel]))),
                                 "fit_pct": 100 * float(np.sqrt(np.mean(kv2 + kl2 * cos2[sel]))),
                                 "in_use_pct": 100 * float(np.sqrt(np.mean(used[sel]))),
                                 "over3sigma_pct": 100 * float(np.mean(rel2[sel] > 9 * used[sel]))})
            say(f"sigma table: {side} device, {name}: k_v {np.sqrt(kv2):.4f}, k_l {np.sqrt(kl2):.4f} (in use {kv}, {kl}); "
                f"beyond 3 k(el) with the one in use: {100 * float(np.mean(rel2 > 9 * used)):.1f} %")
    return write_rows(Path(out) / "sigma_table.csv", rows, say)
