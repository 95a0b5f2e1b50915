"""``cstomo bench --drift --robot`` (cstomo_sensor/tools/bench/robot.py) simulates what it says: a device
outside the model, loads back to back, a restart after a 2 % change from a tare of the unchanged
device, and its "silently wrong" share counts what it says. Expected values come from the issue
(issue 26 item 1) and docs/physics.md#real-devices, not from the code under test."""
import functools

import numpy as np
import pytest

from cstomo_sensor.model.geometry import load_sensor
from cstomo_sensor.model.simulate import Truth
from cstomo_sensor.model.timeline import Timeline, TimelineSpec
from cstomo_sensor.tools.bench import robot

NOMINAL = load_sensor("cuboid_joint")



def rho_at_rest(m):
    return m.rho_h * ((1 - m.phi_c) / (m.phi0 - m.phi_c)) ** m.tau  # docs/physics.md, the percolation law


# (scene, contact impedance x the model's before the +-30 % spread, electrodes' offsets (min, max) m)
DEVICES = [(robot.DEVICE_SCENES[0], 2.0, (0.25e-3, 0.52e-3)), (robot.DEVICE_SCENES[1], 0.5, (0.0, 0.5e-3))]


def test_the_bench_judges_two_devices_and_neither_is_the_model():
    assert len(robot.DEVICE_SCENES) == 2
    names = {robot.device_truth(scene=s)[1].geometry.name for s in robot.DEVICE_SCENES}
    assert len(names) == 2 and NOMINAL.name not in names


@pytest.mark.parametrize("scene, z_scale, offsets", DEVICES)
def test_the_judged_device_is_outside_the_model_within_the_stated_corners(scene, z_scale, offsets):
    sc, truth = robot.device_truth(scene=scene)
    dev = truth.device
    # contact impedance: z_scale x the model's (within 0.5..2.5 x), +-30 % from electrode to electrode
    z = np.asarray(truth.z) / NOMINAL.contact_impedance
    assert z.shape == (16,)
    assert np.all(z >= z_scale * 0.7 - 1e-9) and np.all(z <= z_scale * 1.3 + 1e-9)
    assert np.all(np.abs(z - 1) > 0.25)  # none is the model's
    assert z.max() / z.min() > 1.3  # they differ from electrode to electrode
    # electrodes placed by hand: up to about 0.5 mm from the nominal centres (device_a's file moves
    # each coordinate by up to 0.5 mm: two electrodes are 0.51 mm off), most of them well off
    moved = np.array([np.linalg.norm(np.subtract(e.center, n.center))
                      for e, n in zip(dev.electrodes, NOMINAL.electrodes)])
    assert offsets[0] <= moved.min() and moved.max() <= offsets[1]
    assert moved.max() >= 0.45e-3 and np.median(moved) >= 0.25e-3
    # another rubber batch, within docs/physics.md#real-devices but not the nominal
    m, m0 = truth.geometry.material, NOMINAL.material
    assert 0.7e6 <= m.E <= 1.3e6 and 0.43 <= m.nu <= 0.47 and 0.056 <= m.phi0 <= 0.064 and 1.8 <= m.tau <= 2.4
    assert 9 <= m.tau * m.phi0 / (m.phi0 - m.phi_c) <= 19  # d ln(rho) / d theta, in magnitude
    assert 0.2 <= rho_at_rest(m) / rho_at_rest(m0) <= 5
    assert abs(rho_at_rest(m) / rho_at_rest(m0) - 1) > 0.3
    assert (m.E, m.nu, m.phi0, m.tau) != (m0.E, m0.nu, m0.phi0, m0.tau)
    assert sc.snr_db == 60


def test_the_two_devices_sit_at_opposite_corners():
    (_, a), (_, b) = (robot.device_truth(scene=s) for s in robot.DEVICE_SCENES)
    ma, mb = a.geometry.material, b.geometry.material
    assert ma.E < 1.0e6 < mb.E and ma.nu < 0.45 < mb.nu
    assert rho_at_rest(ma) > rho_at_rest(NOMINAL.material) > rho_at_rest(mb)
    assert np.min(a.z) > NOMINAL.contact_impedance > np.max(b.z)


