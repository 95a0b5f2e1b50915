"""A device over time (cstomo_sensor/model/timeline.py, docs/physics.md#device-changes): temperature,
drive and contact drift, creep, contact tasks; the knots' interpolation against direct solves; the
scene files, ``cstomo simulate`` and the simulated board playing a timeline scene.

The truth mesh is coarse here (4 mm, as the model's) to keep the tests fast: these tests judge the
timeline, not an estimator."""
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from cstomo_sensor.errors import ConfigError
from cstomo_sensor.model.simulate import Load, Scene, Truth
from cstomo_sensor.model.timeline import (
    Profile,
    Tasks,
    Timeline,
    TimelineSpec,
    drive_change,
    held_load_creep,
    uniform_resistivity,
    warmup_30min,
)

SCENES = Path(__file__).resolve().parent.parent / "scenes"
TRUTH_H = 4.0e-3


@pytest.fixture(scope="module")
def truth(cuboid):
    return Truth(cuboid, truth_h=TRUTH_H, seed=3)


def rms(v):
    return float(np.sqrt(np.mean(np.square(v))))


def test_a_uniform_1pct_resistivity_change_is_a_direct_solve_with_sigma_over_1_01(truth):
    tl = Timeline(uniform_resistivity(1.0, duration=3.0, ramp_s=1.0), truth=truth, snr_db=None)
    times, frames, forces, state = tl.frames(10)
    fm = truth.forward
    v0 = fm.voltages()  # the tare: the device as it was, unloaded (to rounding: BLAS kernels differ)
    np.testing.assert_allclose(tl.reference, v0, rtol=0, atol=1e-12 * np.abs(v0).max())
    err = tl.interpolation_error(5)
    assert err["max"] < 1e-5, err  # a ramp of resistivity: the chord of a nearly linear map
    held = times >= 1.0
    direct = fm.voltages(fm.sigma0 / 1.01)
    assert np.abs(frames[held] - direct).max() / rms(direct) <= err["max"] + 1e-12
    mid = fm.voltages(fm.sigma0 / 1.005)  # half way up the ramp: between knots
    assert np.abs(tl.voltages([0.5])[0] - mid).max() / rms(mid) <= err["max"] + 1e-12
    assert np.allclose(state.rho_change[held], 0.01) and np.allclose(state.contact, 1.0)
    assert not forces.any() and not state.force_eff.any()


def test_a_drive_change_scales_every_voltage_exactly(truth):
    tl = Timeline(drive_change(0.005, duration=2.0, ramp_s=1.0), truth=truth, snr_db=None)
    times, frames, _, state = tl.frames(20)
    d = 0.005 * np.minimum(times, 1.0)
    np.testing.assert_allclose(frames / tl.reference, np.broadcast_to(1 + d[:, None], frames.shape), rtol=0,  # to rounding
                               atol=1e-10)  # a step of the drive is 2.5e-4
    np.testing.assert_allclose(state.drive, 1 + d, rtol=0, atol=1e-15)


@pytest.mark.slow
def test_creep_of_a_held_20N_load_follows_the_log_law_and_recovers(truth):
    c = 0.04
    tl = Timeline(held_load_creep(20.0, on=1.0, off=31.0, duration=60.0, creep=c), truth=truth, snr_db=None)
    t = np.array([0.5, 1.0, 1.05, 1.1, 2.0, 11.0, 30.9, 31.0, 31.05, 32.0, 41.0, 60.0])
    f = tl.state(t).force_eff
    on = np.log10(np.maximum(t - 1.0, 0.1) / 0.1)
    off = np.log10(np.maximum(t - 31.0, 0.1) / 0.1)
    want = np.where(t < 1, 0.0, np.where(t < 31, 20 * (1 + c * on), 20 * c * (on - off)))
    np.testing.assert_allclose(-f[:, 2], want, rtol=1e-12, atol=1e-12)
    assert np.allclose(f[:, :2], 0, atol=1e-12)
    assert -f[-1, 2] < -f[-4, 2] < 20 * c * 3  # recovering: the residual falls after the release
    # positive homogeneity: at a knot the device is the truth under the force scaled by the creep
    kt, kn, _ = tl.knots
    for tk in (kt[(kn == 1) & (kt > 5)][0], kt[(kn == 2) & (kt > 35)][0]):
        fe = tl.state([tk]).force_eff[0]
        v = truth.voltages(Load("socket", force=tuple(fe)))
        assert np.abs(tl.voltages([tk])[0] - v).max() / rms(v) < 1e-8, tk
    # the load's change grows along the log law while it is held
    dv = [rms(tl.voltages([x])[0] - tl.reference) for x in (1.1, 2.0, 11.0, 30.0)]
    assert dv[0] < dv[1] < dv[2] < dv[3]
    err = tl.interpolation_error(8)
    assert err["max"] < 0.2 * 10 ** (-60 / 20), err  # a fifth of the noise of a 60 dB board


