"""``cstomo bench --drift``: does the zero hold when the device changes after its tare (force/slow_states/drift.py)?

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
- ``us_per_frame``: median time of one frame through the stream (``FrameStream.push``) in this run;
- ``over3sigma_pct``: the published frames whose error norm exceeds 3 ``sigma_n`` (force/slow_states/sigma.py; the
  aim <= 1 % where the drift is tracked or absent), ``sigma_ratio`` the median ``sigma_n`` over the
  median error (informative: within 2x).

Then the device over time (model/timeline.py: the truth solved at knots of its state, interpolated,
60 dB): a temperature gradient (10 K at 0.8 %/K over RAMP_S, +-30 % across the block along x), every electrode's
contact drifting on its own by up to 20 %, creep of a 20 N load held 10 minutes (4 % per decade,
compensated at 0 (off), 2, 4 and 6 %: ``magnitude_pct`` is the reading at the end against the reading
1 s after the load), and the 30-minute warm-up (15 K at 0.8 %/K, 30 % gradient, contacts -1 %/K,
drive +0.3 %, creep 4 % compensated at 4 %, contact tasks with unannounced rests) at :data:`WARMUP_RATE` frames/s against the same tasks
without the device's drift (``baseline``), and the warm-up without creep (what the drift alone
does). The warm-up's plot, ``drift_warmup.png``: the true uniform change (the rubber's mean
resistivity change and the drive) and the tracked one, and the zero-load readings, over the 30
minutes.

Writes drift.csv (and the markdown table) in ``--out``.
"""
from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from ...angles import angle_between, force_from_angles
from ...frame_path.config import PipelineConfig, StreamConfig
from ...frame_path.loop import Trace, run
from ...frame_path.pipeline import Pipeline
from ...frame_path.sources import ArraySource
from ...frame_path.stream import FrameStream
from ...model.geometry import load_sensor
from ...model.simulate import Load, Truth, add_noise
from ...model.timeline import ZERO, Timeline, contact_drift, held_load_creep, temperature_gradient, warmup_30min
from ...settings import DEFAULT_SENSOR, ESTIMATORS
from .report import write_rows
from .scenes import SNR_DB
from .timing import one_core

RATE = 100.0            # frames per second
RAMP_S = 300.0          # the change happens over this long after the tare (unloaded; 10 %: 2.5 K a minute)
REST_S, HOLD_S = 1.0, 1.0
N_LOADS = 12
SEED = 31
UNIFORM = (-0.10, -0.05, -0.01, 0.01, 0.05, 0.10)
DRIVE = (-0.005, 0.005)
WARMUP_RATE = 50.0


def _truth_frames(say, changes=UNIFORM):
    """(reference, {change: unloaded}, forces (n, 3), {change: loaded (n, 208)}): the truth unchanged
    and at each uniform resistivity change of ``changes`` (noise-free)."""
    truth = Truth(load_sensor(DEFAULT_SENSOR), seed=SEED)
    rng = np.random.default_rng(SEED)
    forces = np.array([force_from_angles(m, np.radians(e), np.radians(a)) for m, e, a in
                       zip(rng.uniform(5, 30, N_LOADS), rng.uniform(15, 85, N_LOADS), rng.uniform(-180, 180, N_LOADS))])
    sigma = [truth.conductivity(Load("socket", force=tuple(f))) for f in forces]
    s0 = truth.forward.sigma0
    unloaded, loaded = {}, {}
    for a in (0.0, *changes):
        unloaded[a] = truth.forward.voltages(s0 / (1 + a))
        loaded[a] = np.array([truth.forward.voltages(s / (1 + a)) for s in sigma])
        say(f"drift bench: truth at a uniform change of {a:+.0%}")
    return unloaded[0.0], unloaded, forces, loaded