def test_the_loaded_warm_up_has_no_unloaded_frame_and_warms_2_pct_in_5_minutes():
    spec, still = robot.loaded_warmup(True), robot.loaded_warmup(False)
    t = np.arange(0, 300.0, 1 / 50)
    f = spec.force(t)
    mag = np.linalg.norm(f, axis=1)
    assert mag.min() >= 5.0 - 1e-9 and mag.max() <= 30.0 + 1e-9  # no unloaded frame, loads of 5..30 N
    steps, forces = spec.steps()
    assert steps[0] == 0.0 and np.allclose(np.diff(steps), 3.0)  # back to back, 3 s each, from the first frame
    assert len(steps) == 100
    assert spec.resistivity_per_k * spec.temperature(300.0) == pytest.approx(0.02)
    assert spec.resistivity_per_k * spec.temperature(150.0) == pytest.approx(0.01)
    assert spec.contact_per_k == 0.0 and spec.gradient.is_zero and spec.drive.is_zero  # a uniform change
    assert np.array_equal(still.force(t), f) and still.temperature.is_zero  # the same loads without warming


def test_the_warm_up_with_rests_has_the_loaded_warm_ups_loads_each_followed_by_a_1_s_rest():
    # issue 26's "warming with rests": 2 % over 5 minutes, 3 s loads, a rest after each
    spec, still, loaded = robot.loaded_warmup(True, 1.0), robot.loaded_warmup(False, 1.0), robot.loaded_warmup(True)
    steps, forces = spec.steps()
    on, off = steps[0::2], steps[1::2]
    assert on[0] == 0.0 and np.allclose(off - on, 3.0) and np.allclose(on[1:] - off[:-1], 1.0)
    assert len(on) == 75 and np.all(forces[1::2] == 0)
    assert np.array_equal(forces[0::2], loaded.steps()[1][:75])  # the loaded warm-up's loads, in its order
    t = np.arange(0, 300.0, 1 / 50)
    assert np.mean(np.linalg.norm(spec.force(t), axis=1) == 0) == pytest.approx(0.25, abs=0.01)
    assert spec.resistivity_per_k * spec.temperature(300.0) == pytest.approx(0.02)
    assert spec.contact_per_k == 0.0 and spec.gradient.is_zero and spec.drive.is_zero  # a uniform change
    assert np.array_equal(still.force(t), spec.force(t)) and still.temperature.is_zero


def test_the_loaded_restart_is_loaded_from_its_first_frame():
    spec = robot.restart(0.02, loaded=True)
    assert np.linalg.norm(spec.force([0.0])[0]) >= 5.0
    assert np.linalg.norm(spec.force(np.arange(0, spec.duration, 0.01)), axis=1).min() > 0
    assert np.linalg.norm(robot.restart(0.02, loaded=False).force(np.arange(0, 20, 0.01)), axis=1).max() == 0


@pytest.mark.slow
@pytest.mark.parametrize("scene", robot.DEVICE_SCENES)
@pytest.mark.parametrize("change", [0.02, -0.02])
def test_a_restart_finds_the_device_2_pct_off_its_tare_at_the_first_frame(change, scene):
    # the bench's device on a coarse truth mesh (4 mm): the test judges the timeline, not a mesh
    sc, fine = robot.device_truth(scene=scene)
    truth = Truth(fine.geometry, truth_h=4.0e-3, z_rel=sc.z_rel, jitter=sc.jitter, seed=sc.seed)
    tare = Timeline(TimelineSpec(duration=1.0), truth=truth, snr_db=None).reference
    tl = Timeline(robot.restart(change, loaded=False), truth=truth, snr_db=None)
    v0 = tl.voltages([0.0])[0]
    ratio = v0 / tare
    big = np.abs(tare) > 0.2 * np.abs(tare).max()  # channels the rubber's voltage dominates
    # a uniform resistivity change of the rubber, contacts unchanged: every voltage nearly x (1 + change)
    assert np.median(ratio[big]) == pytest.approx(1 + change, abs=0.003)
    assert np.all(np.abs(ratio[big] - (1 + change)) < 0.01)
    assert np.allclose(tl.voltages([10.0])[0], v0)  # and it stays so
    # the same truth unchanged gives the tare back (the change is the scenario's, nothing else)
    assert np.allclose(Timeline(TimelineSpec(duration=1.0), truth=truth, snr_db=None).voltages([0.0])[0], tare)


def test_the_silently_wrong_share_counts_errors_beyond_half_a_newton_at_rest_or_10_pct_of_the_load():
    forces = np.array([[0, 0, 0], [0, 0, 0], [0, 0, -10.0], [0, 0, -10.0], [0, 0, -20.0], [0, 0, 0]])
    est = np.array([[0.4, 0, 0], [0, 0.6, 0], [0, 0, -10.9], [0, 0, -8.8], [0, 0, -20.0], [np.nan] * 3])
    r = robot.window_errors(est, forces, np.ones(len(forces)), np.ones(len(forces), bool))
    assert r["wrong_pct"] == pytest.approx(100 * 2 / 5)  # 0.6 N at rest and 1.2 N of 10 N; the refused frame not published
    assert r["implausible"] == 1
    assert r["zero_p99_n"] == pytest.approx(np.percentile([0.4, 0.6], 99))