@pytest.mark.slow  # seconds of computation (the held load's mechanics: the creep test's, above, when it ran)
def test_equal_states_among_the_knots_are_solved_once_and_read_as_solved(truth, tmp_path):
    """A load held three times with rests between and nothing else changing: each segment's knots are one
    state, every rest the unloaded one, so its 15 knots need 2 solves; each knot still reads the device
    loaded or not (Truth.voltages: another path); warming the same loads makes every knot a state of its own."""
    f = (0.0, 0.0, -20.0)
    loads = dict(load_times=(0.0, 1.0, 2.0, 3.0, 4.0), load_forces=(f, (0.0, 0.0, 0.0)) * 2 + (f,))
    still = Timeline(TimelineSpec(duration=5.0, **loads), truth=truth, snr_db=None, cache_dir=tmp_path)
    kt, kn, v = still.knots
    assert len(kt) == 15 and still.states_solved == 2
    loaded, rest = truth.voltages(Load("socket", force=f)), truth.reference
    for i, n in enumerate(kn):
        w = loaded if n % 2 else rest  # segments 1, 3, 5 loaded
        assert np.abs(v[i] - w).max() / rms(w) < 1e-9, (i, n)
    warm = Timeline(TimelineSpec(duration=5.0, temperature=Profile(((0.0, 0.0), (5.0, 1.0))), **loads), truth=truth,
                    snr_db=None, cache_dir=tmp_path)
    assert len(warm.knots[0]) == 15 and warm.states_solved == 15


@pytest.mark.slow  # seconds of computation
def test_the_timeline_is_deterministic_for_a_seed():
    a, b, other = Tasks(seed=3).steps(600), Tasks(seed=3).steps(600), Tasks(seed=4).steps(600)
    assert all(np.array_equal(x, y) for x, y in zip(a, b))
    assert not np.array_equal(a[0], other[0])
    t, f = a
    loaded = np.linalg.norm(f, axis=1) > 0
    assert loaded[::2].all() and not loaded[1::2].any()  # tasks, each followed by a rest
    hold, rest = np.diff(t)[::2], np.diff(t)[1::2]
    assert (hold >= 1).all() and (hold <= 30).all() and (rest >= 1).all() and (rest <= 30).all()
    mag = np.linalg.norm(f[loaded], axis=1)
    el = np.degrees(np.arctan2(-f[loaded, 2], np.hypot(f[loaded, 0], f[loaded, 1])))
    assert (mag >= 5).all() and (mag <= 30).all() and (el >= 15 - 1e-9).all() and (el <= 90 + 1e-9).all()
    spec = TimelineSpec.from_dict(Scene.load(SCENES / "timeline_drift_short.yaml").timeline)
    runs = [Timeline.from_scene(SCENES / "timeline_drift_short.yaml").frames(5) for _ in range(2)]
    assert np.array_equal(runs[0][1], runs[1][1])
    assert np.array_equal(runs[0][3].contact, runs[1][3].contact) and np.ptp(runs[0][3].contact[-1]) > 0
    redrawn = Timeline.from_scene(SCENES / "timeline_drift_short.yaml")
    redrawn.seed += 1  # other noise, same device
    assert not np.array_equal(redrawn.frames(5)[1], runs[0][1])
    assert spec.contact_drift is not None and spec.contact_drift.seed == 1


def test_the_warmup_scene_file_is_the_builders_scenario():
    spec = TimelineSpec.from_dict(Scene.load(SCENES / "warmup_30min.yaml").timeline)
    assert spec == replace(warmup_30min(), rate_hz=10.0)
    assert spec.temperature([0.0, 1800.0]).tolist() == [0.0, 15.0] and len(spec.steps()[0]) > 50