def _run(pipe, ref, v_unloaded, v_loaded, forces, tracking, seed, costs: list | None = None, ramp_s: float = RAMP_S,
         creep: float = 0.0):
    """One scenario's stream: the figures of the module docstring (``costs``: a list that gets every
    frame's seconds through the stream; ``ramp_s``: the change's duration; ``creep``: the stream's
    creep_per_decade: the truth has no creep, so by default neither has the stream; the timelines'
    streams take their truth's)."""
    rng = np.random.default_rng(seed)
    stream = FrameStream(pipe, StreamConfig.offline(drift_tracking=tracking, creep_per_decade=creep))
    tare = add_noise(np.repeat(ref[None], 20, 0), ref, SNR_DB, rng)
    stream.set_reference(tare.mean(axis=0), tare.std(axis=0, ddof=1), 20, "tare")
    plan = [(ref + (v_unloaded - ref) * k / (ramp_s * RATE), None, False) for k in range(int(ramp_s * RATE))]
    plan += [(v_unloaded, None, True)] * int(2 * REST_S * RATE)
    for i in range(len(forces)):
        plan += [(v_loaded[i], i, False)] * int(HOLD_S * RATE) + [(v_unloaded, None, True)] * int(REST_S * RATE)
    frames = np.array([add_noise(v, ref, SNR_DB, rng) for v, _, _ in plan])
    trace = Trace()
    run(ArraySource(frames, rate_hz=RATE, start_s=1.0), stream, [trace])
    zero, ang, mag, cost = [], [], [], trace.seconds
    for (_, i, measured_rest), f in zip(plan, np.array(trace.forces, float)):
        if measured_rest:
            zero.append(f)
        elif i is not None and np.isfinite(f).all():
            ang.append(np.degrees(angle_between(f, forces[i])))
            mag.append(100 * abs(np.linalg.norm(f) / np.linalg.norm(forces[i]) - 1))
    if costs is not None:
        costs.extend(cost)
    zero = np.array(zero)
    ok = np.isfinite(zero).all(axis=1)
    true = np.array([forces[i] if i is not None else np.zeros(3) for _, i, _ in plan])
    return {"zero_bias_n": float(np.linalg.norm(zero[ok].mean(axis=0))) if ok.any() else np.nan,
            "zero_p99_n": float(np.percentile(np.linalg.norm(zero[ok], axis=1), 99)) if ok.any() else np.nan,
            "angle_deg": float(np.median(ang)) if ang else np.nan, "magnitude_pct": float(np.median(mag)) if mag else np.nan,
            "tracked_change": stream.slow.drift.change if stream.slow.drift is not None else 0.0,
            "implausible": stream.counter.counts.implausible, "us_per_frame": 1e6 * float(np.median(cost)),
            **_sigma(np.array(trace.forces, float), true, np.array(trace.sigma_n))}


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
    rows += _timelines(out, cache_dir, say)
    Path(out).mkdir(parents=True, exist_ok=True)
    return write_rows(Path(out) / "drift.csv", rows, say)


def frame_cost(out: str | os.PathLike, cache_dir=None, say=print, rounds: int = 5) -> list[dict]:
    """``cstomo bench --frame-cost``: the time of one frame through the stream (``FrameStream.push``:
    the plausibility gate, the estimator, the consistency statistic, the drift tracker, the creep
    compensation at the node's default, the filter and the counts; no stress field) for both
    estimators, tracking off and on, side by side: the drift bench's unchanged device (7 s at rest,
    then its held-out loads held 1 s with 1 s rests: 3100 frames, 61 % at rest; 60 dB, 100 frames/s),
    ``rounds`` rounds of every setting in turn on one pinned core, so the host's load weighs on all
    alike; median, mean (the CPU a robot pays per frame: the slow frames, e.g. a learner's batch, count) and
    90th percentile over every frame of the rounds, with the host's load average at the start and the end.
    Writes frame_cost.csv in ``out``."""
    ref, unloaded, forces, loaded = _truth_frames(say, changes=())
    pipes = {name: Pipeline.build(PipelineConfig(estimator=name, cache_dir=str(cache_dir or ""))) for name in ESTIMATORS}
    settings = [(name, tracking) for name in ESTIMATORS for tracking in (False, True)]
    costs = {s: [] for s in settings}
    load0 = os.getloadavg()[0]
    with one_core():
        for _ in range(rounds):
            for name, tracking in settings:
                _run(pipes[name], ref, unloaded[0.0], loaded[0.0], forces, tracking, seed=7, costs=costs[name, tracking],
                     ramp_s=5.0, creep=StreamConfig.creep_per_decade)
    load1 = os.getloadavg()[0]
    rows = [{"estimator": name, "tracking": tracking, "frames": len(c), "us_median": 1e6 * float(np.median(c)),
             "us_mean": 1e6 * float(np.mean(c)), "us_p90": 1e6 * float(np.percentile(c, 90)), "load_start": load0,
             "load_end": load1}
            for (name, tracking), c in costs.items()]
    Path(out).mkdir(parents=True, exist_ok=True)
    return write_rows(Path(out) / "frame_cost.csv", rows, say)


