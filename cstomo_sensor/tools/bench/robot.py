"""``cstomo bench --drift --robot``: what a robot does to the zero and to the forces (issue 26, item 1: the measuring stick).

The device judged is never the one the tracker's directions (and the estimators) were computed for:
it is each of :data:`DEVICE_SCENES`, two corners of docs/physics.md#real-devices. ``cuboid_device_a_60db.yaml``:
another rubber batch (E 0.8 MPa, nu 0.44, phi0 0.062, tau 2.2, 1.7 x as resistive at rest), contact
impedance 2 x the model's with +-30 % from electrode to electrode (seeded), electrodes placed by hand up
to 0.5 mm from their nominal centres; ``cuboid_device_b_60db.yaml``: stiff (E 1.3 MPa, nu 0.47), the least
sensitive rubber (phi0 0.063, tau 1.9), half as resistive at rest, contact impedance 0.5 x the model's
+-30 %, every electrode moved by up to 0.5 mm (seeded). Each has its own truth mesh, 60 dB. As on a
robot each is calibrated once on
:data:`CAL_LOADS` known loads (``cstomo calibrate``'s :func:`~cstomo_sensor.force.reference.calibration.calibrate`,
:data:`CAL_FRAMES` frames each) against its tare, unchanged; then (model/timeline.py, the truth solved at
knots, no parallel simulation):

a. ``loaded warm-up``: the rubber warms by 2 % (uniform resistivity: 2.5 K at 0.8 %/K, contacts
   unchanged) over 5 minutes while socket loads follow each other without rest from the first frame
   (3 s each, 5..30 N, elevations 15..85 deg; :class:`~cstomo_sensor.model.timeline.Tasks` without rests),
   against the same loads without warming (``loaded, no warming``); errors per minute.
b. ``restart at rest +-2 %``: the node restarts from a tare saved on the unchanged device 2 hours
   before (a fresh stream given that old reference and its age, as :meth:`FrameStream.set_reference` at
   a start) after the rubber changed by +-2 % (uniform); unloaded; the readings over the first 0.1 s
   and 1 s, the zero from 1 s.
c. ``restart loaded +-2 %``: the same restart with the joint loaded from the first frame (loads back to
   back, 3 s each); the first second, and the errors from 5 s on; ``+0 %`` the same loads without a
   change (the aim's reference); ``expected load 2 N``: +2 % with a controller's expected load
   (``FrameStream.expect_load``: the true force plus a 2 N error per axis, per frame; ``model``, tracking on).
d. ``warm-up 30 min (rests)``: the existing 30-minute warm-up (timeline.warmup_30min: 15 K, gradient,
   contacts, drive, creep 4 %/decade compensated at 4 %, contact tasks with unannounced rests) on this
   device, against the same tasks without the drift (``warm-up baseline``).
e. ``warm-up 2 % in 5 min, rests``: issue 26's "warming with rests" (its aim: within 1.25 x of no warming):
   the warming of a (2 %, uniform resistivity, contacts unchanged, 5 minutes) under the loads of a in the
   same order (the same seed), each held :data:`HOLD_S` and followed by :data:`REST_S` unloaded (a rest
   every 4 s: 75 loads, a quarter of the frames at rest), against the same loads and rests without
   warming (``rests, no warming``); errors per minute and over all frames.

Both estimators, drift tracking off and on; creep compensation off (0) except in d, whose truth creeps
(a, d and e at :data:`LOADED_RATE`, b and c at :data:`RATE`).
Per window of frames: ``err_n`` the median of |F - F_true| (the timeline's applied force),
``zero_p99_n`` the 99th percentile of |F| over its zero-load frames, ``angle_deg`` / ``magnitude_pct``
the median errors over its loaded frames, ``wrong_pct`` the "silently wrong" share: published
(plausible) frames whose error exceeds 0.5 N at zero load or 10 % of the load, ``silent_pct`` those of
them whose error also exceeds 3 ``sigma_n`` (silently wrong as issue 34 counts it), ``implausible`` frames
refused, ``tracked_change`` the tracker's scale - 1 at the window's end; the error bars' honesty
(force/slow_states/sigma.py): ``over3sigma_pct`` the share of published frames whose error norm exceeds 3
``sigma_n`` (the aim: <= 1 %), ``sigma_n`` the median ``sigma_n`` and ``sigma_ratio`` it over the
median error (informative: within 2x).
Then robot_change.py's rows (issue 34): the loaded warm-up and both restarts with the full change of a
device over time (a gradient and the contacts besides the uniform change), on device_b and device_c.
Writes robot.csv and robot.md (the condensed tables) in ``--out``.
"""
from __future__ import annotations