@pytest.mark.parametrize("text,match", [
    ("timeline: {duration: 5, wind: 3}\n", "timeline.wind"),
    ("timeline: {duration: 5, tasks: {seed: 1, pause: 3}}\n", "timeline.tasks.pause"),
    ("timeline: {duration: 5, temperature: [[0, 0], [0, 1]]}\n", "timeline.temperature"),
    ("timeline: {duration: 5}\nloads:\n  - {socket: {force: [0, 0, -10]}}\n", "not both"),
])
def test_a_bad_timeline_is_refused_naming_the_key(tmp_path, text, match):
    f = tmp_path / "scene.yaml"
    f.write_text(text)
    with pytest.raises(ConfigError, match=match):
        Timeline.from_scene(f)


def test_cstomo_simulate_writes_a_timeline_scene_with_times_and_state(tmp_path):
    from cstomo_sensor.frames_io import read_forces, read_frames
    from cstomo_sensor.tools.cli import main

    assert main(["simulate", "--scene", str(SCENES / "timeline_drift_short.yaml"), "--out", str(tmp_path)]) == 0
    frames, ref = read_frames(tmp_path / "frames.csv"), read_frames(tmp_path / "reference.csv")
    assert frames.shape == (200, 208) and ref.shape == (1, 208)
    assert read_forces(tmp_path / "truth.csv").shape == (200, 3)
    head, *rows = (tmp_path / "truth.csv").read_text().splitlines()
    names = head.split(",")
    assert names[:8] == "frame,fx,fy,fz,magnitude,elevation_deg,azimuth_deg,time".split(",")
    assert {"delta_t", "gradient", "rho_change", "drive", "fx_eff", "contact_16"} <= set(names)
    table = np.array([[float(x) for x in r.split(",")] for r in rows])
    np.testing.assert_allclose(table[:, names.index("time")], np.arange(200) / 20)
    np.testing.assert_allclose(table[-1, names.index("rho_change")], 0.01 * 3 * 199 / 200, rtol=1e-6)


@pytest.mark.slow  # seconds of a real clock
def test_the_board_plays_a_timeline_scene_in_time(tmp_path):
    """``cstomo board-sim --scene`` with a timeline: the drive drifts by 10 % in 1 s (no noise), so
    every frame is the tare frame times one factor that grows with the frame's time."""
    from cstomo_sensor.board.driver import BoardDriver
    from cstomo_sensor.tools import board_sim

    scene = tmp_path / "drift.yaml"
    scene.write_text("sensor: cuboid_joint\nsnr_db: null\nseed: 2\ntruth_mesh_size: 0.004\n"
                     "timeline: {duration: 1, drive: [[0, 0], [1, 0.1]]}\n")
    ref = Timeline.from_scene(scene).reference
    link = tmp_path / "board"
    with BoardDriver(str(link), reconnect_backoff=(0.01, 0.02)) as driver:
        argv = ["--sensor", "cuboid_joint", "--scene", str(scene), "--rate", "50", "--duration", "1.2",
                "--link", str(link)]
        assert board_sim.main(argv) == 0
        frames = []
        while (f := driver.get(0.2)) is not None:
            frames.append(f)
    assert len(frames) > 20
    ratio = np.array([f.values / np.float32(ref) for f in frames])
    assert np.abs(ratio - ratio.mean(axis=1, keepdims=True)).max() < 1e-6  # one factor per frame
    factor = ratio.mean(axis=1)
    assert np.all(np.diff(factor) >= -1e-7) and factor[0] < 1.01 and factor[-1] > 1.09


def test_a_forward_model_with_other_contact_impedances_is_a_new_model_with_them(truth):
    from cstomo_sensor.model.cem import ForwardModel

    z = truth.z * np.linspace(0.8, 1.2, len(truth.z))
    fm = truth.forward
    want = ForwardModel(truth.device, fm.mesh, contact_impedance=z).voltages()
    assert np.array_equal(fm.with_contact_impedance(z).voltages(), want)
    assert np.array_equal(fm.cem.z, truth.z)  # the original is untouched
    with pytest.raises(ConfigError, match="contact_impedance"):
        fm.with_contact_impedance(-z)