# --- issue 26 items 2-4: following the device under load and across restarts (force/estimators/scale_fit.py JointScale) ---
# The bench's device_b (the least sensitive corner) on its own coarse truth mesh (4 mm: the test judges
# the tracking, not a mesh), calibrated on 20 loads with the tests' coarse model and the default
# estimator (model). Aims from issue 26; the bounds pinned below are what was measured, with a margin
# (the report of the commit that added them gives the figures).


@pytest.fixture(scope="module")
def device_b(tmp_path_factory):
    from conftest import PIPE

    sc, fine = robot.device_truth(scene=robot.DEVICE_SCENES[1])
    truth = Truth(fine.geometry, truth_h=4.0e-3, z_rel=sc.z_rel, jitter=sc.jitter, seed=sc.seed)
    pipe = robot.calibrated_pipes(truth, sc.snr_db, say=lambda m: None, estimators=("model",),
                                  **{**PIPE, "grid": tuple(PIPE["grid"])})["model"]
    tare = Timeline(TimelineSpec(duration=1.0), snr_db=sc.snr_db, seed=robot.SEED, truth=truth).tare(
        20, np.random.default_rng([robot.SEED, 22]))
    return sc, truth, pipe, tare


def _win(out, sel):
    """``robot.window_errors`` of a ``run_stream`` result over the frames ``sel``."""
    times, est, forces, scale, sigma = out
    return robot.window_errors(est, forces, scale, sel, sigma)


def _run(device, spec, tracking, rate, **kw):
    sc, truth, pipe, tare = device
    tl = Timeline(spec, snr_db=sc.snr_db, seed=robot.SEED, truth=truth).prepare()
    return robot.run_stream(pipe, tl, tare, tracking, rate, 0.0, **kw)


@pytest.mark.slow
def test_a_loaded_warm_up_is_followed_without_a_rest(device_b):
    """Issue 26's aim for a uniform 2 % warm-up under loads back to back, no rest (last minute within 1.5 x angle
    / 1.6 x magnitude of the same loads unwarmed, every frame honest). A strict xfail on main while the other
    states' slope against the scale was a random walk (1.66 deg / 2.09 %, 1.61 x / 1.82 x); with the slopes as
    states of the tracker 1.06 / 1.50 against 1.03 / 1.15 (1.03 x / 1.30 x), 0 % beyond 3 sigma."""
    warm = _run(device_b, robot.loaded_warmup(True), True, robot.LOADED_RATE)
    still = _run(device_b, robot.loaded_warmup(False), False, robot.LOADED_RATE)
    last = warm[0] >= 240.0
    w, s = _win(warm, last), _win(still, last)
    print(f"loaded warm-up, last minute: {w['angle_deg']:.2f} deg / {w['magnitude_pct']:.2f} % against "
          f"{s['angle_deg']:.2f} / {s['magnitude_pct']:.2f} without warming; > 3 sigma {w['over3sigma_pct']:.2f} %, "
          f"sigma/error {w['sigma_ratio']:.2f}, tracked {w['tracked_change']:+.4f}")
    assert w["tracked_change"] == pytest.approx(0.02, abs=0.002)  # it followed the 2 % under load
    assert w["angle_deg"] <= 1.5 * s["angle_deg"] and w["magnitude_pct"] <= 1.6 * s["magnitude_pct"]  # issue 26's aims
    assert w["over3sigma_pct"] <= 1.0
    assert _win(warm, warm[0] >= 0)["over3sigma_pct"] <= 1.0  # every minute, not only the last