import os
import tempfile
import time
from pathlib import Path

import numpy as np

from ...angles import angle_between
from ...force.reference.calibration import calibrate
from ...force.reference.files import write_reference
from ...force.slow_states.learned import write_directions
from ...frame_path.config import PipelineConfig, StreamConfig
from ...frame_path.loop import Trace, run, step
from ...frame_path.pipeline import Pipeline
from ...frame_path.sources import ArraySource
from ...frame_path.stream import FrameStream
from ...model.material import RESISTIVITY_PER_K
from ...model.simulate import Load, Scene, add_noise
from ...model.timeline import ZERO, Profile, Tasks, Timeline, TimelineSpec, warmup_30min
from ...settings import ESTIMATORS, default
from .scenes import SCENES, random_forces

#: The devices judged, at two corners of docs/physics.md#real-devices (module docstring).
DEVICE_SCENES = (SCENES / "cuboid_device_a_60db.yaml", SCENES / "cuboid_device_b_60db.yaml")
CAL_LOADS, CAL_FRAMES, CAL_SEED = 20, 5, 515
WARM = 0.02                 # the uniform resistivity change (a and b, c): 2.5 K at RESISTIVITY_PER_K
WARM_S = 300.0              # a: 5 minutes
HOLD_S = 3.0                # a, c, e: each load held 3 s (a, c: back to back)
REST_S = 1.0                # e: the rest after each load
RATE = 100.0                # b, c frames/s
LOADED_RATE = 50.0          # a, d, e frames/s (the drift bench's warm-up rate)
RESTART_S, RESTART_LOADED_S = 20.0, 60.0
RESTART_AGE_S = 7200.0      # b, c: the saved tare is 2 hours old (FrameStream.set_reference's age_s)
SEED = 31
#: N (the node's default): c with a controller's expected load (FrameStream.expect_load), its error drawn per frame
EXPECTED_SIGMA = default("expected_wrench_sigma")
ZERO_TOL_N, LOAD_TOL = 0.5, 0.10   # the "silently wrong" bounds
WITH_RESTS = ("warm-up 2 % in 5 min, rests", "rests, no warming")   # e's scenarios


def socket_tasks(seed: int, rest_s: float = 0.0) -> Tasks:
    """Socket loads from t = 0, each held :data:`HOLD_S`, then ``rest_s`` unloaded (0: back to back; 5..30 N,
    15..85 deg). The loads and their order depend on ``seed`` only, not on ``rest_s``."""
    return Tasks(start=0.0, duration_s=(HOLD_S, HOLD_S), rest_s=(rest_s, rest_s), magnitude=(5.0, 30.0),
                 elevation_deg=(15.0, 85.0), seed=seed)


def loaded_warmup(warm: bool = True, rest_s: float = 0.0) -> TimelineSpec:
    """Scenario a (``rest_s`` 0: back-to-back loads) and e (``rest_s`` :data:`REST_S`): 2 % over 5 minutes
    (or none, ``warm`` False) under the same loads."""
    temp = Profile(((0.0, 0.0), (WARM_S, WARM / RESISTIVITY_PER_K))) if warm else ZERO
    return TimelineSpec(duration=WARM_S, temperature=temp, resistivity_per_k=RESISTIVITY_PER_K, contact_per_k=0.0,
                        tasks=socket_tasks(SEED, rest_s))