def test_kept_mechanics_are_factorised_once_across_batches_and_freed_at_the_end(cuboid, monkeypatch):
    """A batch of loads releases the mechanics when done (Truth.frames, Timeline.knots, the calibration);
    inside ``elasticity.kept()`` the release waits for the block's end, so the next batch on the same mesh
    reuses the factor (the same solution to rounding), and after the block the factor is gone. (A small
    block of tetrahedra: the cache's behaviour, not a mesh, is judged.)"""
    from skfem import MeshTet

    from cstomo_sensor.model import elastic_fem, elasticity
    from cstomo_sensor.model.cem import symmetric_lu

    calls = []
    monkeypatch.setattr(elastic_fem, "symmetric_lu", lambda A: calls.append(A.shape) or symmetric_lu(A))
    # a cache of this test's own: its releases free nothing this worker keeps for the next tests (conftest.py)
    monkeypatch.setattr(elastic_fem, "_CACHE", {})
    box = MeshTet.init_tensor(*(np.linspace(0.0, 0.01, 4),) * 3)
    points, tets = box.p.T.copy(), box.t.T.astype(np.int64)

    def batch(seed):
        prob = elastic_fem.problem(points, tets, cuboid.material)
        f = np.random.default_rng(seed).normal(size=prob.basis.N)
        fixed = prob.basis.get_dofs(lambda x: x[2] < 1e-9).flatten()
        u = prob.solve(f, fixed, {}, np.zeros(3)).dofs
        elastic_fem.release()  # as every batch ends (elasticity.release, the same function, frees nothing in the suite: conftest.py)
        return u

    with elasticity.kept():
        with elasticity.kept():  # nested: the outer block decides
            batch(1)
        kept = batch(2)
        assert len(calls) == 1
    fresh = batch(2)
    assert len(calls) == 2  # released at the block's end: factorised anew
    batch(3)
    assert len(calls) == 3  # and outside a block every batch releases, as before
    np.testing.assert_allclose(kept, fresh, rtol=1e-9, atol=1e-12 * np.abs(fresh).max())



def test_the_mechanics_cache_drops_a_problem_cheap_to_set_up_again_first(cuboid, monkeypatch):
    """The cache of assembled problems (two) keeps a costly factor past small meshes used since (a worker that
    solved a 4 mm mesh's loads, then a patch scene's small mesh, solves the 4 mm mesh's next load without a new
    factorisation); among problems of like cost the least recently used goes. (Small blocks of tetrahedra;
    their setup costs set here: the policy is judged.)"""
    from skfem import MeshTet

    from cstomo_sensor.model import elastic_fem

    monkeypatch.setattr(elastic_fem, "_CACHE", {})
    meshes = {}
    for n in range(2, 6):
        box = MeshTet.init_tensor(*(np.linspace(0.0, 0.01, n),) * 3)
        meshes[n] = box.p.T.copy(), box.t.T.astype(np.int64)

    def use(n, cost):
        prob = elastic_fem.problem(*meshes[n], cuboid.material)
        prob.setup_cost = cost
        return prob

    def kept():
        return {n for n, m in meshes.items() for p in elastic_fem._CACHE.values() if p.points is m[0]}

    costly = use(2, 5.0)
    use(3, 1.0)
    use(4, 1.0)
    assert kept() == {2, 4}  # the small mesh 3 went, not the older costly one
    assert use(2, 5.0) is costly  # its factor reused
    use(3, 1.0)
    use(5, 1.0)
    assert kept() == {2, 5}
    use(3, 4.0)  # a costly one comes: the small one goes
    assert kept() == {2, 3}
    use(4, 5.0)  # and another: of the two costly ones the least recently used goes
    assert kept() == {3, 4}
    monkeypatch.setattr(elastic_fem, "_CACHE", {})  # equal costs: the least recently used goes (LRU)
    for n in (2, 3, 2, 4):
        use(n, 1.0)
    assert kept() == {2, 4}


@pytest.mark.slow  # seconds (a factorisation of the mechanics when run alone: the creep test's load)
def test_a_loads_mechanics_is_solved_once_for_every_truth_of_the_sensor(truth, monkeypatch):
    """Truth.theta keeps each load's mechanics on disk, keyed by the sensor, the mechanics mesh and the load:
    another device of the sensor (another seed: its own electrodes and contacts) reads it without a solve,
    the same numbers (the held load of the creep test above, solved there when it ran)."""
    from cstomo_sensor.model import elasticity

    down = Load("socket", force=(0.0, 0.0, -20.0))
    first = truth.theta(down)
    solve, solved = elasticity.solve_socket_load, []
    monkeypatch.setattr(elasticity, "solve_socket_load", lambda *a: solved.append(tuple(a[3])) or solve(*a))
    other = Truth(truth.geometry, truth_h=TRUTH_H, seed=4)
    assert [e.center for e in other.device.electrodes] != [e.center for e in truth.device.electrodes]
    np.testing.assert_array_equal(other.theta(down), first)  # read, not solved: the same bytes
    assert solved == []