@pytest.mark.slow
def test_a_warm_up_with_rests_reads_as_without_warming(device_b):
    """Issue 26's "warming with rests: within 1.25x of no warming": tracked, against the same loads and
    rests without warming, untracked (the robot bench's fine-mesh device_b: 1.00 x angle, 0.95 x magnitude
    over all frames)."""
    warm = _run(device_b, robot.loaded_warmup(True, robot.REST_S), True, robot.LOADED_RATE)
    cold = _run(device_b, robot.loaded_warmup(True, robot.REST_S), False, robot.LOADED_RATE)
    still = _run(device_b, robot.loaded_warmup(False, robot.REST_S), False, robot.LOADED_RATE)
    for label, sel in (("last minute", warm[0] >= 240.0), ("all frames", warm[0] >= 0.0)):
        w, c, s = _win(warm, sel), _win(cold, sel), _win(still, sel)
        print(f"warm-up with rests, {label}: {w['angle_deg']:.2f} deg / {w['magnitude_pct']:.2f} % against "
              f"{s['angle_deg']:.2f} / {s['magnitude_pct']:.2f} without warming (untracked {c['angle_deg']:.2f} / "
              f"{c['magnitude_pct']:.2f}); > 3 sigma {w['over3sigma_pct']:.2f} %, tracked {w['tracked_change']:+.4f}")
        assert c["angle_deg"] > 5 * s["angle_deg"]  # the warming matters: untracked it is far off
        assert w["angle_deg"] <= 1.25 * s["angle_deg"] and w["magnitude_pct"] <= 1.25 * s["magnitude_pct"]
        assert w["over3sigma_pct"] <= 1.0
    assert w["tracked_change"] == pytest.approx(0.02, abs=0.002)  # it followed the 2 %


@pytest.mark.slow
def test_a_tracked_loaded_stream_says_how_sure_it_is_within_2x(device_b):
    """Issue 26, informative: back-to-back loads without a rest for two minutes, tracked: the median sigma_n
    within 2x the median error, every frame honest (on main, whose model sigma took the noise and the
    tracker's states through the estimator's linear part, 2x as sensitive as its fit: the robot bench's
    device_b 2.5-3.2x; this coarse one 2.65x; now 1.72x)."""
    spec = robot.loaded_warmup(False)
    out = _run(device_b, type(spec)(**{**spec.__dict__, "duration": 120.0}), True, robot.LOADED_RATE)
    w = _win(out, out[0] >= 0)
    print(f"loaded, no warming, tracked: > 3 sigma {w['over3sigma_pct']:.2f} %, sigma/error {w['sigma_ratio']:.2f}")
    assert w["over3sigma_pct"] <= 1.0
    assert w["sigma_ratio"] <= 2.0


@pytest.fixture(scope="module")
def unchanged(device_b):
    """The restart of the unchanged device, untracked, at rest (False) or loaded (True): the baseline of
    both changes (+-2 %), run once per module (a run reads its frames and returns new arrays)."""
    return functools.cache(lambda loaded: _run(device_b, robot.restart(0.0, loaded), False, robot.RATE))


def _restart(device, unchanged, change: float, loaded: bool, after: float):
    """A restart from a 2 h old tare after a ``change`` of the device, tracked, and the same frames of an
    unchanged device untracked: (the run, its window from ``after`` s, the baseline's window)."""
    still = unchanged(loaded)
    out = _run(device, robot.restart(change, loaded), True, robot.RATE, tare_age=robot.RESTART_AGE_S)
    late = out[0] >= after
    return out, _win(out, late), _win(still, late)


@pytest.mark.slow
@pytest.mark.parametrize("change", [0.02, -0.02])
def test_a_restart_at_rest_from_an_old_tare_finds_its_zero_within_a_second(device_b, unchanged, change):
    out, r, base = _restart(device_b, unchanged, change, False, 1.0)
    print(f"restart at rest {change:+.0%}: zero p99 from 1 s {r['zero_p99_n']:.3f} N (no change, untracked "
          f"{base['zero_p99_n']:.3f}); > 3 sigma {r['over3sigma_pct']:.2f} %, tracked {r['tracked_change']:+.4f}")
    # the aim is 0.5 N; this device's own noise at rest gives a p99 near it without any change (the
    # fine-mesh bench: 0.74 N with the change, 0.78 N without it): pinned against its baseline
    assert r["zero_p99_n"] <= max(0.5, 1.15 * base["zero_p99_n"])
    assert _win(out, out[0] >= 0)["over3sigma_pct"] <= 1.0


@pytest.mark.slow
@pytest.mark.parametrize("change", [0.02, -0.02])
def test_a_restart_under_load_from_an_old_tare_reads_within_the_aims_from_5_s(device_b, unchanged, change):
    out, r, base = _restart(device_b, unchanged, change, True, 5.0)
    print(f"restart loaded {change:+.0%}: {r['angle_deg']:.2f} deg / {r['magnitude_pct']:.2f} % against "
          f"{base['angle_deg']:.2f} / {base['magnitude_pct']:.2f} unchanged; > 3 sigma {r['over3sigma_pct']:.2f} %, "
          f"sigma/error {r['sigma_ratio']:.2f}, tracked {r['tracked_change']:+.4f}")
    assert r["angle_deg"] <= 1.5 * base["angle_deg"] and r["magnitude_pct"] <= 1.6 * base["magnitude_pct"]
    assert _win(out, out[0] >= 0)["over3sigma_pct"] <= 1.0  # from the first frame on
    assert r["sigma_ratio"] <= 2.5  # informative (2.3-3 through the model's linear part; its own map: 1.7-1.9)