def restart(change: float, loaded: bool) -> TimelineSpec:
    """Scenarios b, c: the rubber already ``change`` (uniform) off its tare at the first frame."""
    duration = RESTART_LOADED_S if loaded else RESTART_S
    return TimelineSpec(duration=duration, temperature=Profile(((0.0, change / RESISTIVITY_PER_K),)),
                        resistivity_per_k=RESISTIVITY_PER_K, contact_per_k=0.0,
                        tasks=socket_tasks(SEED + 1) if loaded else None)


def restart_changes(loaded: bool) -> tuple[float, ...]:
    """The restarts' changes: +-2 %, and for the loaded restart 0 (the same loads without a change: what
    the aim compares with)."""
    return (WARM, -WARM, 0.0) if loaded else (WARM, -WARM)


def device_truth(cache_dir=None, scene=DEVICE_SCENES[0]):
    sc = Scene.load(scene)
    return sc, sc.truth(cache_dir)


def calibrated_pipes(truth, snr_db: float, cache_dir=None, say=print, estimators=ESTIMATORS, **config) -> dict:
    """The estimators' pipelines, calibrated on the device (unchanged) as ``cstomo calibrate`` does
    (``config``: other PipelineConfig settings, e.g. the tests' coarser model). The pipelines are built
    (or read from the cache) before the device is simulated: on a fresh cache another process that needs
    the same estimators then finds them built instead of waiting for them while this one simulates."""
    pipes = {name: Pipeline.build(PipelineConfig(**{"cache_dir": str(cache_dir or ""), **config, "estimator": name}))
             for name in estimators}
    forces = random_forces(CAL_LOADS, CAL_SEED)
    ref, clean = truth.frames([Load("socket", force=tuple(f)) for f in forces])
    rng = np.random.default_rng(CAL_SEED)
    tare = add_noise(np.repeat(ref[None], 50, 0), ref, snr_db, rng)
    frames = add_noise(np.repeat(clean, CAL_FRAMES, 0), ref, snr_db, rng)
    for name, pipe in pipes.items():
        pipe.set_reference(tare.mean(axis=0), tare.std(axis=0, ddof=1), n_frames=len(tare))
        pipe.set_calibration(calibrate(pipe, frames, np.repeat(forces, CAL_FRAMES, 0)))
        say(f"robot bench: {name} calibrated on {CAL_LOADS} loads of {truth.geometry.name}")
    return pipes


def run_stream(pipe, tl: Timeline, tare: np.ndarray, tracking: bool, rate: float, creep: float, seed: int = 7,
               tare_age: float | None = None, expected_sigma: float | None = None, tare_file_age: float | None = None,
               streams: list | None = None, directions=None):
    """A fresh stream given ``tare`` (frames of the device's tare state) as its reference, then the
    timeline's frames: (times, forces read (n, 3; NaN when refused), true forces, tracked scale,
    sigma_n (NaN when refused)). ``tare_file_age``: the tare is saved as the node saves it and the stream
    starts as the node does (:meth:`FrameStream.init_reference` on a tare file of that age: a restart), with
    the device's learned ``directions`` saved beside it (force/slow_states/learned.py; None: none);
    ``streams``: a list that gets the stream."""
    rng = np.random.default_rng(seed)
    times, frames, forces, _ = tl.frames(rate, rng=rng)
    config = StreamConfig.offline(drift_tracking=tracking, creep_per_decade=creep)
    if tare_file_age is None:
        stream = FrameStream(pipe, config)
        stream.set_reference(tare.mean(axis=0), tare.std(axis=0, ddof=1), len(tare), "saved tare", age_s=tare_age)
    else:
        stream = restarted_stream(pipe, config, tare, tare_file_age, directions)
    if streams is not None:
        streams.append(stream)
    trace = Trace(lambda: stream.slow.scale)
    stamps = (1e9 * (1 + np.asarray(times))).astype(np.int64)
    source = ArraySource(frames, stamps)
    if expected_sigma is None:
        run(source, stream, [trace])
    else:  # a controller that knows the load to expected_sigma (its own error drawn per frame), told before each
        noisy = forces + rng.normal(0.0, expected_sigma, forces.shape)
        for k in range(len(times)):
            stream.expect_load(noisy[k], expected_sigma, int(stamps[k]))
            step(stream, [trace], source.recv(0.0))
    return times, np.array(trace.forces, float).reshape(-1, 3), forces, np.array(trace.probed), np.array(trace.sigma_n)