def _timeline_stream(pipe, tl: Timeline, tracking: bool, rate: float, seed: int = 7, creep: float | None = None):
    """Push a timeline's frames through a stream tared on its t = 0 state: (times, frames' forces
    (n, 3), true forces (n, 3), state, tracked scale per frame, us per frame, :func:`_sigma`'s figures)."""
    rng = np.random.default_rng(seed)
    times, frames, forces, state = tl.frames(rate, rng=rng)
    tare = tl.tare(20, rng)
    stream = FrameStream(pipe, StreamConfig.offline(drift_tracking=tracking,
                                                    creep_per_decade=tl.spec.creep if creep is None else creep))
    stream.set_reference(tare.mean(axis=0), tare.std(axis=0, ddof=1), 20, "tare")
    trace = Trace(lambda: stream.slow.scale)
    run(ArraySource(frames, (1e9 * (1 + np.asarray(times))).astype(np.int64)), stream, [trace])
    est, scale = np.array(trace.forces, float).reshape(-1, 3), np.array(trace.probed)
    return (times, est, forces, state, scale, 1e6 * float(np.median(trace.seconds)),
            _sigma(est, forces, np.array(trace.sigma_n)))


def _sigma(est, forces, sigma) -> dict:
    """The error bars' honesty over the published frames (robot bench's ``sigma_figures``): ``over3sigma_pct``
    the share whose error norm exceeds 3 ``sigma_n`` (the aim: <= 1 %), ``sigma_ratio`` the median sigma_n over
    the median error (informative: within 2x)."""
    from .robot import sigma_figures

    ok = np.isfinite(est).all(axis=1) & np.isfinite(sigma)
    fig = sigma_figures(np.linalg.norm(est[ok] - forces[ok], axis=1), sigma[ok])
    return {"over3sigma_pct": fig["over3sigma_pct"], "sigma_ratio": fig["sigma_ratio"]}


def _errors(est, forces, rest_after: float, times) -> dict:
    loaded = np.linalg.norm(forces, axis=1) > 0
    ok = np.isfinite(est).all(axis=1)
    sel = loaded & ok
    ang = np.degrees(angle_between(est[sel], forces[sel])) if sel.any() else np.array([np.nan])
    mag = 100 * np.abs(np.linalg.norm(est[sel], axis=1) / np.linalg.norm(forces[sel], axis=1) - 1)
    rest = ~loaded & ok & (times >= rest_after)
    zero = np.linalg.norm(est[rest], axis=1)
    return {"zero_bias_n": float(np.linalg.norm(est[rest].mean(axis=0))) if rest.any() else np.nan,
            "zero_p99_n": float(np.percentile(zero, 99)) if rest.any() else np.nan,
            "angle_deg": float(np.median(ang)), "magnitude_pct": float(np.median(mag)) if sel.any() else np.nan}


