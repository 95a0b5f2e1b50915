"""``cstomo bench --drift``: does the zero hold when the device changes after its tare (force/drift.py)?

An honestly simulated device (the benchmark's truth: its own mesh, mismatched electrodes, 60 dB) is
tared unloaded (20 frames), then changes over :data:`RAMP_S` seconds and stays changed: a uniform
resistivity change of the rubber (the truth solved with its conductivity divided by 1 + a, its
contacts unchanged: a scaling plus a contact change, not the tracker's model), or a drive-current
change (every voltage scaled: the tracker's model exactly). Then held-out socket loads (5..30 N, any
carried direction), each held :data:`HOLD_S` s with :data:`REST_S` s rests between them, unannounced,
at :data:`RATE` frames/s. Per scenario, estimator and tracking on/off:

- ``zero_bias_n``: the norm of the mean force over the rest frames after the change (what a
  controller sees through a filter: the zero's error); ``zero_p99_n``: the 99th percentile of the
  per-frame force magnitude over those frames (the frames' own noise included);
- ``angle_deg`` / ``magnitude_pct``: median errors over the loaded frames;
- ``tracked_change``: the tracker's scale - 1 at the end; ``implausible``: frames refused;
- ``us_per_frame``: median time of one frame through the stream (``FrameStream.push``) in this run.

Writes drift.csv (and the markdown table) in ``--out``.
"""
from __future__ import annotations

import os
import time
from pathlib import Path

import numpy as np

from ...angles import angle_between, force_from_angles
from ...force.pipeline import Pipeline, PipelineConfig
from ...force.stream import FrameStream, StreamConfig
from ...model.geometry import DEFAULT_SENSOR, load_sensor
from ...model.simulate import Load, Truth, add_noise
from .report import write_rows

RATE = 100.0            # frames per second
RAMP_S = 5.0            # the change happens over this long after the tare (unloaded)
REST_S, HOLD_S = 1.0, 1.0
N_LOADS = 12
SNR_DB = 60.0
SEED = 31
UNIFORM = (-0.10, -0.05, -0.01, 0.01, 0.05, 0.10)
DRIVE = (-0.005, 0.005)


def _truth_frames(say):
    """(reference, {change: unloaded}, forces (n, 3), {change: loaded (n, 208)}): the truth at each
    uniform resistivity change (noise-free)."""
    truth = Truth(load_sensor(DEFAULT_SENSOR), seed=SEED)
    rng = np.random.default_rng(SEED)
    forces = np.array([force_from_angles(m, np.radians(e), np.radians(a)) for m, e, a in
                       zip(rng.uniform(5, 30, N_LOADS), rng.uniform(15, 85, N_LOADS), rng.uniform(-180, 180, N_LOADS))])
    sigma = [truth.conductivity(Load("socket", force=tuple(f))) for f in forces]
    s0 = truth.forward.sigma0
    unloaded, loaded = {}, {}
    for a in (0.0, *UNIFORM):
        unloaded[a] = truth.forward.voltages(s0 / (1 + a))
        loaded[a] = np.array([truth.forward.voltages(s / (1 + a)) for s in sigma])
        say(f"drift bench: truth at a uniform change of {a:+.0%}")
    return unloaded[0.0], unloaded, forces, loaded


def _run(pipe, ref, v_unloaded, v_loaded, forces, tracking, seed):
    """One scenario's stream: the figures of the module docstring."""
    rng = np.random.default_rng(seed)
    stream = FrameStream(pipe, StreamConfig(stress_field_every=0, drift_tracking=tracking))
    tare = add_noise(np.repeat(ref[None], 20, 0), ref, SNR_DB, rng)
    stream.set_reference(tare.mean(axis=0), tare.std(axis=0, ddof=1), 20, "tare")
    plan = [(ref + (v_unloaded - ref) * k / (RAMP_S * RATE), None, False) for k in range(int(RAMP_S * RATE))]
    plan += [(v_unloaded, None, True)] * int(2 * REST_S * RATE)
    for i in range(len(forces)):
        plan += [(v_loaded[i], i, False)] * int(HOLD_S * RATE) + [(v_unloaded, None, True)] * int(REST_S * RATE)
    zero, ang, mag, cost = [], [], [], []
    for k, (v, i, measured_rest) in enumerate(plan):
        frame = add_noise(v, ref, SNR_DB, rng)
        t0 = time.perf_counter()
        out = stream.push(frame, stamp_ns=int(1e9 * (1 + k / RATE)))
        cost.append(time.perf_counter() - t0)
        f = out.result.force if out is not None and out.result.valid else np.full(3, np.nan)
        if measured_rest:
            zero.append(f)
        elif i is not None and np.isfinite(f).all():
            ang.append(np.degrees(angle_between(f, forces[i])))
            mag.append(100 * abs(np.linalg.norm(f) / np.linalg.norm(forces[i]) - 1))
    zero = np.array(zero)
    ok = np.isfinite(zero).all(axis=1)
    return {"zero_bias_n": float(np.linalg.norm(zero[ok].mean(axis=0))) if ok.any() else np.nan,
            "zero_p99_n": float(np.percentile(np.linalg.norm(zero[ok], axis=1), 99)) if ok.any() else np.nan,
            "angle_deg": float(np.median(ang)) if ang else np.nan, "magnitude_pct": float(np.median(mag)) if mag else np.nan,
            "tracked_change": stream.drift.change if stream.drift is not None else 0.0,
            "implausible": stream.implausible, "us_per_frame": 1e6 * float(np.median(cost))}


def drift_bench(out: str | os.PathLike, cache_dir=None, say=print) -> list[dict]:
    ref, unloaded, forces, loaded = _truth_frames(say)
    scenarios = [("none", unloaded[0.0], loaded[0.0])]
    scenarios += [(f"uniform {a:+.0%}", unloaded[a], loaded[a]) for a in UNIFORM]
    scenarios += [(f"drive {d:+.1%}", unloaded[0.0] * (1 + d), loaded[0.0] * (1 + d)) for d in DRIVE]
    rows = []
    for estimator in ("linear", "model"):
        pipe = Pipeline.build(PipelineConfig(estimator=estimator, cache_dir=str(cache_dir or "")))
        for name, v_un, v_lo in scenarios:
            for tracking in (False, True):
                r = _run(pipe, ref, v_un, v_lo, forces, tracking, seed=7)
                rows.append({"scenario": name, "estimator": estimator, "tracking": tracking, **r})
                say(f"drift bench: {name}, {estimator}, tracking {tracking}: zero {r['zero_bias_n']:.3f} N, "
                    f"angle {r['angle_deg']:.2f} deg, magnitude {r['magnitude_pct']:.2f} %")
    Path(out).mkdir(parents=True, exist_ok=True)
    return write_rows(Path(out) / "drift.csv", rows, say)