def restarted_stream(pipe, config: StreamConfig, tare: np.ndarray, age_s: float, directions=None) -> FrameStream:
    """A stream started as the node starts (ros/node.py): ``tare`` (frames) saved to a tare file as
    :class:`~cstomo_sensor.force.reference.tare_transaction.Taring` saves an accepted tare (and the device's learned
    ``directions`` beside it, force/slow_states/learned.py), the file ``age_s`` seconds old, then
    :meth:`FrameStream.init_reference` without a tare on start (``tare_on_start`` false)."""
    with tempfile.TemporaryDirectory(prefix="cstomo_robot_") as tmp:
        path = Path(tmp) / "tare.csv"
        write_reference(path, tare.mean(axis=0), tare.std(axis=0, ddof=1), comment="robot bench: saved tare",
                        frames=len(tare))
        if directions is not None:
            write_directions(path, directions)
        stamp = time.time() - age_s
        os.utime(path, (stamp, stamp))
        stream = FrameStream(pipe, config, tare_file=path)
        why = stream.init_reference(tare_on_start=False)
        if why:
            raise RuntimeError(f"robot bench: the saved tare was not used: {why}")
    return stream


def window_errors(est, forces, scale, sel, sigma=None) -> dict:
    """The module docstring's figures over the frames ``sel``."""
    est, forces = est[sel], forces[sel]
    sig = np.full(len(est), np.nan) if sigma is None else sigma[sel]
    ok = np.isfinite(est).all(axis=1)
    true = np.linalg.norm(forces, axis=1)
    loaded = true > 0
    err = np.linalg.norm(est - forces, axis=1)
    wrong = np.where(loaded, err > LOAD_TOL * true, err > ZERO_TOL_N)
    silent = wrong & (err > 3 * sig)  # wrong and the error bar does not say so (NaN sigma: not counted)
    lo = loaded & ok
    ang = np.degrees(angle_between(est[lo], forces[lo])) if lo.any() else np.array([])
    mag = 100 * np.abs(np.linalg.norm(est[lo], axis=1) / true[lo] - 1)
    rest = ~loaded & ok
    return {"frames": int(len(est)), "loaded_pct": 100 * float(loaded.mean()),
            "err_n": float(np.median(err[ok])) if ok.any() else np.nan,
            "zero_p99_n": float(np.percentile(np.linalg.norm(est[rest], axis=1), 99)) if rest.any() else np.nan,
            "angle_deg": float(np.median(ang)) if len(ang) else np.nan,
            "magnitude_pct": float(np.median(mag)) if len(mag) else np.nan,
            "wrong_pct": 100 * float(wrong[ok].mean()) if ok.any() else np.nan,
            "silent_pct": 100 * float(silent[ok].mean()) if ok.any() and np.isfinite(sig[ok]).all() else np.nan,
            "implausible": int((~ok).sum()), "tracked_change": float(scale[sel][-1] - 1),
            **sigma_figures(err[ok], sig[ok])}


def sigma_figures(err: np.ndarray, sigma: np.ndarray) -> dict:
    """The error bars' honesty over published frames of error norms ``err`` and ``sigma`` (sigma_n)."""
    if not len(err) or not np.isfinite(sigma).all():
        return {"over3sigma_pct": np.nan, "sigma_n": np.nan, "sigma_ratio": np.nan}
    med = float(np.median(sigma))
    return {"over3sigma_pct": 100 * float(np.mean(err > 3 * sigma)), "sigma_n": med,
            "sigma_ratio": med / max(float(np.median(err)), 1e-12)}