def _timelines(out, cache_dir, say) -> list[dict]:
    rows = []
    pipe = Pipeline.build(PipelineConfig(cache_dir=str(cache_dir or "")))
    cases = [("gradient 10 K, 30 %", temperature_gradient(10.0, 0.3, duration=RAMP_S + 10, ramp_s=RAMP_S), RATE),
             ("contact drift 20 %", contact_drift(0.2, "linear", duration=10.0, over_s=5.0), RATE)]
    for name, spec, rate in cases:
        settled = spec.duration - 4.0  # the zero over the last 4 s, after the change
        tl = Timeline(spec, DEFAULT_SENSOR, snr_db=SNR_DB, seed=SEED, cache_dir=cache_dir).prepare()
        for tracking in (False, True):
            times, est, forces, state, scale, us, sig = _timeline_stream(pipe, tl, tracking, rate)
            rows.append({"scenario": name, "estimator": pipe.estimator_name, "tracking": tracking,
                         **_errors(est, forces, settled, times), "tracked_change": float(scale[-1] - 1),
                         "implausible": int(np.isnan(est).any(axis=1).sum()), "us_per_frame": us, **sig})
            say(f"drift bench: {name}, tracking {tracking}: zero {rows[-1]['zero_bias_n']:.3f} N")
    tl = Timeline(held_load_creep(20.0, creep=0.04, on=1.0, duration=601.0), DEFAULT_SENSOR, snr_db=SNR_DB, seed=SEED,
                  cache_dir=cache_dir).prepare()
    for creep in (0.0, 0.02, 0.04, 0.06):
        times, est, forces, state, scale, us, sig = _timeline_stream(pipe, tl, True, 10.0, creep=creep)
        mag = np.linalg.norm(est, axis=1)
        early, late = np.nanmedian(mag[(times >= 1.9) & (times <= 2.1)]), np.nanmedian(mag[times >= 590.0])
        rows.append({"scenario": f"creep 4 % of 20 N held 10 min, compensated at {creep:.0%}",
                     "estimator": pipe.estimator_name, "tracking": True,
                     "zero_bias_n": np.nan, "zero_p99_n": np.nan, "angle_deg": np.nan,
                     "magnitude_pct": float(100 * (late / early - 1)), "tracked_change": float(scale[-1] - 1),
                     "implausible": 0, "us_per_frame": us, **sig})
        say(f"drift bench: creep, compensated at {creep:.0%}: the reading after 10 min is {rows[-1]['magnitude_pct']:+.1f} % "
            "of the one after 1 s (creep_drift_pct)")
    spec = warmup_30min(seed=SEED)
    still = type(spec)(**{**spec.__dict__, "temperature": ZERO, "drive": ZERO, "gradient": ZERO})
    dry = warmup_30min(seed=SEED, creep=0.0)  # the same without creep: what the drift alone does
    curves = {}
    for name, sp, trackings in (("warm-up 30 min", spec, (False, True)), ("warm-up baseline (no drift)", still, (False,)),
                                ("warm-up 30 min without creep", dry, (False, True))):
        tl = Timeline(sp, DEFAULT_SENSOR, snr_db=SNR_DB, seed=SEED, cache_dir=cache_dir).prepare()
        for tracking in trackings:
            times, est, forces, state, scale, us, sig = _timeline_stream(pipe, tl, tracking, WARMUP_RATE)
            rows.append({"scenario": name, "estimator": pipe.estimator_name, "tracking": tracking,
                         **_errors(est, forces, 0.0, times), "tracked_change": float(scale[-1] - 1),
                         "implausible": int(np.isnan(est).any(axis=1).sum()), "us_per_frame": us, **sig})
            say(f"drift bench: {name}, tracking {tracking}: zero p99 {rows[-1]['zero_p99_n']:.3f} N, angle "
                f"{rows[-1]['angle_deg']:.2f} deg, magnitude {rows[-1]['magnitude_pct']:.2f} %")
            if name.startswith("warm-up 30"):
                curves.setdefault(name, {})[tracking] = (times, est, forces, state, scale)
    _plot(curves["warm-up 30 min"], Path(out) / "drift_warmup.png")
    _plot(curves["warm-up 30 min without creep"], Path(out) / "drift_warmup_no_creep.png")
    return rows


def _plot(curves: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    times, est, forces, state, scale = curves[True]
    true = (1 + state.rho_change) * state.drive - 1
    fig, (a, b) = plt.subplots(2, 1, figsize=(9, 6), sharex=True)
    a.plot(times / 60, 100 * true, label="true: rubber's mean resistivity change and drive")
    a.plot(times / 60, 100 * (scale - 1), "--", label="tracked scale - 1")
    a.set_ylabel("uniform change (%)")
    a.legend()
    rest = np.linalg.norm(forces, axis=1) == 0
    for tracking, style in ((False, "."), (True, ".")):
        t, e = curves[tracking][0], curves[tracking][1]
        z = np.linalg.norm(e, axis=1)
        b.plot(t[rest] / 60, z[rest], style, ms=1, label=f"zero-load reading, tracking {'on' if tracking else 'off'}")
    b.set_yscale("log")
    b.set_ylabel("|F| at zero load (N)")
    b.set_xlabel("time since the tare (min)")
    b.legend(markerscale=8)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