# --- issue 26: "the warm-up at 1.5 %/K keeps its zero (the tracking never locks: when it loses the device,
# it says so and re-acquires)". scenes/warmup_30min.yaml's timeline (15 K over 30 min, a 30 % gradient,
# contacts -1 %/K, drive +0.3 %, creep 4 %/decade, its own 1-30 s tasks with unannounced rests) at the
# top of section 9's range, 1.5 %/K, its first 2 minutes, on device_b (outside the model). Measured on
# bba0747 (the commit before this test): the scale is followed (+4.0 % against +4.3 % true at 120 s), but the
# contacts' and the gradient's states go stale during a 20 s task and the rest test, taking them as
# known, refuses every later rest: drift_rest_frames stops at 1201 (57 s), the zero at rest reads 3.6 N
# at 57 s and 11.5 N at 110 s (37 N at 6 minutes) with sigma_n 1.3-1.8 N, status OK; this test: rest frames
# 1201 by 60 s and at the end, the zero from 60 s 6.2 N (sigma_n 1.4). Now the other states follow the scale
# under load by their slope fitted at rest (force/slow_states/drift.py FOLLOW_MEMORY): rest frames keep counting, the zero
# from 60 s reads about 0.4 N.

WARM_FAST = 0.015   # resistivity per K: section 9's top
WARM_FAST_S = 120.0


@pytest.mark.slow  # an honest simulation over time and the model estimator (~60 s on a fresh clone)
def test_a_warm_up_at_1_5_pct_per_k_keeps_its_zero_and_never_locks(device_b):
    from pathlib import Path

    from cstomo_sensor.frame_path.stream import FrameStream, StreamConfig
    from cstomo_sensor.model.simulate import Scene

    sc, truth, pipe, tare = device_b
    scene = Path(__file__).resolve().parents[1] / "scenes" / "warmup_30min.yaml"
    spec = TimelineSpec.from_dict(Scene.load(scene).timeline, scene.parent)
    spec = type(spec)(**{**spec.__dict__, "resistivity_per_k": WARM_FAST, "duration": WARM_FAST_S})
    tl = Timeline(spec, snr_db=sc.snr_db, seed=robot.SEED, truth=truth).prepare()
    times, frames, forces, state = tl.frames(robot.LOADED_RATE, rng=np.random.default_rng(7))
    stream = FrameStream(pipe, StreamConfig.offline(creep_per_decade=spec.creep))
    stream.set_reference(tare.mean(axis=0), tare.std(axis=0, ddof=1), len(tare), "tare")
    est, sigma, rest_frames = np.full((len(times), 3), np.nan), np.full(len(times), np.nan), np.zeros(len(times))
    for k, (t, v) in enumerate(zip(times, frames)):
        out = stream.push(v, stamp_ns=int(1e9 * (1 + t)))
        if out is not None and out.result.valid:
            est[k], sigma[k] = out.result.force, out.result.sigma_n
        rest_frames[k] = stream.slow.drift.rest_frames
    true_change = (1 + state.rho_change[-1]) * state.drive[-1] - 1
    assert true_change > 0.04  # the device changed by more than 4 % in 2 minutes
    err = np.linalg.norm(est - forces, axis=1)
    at_rest = (np.linalg.norm(forces, axis=1) == 0) & np.isfinite(err)
    late = at_rest & (times >= 60.0)
    print(f"1.5 %/K: rest frames {rest_frames[times < 60].max():.0f} by 60 s, {rest_frames[-1]:.0f} at the end; zero "
          f"at rest from 60 s median {np.median(err[late]):.2f} N (sigma_n {np.median(sigma[late]):.2f}); tracked "
          f"{stream.slow.drift.change:+.4f} against {true_change:+.4f}")
    # never locks: the rests after the first minute count as rest (the scene rests about half the time)
    assert rest_frames[-1] - rest_frames[times < 60].max() > 0.5 * late.sum()
    # keeps its zero: this device's own noise at rest gives a median near 0.4 N (0.41 N at 57 s above)
    assert np.median(err[late]) <= 0.8
    # and says so when it does not: no more than 1 % of the published frames beyond 3 sigma_n
    ok = np.isfinite(err)
    assert np.mean(err[ok] > 3 * sigma[ok]) <= 0.01