def describe(r: dict) -> str:
    """A row of :func:`window_errors` in words: a window without a published force says so (not
    'err nan N'), and the error bar is said against the error it should cover (too small, honest, or
    too cautious: over 3 x the median error)."""
    if not np.isfinite(r["err_n"]):
        return f"no force published ({r['implausible']} of {r['frames']} frames implausible)"
    text = f"median error {r['err_n']:.3f} N"
    if np.isfinite(r["angle_deg"]):
        text += f", angle {r['angle_deg']:.2f} deg, magnitude {r['magnitude_pct']:.2f} %"
    text += f", wrong {r['wrong_pct']:.1f} %" + (f", {r['implausible']} implausible" if r["implausible"] else "")
    if np.isfinite(r["sigma_n"]):
        ratio = r["sigma_ratio"]
        verdict = ("smaller than the error" if ratio < 1 else "covers the error" if ratio <= 3
                   else "over-cautious: over 3 x the error")
        text += (f"; sigma_n {r['sigma_n']:.3f} N, {ratio:.1f} x the median error ({verdict}), "
                 f"{r['over3sigma_pct']:.2f} % of errors beyond 3 sigma_n")
    return text


def prepare_device(scene, cache_dir=None, say=print) -> tuple:
    """(scene, truth, {estimator: pipeline calibrated on it}, its tare's frames): the device of ``scene``
    as every scenario takes it, unchanged and unloaded at its tare."""
    sc, truth = device_truth(cache_dir, scene)
    pipes = calibrated_pipes(truth, sc.snr_db, cache_dir, say)
    tare = Timeline(TimelineSpec(duration=1.0), snr_db=sc.snr_db, seed=SEED, cache_dir=cache_dir,
                    truth=truth).tare(20, np.random.default_rng([SEED, 22]))
    return sc, truth, pipes, tare


def device_rows(scene, cache_dir=None, say=print, device: tuple | None = None) -> list[dict]:
    """Every scenario on the device of ``scene`` (the module docstring's rows); ``device``:
    :func:`prepare_device`'s, when already prepared."""
    sc, truth, pipes, tare = device or prepare_device(scene, cache_dir, say)
    dev = truth.geometry.name

    def timeline(spec):
        t0 = time.perf_counter()
        tl = Timeline(spec, snr_db=sc.snr_db, seed=SEED, cache_dir=cache_dir, truth=truth).prepare()
        say(f"robot bench: timeline of {spec.duration:g} s, {len(tl.knots[0])} knots, {time.perf_counter() - t0:.0f} s")
        return tl

    # the tare saved on the device as it was (unchanged, unloaded): every scenario's stream starts from it
    rows = []

    def record(scenario, name, tracking, times, est, forces, scale, sigma, windows):
        for label, sel in windows(times):
            rows.append({"scenario": scenario, "device": dev, "estimator": name, "tracking": tracking, "window": label,
                         **window_errors(est, forces, scale, sel, sigma)})
        r = rows[-1]
        say(f"robot bench: {scenario}, {name}, tracking {tracking}, {r['window']}: {describe(r)}")

    def minutes(t):
        return [(f"min {m + 1}", (t >= 60 * m) & (t < 60 * (m + 1))) for m in range(int(WARM_S // 60))]

    for scenario, spec, windows in (
            ("loaded warm-up 2 % in 5 min", loaded_warmup(True), minutes),
            ("loaded, no warming", loaded_warmup(False), minutes),
            (WITH_RESTS[0], loaded_warmup(True, REST_S), lambda t: minutes(t) + [("all", t >= 0.0)]),
            (WITH_RESTS[1], loaded_warmup(False, REST_S), lambda t: minutes(t) + [("all", t >= 0.0)])):
        tl = timeline(spec)
        for name, pipe in pipes.items():
            for tracking in (False, True):
                record(scenario, name, tracking, *run_stream(pipe, tl, tare, tracking, LOADED_RATE, 0.0), windows)

    def restart_windows(loaded):
        def w(t):
            return [("first 0.1 s", t < 0.1), ("first 1 s", t < 1.0),
                    ("from 5 s", t >= 5.0) if loaded else ("from 1 s", t >= 1.0)]
        return w

    for loaded in (False, True):
        for change in restart_changes(loaded):
            tl = timeline(restart(change, loaded))
            scenario = f"restart {'loaded' if loaded else 'at rest'} {change:+.0%}"
            for name, pipe in pipes.items():
                for tracking in (False, True):
                    record(scenario, name, tracking, *run_stream(pipe, tl, tare, tracking, RATE, 0.0,
                                                                 tare_age=RESTART_AGE_S), restart_windows(loaded))
                if loaded and change == WARM and name == "model":  # a controller that knows the load to 2 N
                    record(scenario + ", expected load 2 N", name, True,
                           *run_stream(pipe, tl, tare, True, RATE, 0.0, tare_age=RESTART_AGE_S,
                                       expected_sigma=EXPECTED_SIGMA), restart_windows(loaded))

    spec = warmup_30min(seed=SEED)
    still = type(spec)(**{**spec.__dict__, "temperature": ZERO, "drive": ZERO, "gradient": ZERO})
    for scenario, sp, trackings in (("warm-up 30 min (rests)", spec, (False, True)),
                                    ("warm-up baseline (no drift)", still, (False,))):
        tl = timeline(sp)
        for name, pipe in pipes.items():
            for tracking in trackings:
                record(scenario, name, tracking, *run_stream(pipe, tl, tare, tracking, LOADED_RATE, sp.creep),
                       lambda t, end=sp.duration - 300.0: [("all", t >= 0.0), ("last 5 min", t >= end)])
    return rows


def _f(v, fmt=".2f") -> str:
    return "" if v is None or (isinstance(v, float) and not np.isfinite(v)) else format(v, fmt)


def _ratio(warm: dict, still: dict, key: str) -> str:
    """``warm`` / ``still`` (rows) of ``key`` and their ratio."""
    r = warm[key] / still[key]
    return f"{_f(warm[key])} / {_f(still[key])}" + (f" ({r:.2f} x)" if np.isfinite(r) else "")


def markdown(rows: list[dict]) -> str:
    """The condensed tables of docs/benchmark.md (issue 26's "before")."""
    devices = list(dict.fromkeys(r["device"] for r in rows))

    def find(scenario, est, tracking, window):
        for r in rows:
            if (r["device"], r["scenario"], r["estimator"], r["tracking"], r["window"]) == (dev, scenario, est, tracking,
                                                                                          window):
                return r
        return None

    def off_on(scenario, est, window, key, fmt=".2f"):
        a, b = find(scenario, est, False, window), find(scenario, est, True, window)
        return f"{_f(a and a[key], fmt)} -> {_f(b and b[key], fmt)}"

    def short(d):
        return d.replace("cuboid_joint_", "")

    lines = ["Loaded warm-up (a) and warm-up with rests (e): median angle deg / magnitude % per minute, tracking "
             "off -> on; silently wrong % per minute",
             "", "| device | scenario | estimator | tracking | angle deg, min 1..5 | magnitude %, min 1..5 | wrong %, min 1..5 "
             "| > 3 sigma %, min 1..5 | sigma_n / error, min 1..5 |",
             "|---|---|---|---|---|---|---|---|---|"]
    for dev, scenario in ((d, s) for d in devices for s in ("loaded warm-up 2 % in 5 min", "loaded, no warming")
                          + WITH_RESTS):
        for est in ESTIMATORS:
            for tracking in (False, True):
                rs = [find(scenario, est, tracking, f"min {m + 1}") for m in range(int(WARM_S // 60))]
                lines.append(f"| {short(dev)} | {scenario} | {est} | {'on' if tracking else 'off'} | "
                             + " | ".join(" / ".join(_f(r[k], ".2f" if k != "wrong_pct" else ".0f") for r in rs)
                                          for k in ("angle_deg", "magnitude_pct", "wrong_pct")) + " | "
                             + " / ".join(_f(r["over3sigma_pct"], ".1f") for r in rs) + " | "
                             + " / ".join(_f(r["sigma_ratio"], ".2f") for r in rs) + " |")
    last = f"min {int(WARM_S // 60)}"
    lines += ["", "Warm-up with rests (e): warmed / unwarmed (the same loads and rests without warming, the same "
              "tracking) and their ratio, the last minute and all frames", "",
              "| device | estimator | tracking | angle deg, last min | angle deg, all | magnitude %, last min "
              "| magnitude %, all | zero p99 N, all | > 3 sigma %, all | sigma_n / error, all |",
              "|---|---|---|---|---|---|---|---|---|---|"]
    for dev in devices:
        for est in ESTIMATORS:
            for tracking in (False, True):
                w, u = ({wd: find(sc, est, tracking, wd) for wd in (last, "all")} for sc in WITH_RESTS)
                if not all([*w.values(), *u.values()]):
                    continue
                lines.append(f"| {short(dev)} | {est} | {'on' if tracking else 'off'} | "
                             f"{_ratio(w[last], u[last], 'angle_deg')} | {_ratio(w['all'], u['all'], 'angle_deg')} | "
                             f"{_ratio(w[last], u[last], 'magnitude_pct')} | "
                             f"{_ratio(w['all'], u['all'], 'magnitude_pct')} | {_f(w['all']['zero_p99_n'])} / "
                             f"{_f(u['all']['zero_p99_n'])} | {_f(w['all']['over3sigma_pct'], '.1f')} / "
                             f"{_f(u['all']['over3sigma_pct'], '.1f')} | {_f(w['all']['sigma_ratio'])} / "
                             f"{_f(u['all']['sigma_ratio'])} |")
    lines += ["", "Restarts (b, c): tracking off -> on; first 0.1 s / 1 s: median |F - F_true| N; then the "
              "window from 1 s (at rest) or 5 s (loaded)", "",
              "| device | scenario | estimator | first 0.1 s N | first 1 s N | zero p99 N | angle deg | magnitude % | wrong % "
              "| implausible | > 3 sigma % | sigma_n / error |", "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for dev, loaded, scenario in ((d, ld, f"restart {'loaded' if ld else 'at rest'} {c:+.0%}{x}") for d in devices
                                  for ld in (False, True) for c in restart_changes(ld)
                                  for x in (("", ", expected load 2 N") if ld and c == WARM else ("",))):
        w = "from 5 s" if loaded else "from 1 s"
        for est in ESTIMATORS:
            lines.append(f"| {short(dev)} | {scenario} | {est} | {off_on(scenario, est, 'first 0.1 s', 'err_n')} | "
                         f"{off_on(scenario, est, 'first 1 s', 'err_n')} | {off_on(scenario, est, w, 'zero_p99_n')} | "
                         f"{off_on(scenario, est, w, 'angle_deg')} | {off_on(scenario, est, w, 'magnitude_pct')} | "
                         f"{off_on(scenario, est, w, 'wrong_pct', '.1f')} | {off_on(scenario, est, w, 'implausible', 'd')} | "
                         f"{off_on(scenario, est, w, 'over3sigma_pct', '.1f')} | {off_on(scenario, est, w, 'sigma_ratio')} |")
    lines += ["", "Warm-up 30 min with rests (d), all frames (last 5 min in robot.csv): tracking off -> on", "",
              "| device | scenario | estimator | zero p99 N | angle deg | magnitude % | wrong % | implausible | > 3 sigma % "
              "| sigma_n / error |", "|---|---|---|---|---|---|---|---|---|---|"]
    for dev, scenario in ((d, s) for d in devices for s in ("warm-up 30 min (rests)", "warm-up baseline (no drift)")):
        for est in ESTIMATORS:
            lines.append(f"| {short(dev)} | {scenario} | {est} | {off_on(scenario, est, 'all', 'zero_p99_n')} | "
                         f"{off_on(scenario, est, 'all', 'angle_deg')} | {off_on(scenario, est, 'all', 'magnitude_pct')} | "
                         f"{off_on(scenario, est, 'all', 'wrong_pct', '.1f')} | {off_on(scenario, est, 'all', 'implausible', 'd')} | "
                         f"{off_on(scenario, est, 'all', 'over3sigma_pct', '.1f')} | {off_on(scenario, est, 'all', 'sigma_ratio')} |")
    return "\n".join(lines) + "\n"
