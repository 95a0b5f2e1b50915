"""The device's own directions (issue 34 item 1; cstomo_sensor/force/slow_states/learned.py): a device whose change after
its tare is not the model's learns the part its rests leave unexplained, tracks it as a state, and keeps it
across a restart (saved beside the tare and read back); a device whose change is the model's learns nothing.

Judged on a device outside the estimator's model (device_c's own mesh, coarse here: the test judges the
mechanism, not a mesh; 60 dB), with the honest simulator's own change (model/timeline.py): the rubber warming
by 2.4 % with a 30 % gradient along a diagonal of the block and the contacts -1 %/K (docs/physics.md#device-changes),
and besides one electrode's contact loosening alone (+90 %: a change none of the model's directions describe).
Expected figures come from the truth, never from the code under test: a restart's zero p99 from 1 s with the
learned directions against without them and against the same restart of the device unchanged."""
import os
import time

import numpy as np
import pytest

from cstomo_sensor.errors import FrameError
from cstomo_sensor.force.reference.files import write_reference
from cstomo_sensor.force.slow_states.learned import (
    AVG,
    BULK,
    STEPS,
    Directions,
    Unloaded,
    _Lanczos,
    directions_path,
    noise_edge,
    read_directions,
    write_directions,
)
from cstomo_sensor.frame_path.config import PipelineConfig, StreamConfig
from cstomo_sensor.frame_path.loop import Trace, run
from cstomo_sensor.frame_path.pipeline import Pipeline
from cstomo_sensor.frame_path.sources import ArraySource
from cstomo_sensor.frame_path.stream import FrameStream
from cstomo_sensor.model.simulate import Truth
from cstomo_sensor.model.timeline import ContactDrift, Profile, Timeline, TimelineSpec, full_change
from cstomo_sensor.tools.bench import robot
from cstomo_sensor.tools.bench import robot_change as rc

SNR_DB = 60.0
LOOSE = 0.9          # one electrode's contact, +90 % (electrode 3)
LEARN_S, RAMP_S, RESTART_S = 90.0, 60.0, 20.0
AGE_S = 8 * 3600.0
CONFIG = StreamConfig.offline(creep_per_decade=0.0)


def local_change(ramp_s: float, duration: float) -> TimelineSpec:
    """The non-uniform change (module docstring), reached at ``ramp_s`` (0: there from the first frame)."""
    spec = full_change(0.024, 0.3, -0.01, 0.008, ramp_s=ramp_s, duration=duration, axis=(1.0, 1.0, 0.0))
    values = [0.0] * 16
    values[2] = LOOSE
    return TimelineSpec(**{**spec.__dict__, "contact_drift": ContactDrift(kind="linear", values=tuple(values),
                                                                          over_s=ramp_s or 1e-3)})


def uniform_change(ramp_s: float, duration: float) -> TimelineSpec:
    """The model's own change: every impedance of the device alike, +2.4 % (the rubber's resistivity and the
    contacts' impedance warming by the same 0.8 %/K: every voltage scales by it, the tracker's scale)."""
    temp = Profile(((0.0, 0.0), (ramp_s, 3.0))) if ramp_s else Profile(((0.0, 3.0),))
    return TimelineSpec(duration=duration, temperature=temp, resistivity_per_k=0.008, contact_per_k=0.008)


@pytest.fixture(scope="module")
def device():
    from conftest import PIPE

    sc, fine = robot.device_truth(scene=rc.FULL_SCENES[1])
    truth = Truth(fine.geometry, truth_h=4.0e-3, z_rel=sc.z_rel, jitter=sc.jitter, seed=sc.seed)
    pipe = Pipeline.build(PipelineConfig(**{**PIPE, "grid": tuple(PIPE["grid"]), "estimator": "model"}))
    tare = Timeline(TimelineSpec(duration=1.0), snr_db=SNR_DB, seed=3, truth=truth).tare(20, np.random.default_rng(22))
    return truth, pipe, tare


def run_frames(stream, truth, spec, seed):
    """(times, forces read, true forces) of the timeline ``spec`` at 100 frames/s through ``stream``."""
    tl = Timeline(spec, snr_db=SNR_DB, seed=seed, truth=truth).prepare()
    times, frames, forces, _ = tl.frames(100.0, rng=np.random.default_rng(seed))
    trace = Trace(lambda: stream.slow.scale)
    run(ArraySource(frames, (1e9 * (1 + times)).astype(np.int64)), stream, [trace])
    return times, np.array(trace.forces, float).reshape(-1, 3), forces


def learning_session(device, tmp_path, spec):
    """A session from a fresh tare saved to a tare file, the device changing at rest; returns the stream."""
    truth, pipe, tare = device
    tmp_path.mkdir(parents=True, exist_ok=True)
    path = tmp_path / "tare.csv"
    write_reference(path, tare.mean(0), tare.std(0, ddof=1), "test: saved tare", len(tare))
    stream = FrameStream(pipe, CONFIG, tare_file=path)
    stream.set_reference(tare.mean(0), tare.std(0, ddof=1), len(tare), "tare")
    stream.test_forces = run_frames(stream, truth, spec, seed=5)[1]  # the forces read, for the replay check
    return stream, path


def restart_p99(device, path, spec) -> tuple[float, FrameStream]:
    """The zero's p99 (N) from 1 s of a restart (the node's start) from the tare file ``path`` aged 8 hours."""
    truth = device[0]
    os.utime(path, (time.time() - AGE_S,) * 2)
    stream = FrameStream(device[1], CONFIG, tare_file=path)
    assert stream.init_reference(tare_on_start=False) == ""
    times, est, forces = run_frames(stream, truth, spec, seed=9)
    assert not forces.any()  # at rest
    err = np.linalg.norm(est - forces, axis=1)[times >= 1.0]
    assert np.isfinite(err).all()
    return float(np.percentile(err, 99)), stream


@pytest.mark.slow
def test_a_non_uniform_change_is_learned_from_rests_and_kept_across_a_restart(device, tmp_path):
    stream, path = learning_session(device, tmp_path, local_change(RAMP_S, LEARN_S))
    learned = stream.slow.directions
    L = stream.slow.learner
    print(f"learned {len(learned)} from {L.n * AVG} clear frames ({L.decisions} decisions), the covariance's largest "
          f"ratio {L.max_ratio:.3f}, {L.max_excess:.3f} x the noise's edge")
    assert 1 <= len(learned) <= 2
    assert stream.slow.drift.m == 1 + 7 + len(learned)  # the scale, 4 contacts and 3 gradients, then the learned
    side = directions_path(path)
    deadline = time.monotonic() + 10.0
    while time.monotonic() < deadline and not side.is_file():  # saved by a thread of its own
        time.sleep(0.05)
    back = read_directions(path)
    assert back is not None and len(back) == len(learned)
    scale = np.abs(learned.rows).max()
    assert np.allclose(back.rows, learned.rows, rtol=1e-6, atol=1e-9 * scale)
    assert np.allclose(back.per_scale, learned.per_scale, rtol=1e-5)
    # the same frames again (a replay): the same directions, learned at the same frames, the same forces (the
    # decomposition is spread over the frames, no thread: learned.py STEPS)
    again, _ = learning_session(device, tmp_path / "again", local_change(RAMP_S, LEARN_S))
    assert len(again.slow.directions) == len(learned)
    assert np.allclose(again.slow.directions.rows, learned.rows, rtol=1e-9, atol=1e-12 * scale)
    f0, f1 = stream.test_forces, again.test_forces
    assert f0.shape == f1.shape and np.allclose(f0, f1, rtol=1e-9, atol=1e-9, equal_nan=True)

    restart = local_change(0.0, RESTART_S)
    with_p99, node = restart_p99(device, path, restart)
    assert len(node.slow.directions) == len(learned) and node.slow.drift.m == stream.slow.drift.m  # it starts with them
    side.rename(tmp_path / "aside.csv")
    without_p99, node = restart_p99(device, path, restart)
    assert len(node.slow.directions) == 0 and node.slow.drift.m == 8  # an old tare file: the model's directions only
    unchanged_p99, _ = restart_p99(device, path, TimelineSpec(duration=RESTART_S, contact_per_k=0.0))
    # with the device's directions the zero is the unchanged device's (issue 34's aim: within 1.25 x), and never
    # worse than without them. Without them the restart's re-acquisition at rest (drift.widen's QUIET_POST) finds
    # the loose contact through the model's states on some truth meshes (0.30 N against 0.28 on a fresh clone's)
    # and not on others (1.6 N): how much the model's directions leave of this change depends on the mesh, so
    # the contrast is printed, not asserted
    assert with_p99 < 1.25 * unchanged_p99, (with_p99, unchanged_p99)
    assert with_p99 < 1.05 * without_p99 + 0.02, (with_p99, without_p99)
    print(f"restart zero p99 from 1 s: {with_p99:.3f} N learned, {without_p99:.3f} N without, {unchanged_p99:.3f} N unchanged")


@pytest.mark.slow
def test_a_device_whose_change_is_the_models_learns_nothing(device, tmp_path):
    stream, path = learning_session(device, tmp_path, uniform_change(RAMP_S, LEARN_S))
    L = stream.slow.learner
    print(f"uniform: learned {len(stream.slow.directions)}, the covariance's largest ratio {L.max_ratio:.3f}, "
          f"{L.max_excess:.3f} x the noise's edge, {L.decisions} decisions")
    assert L.n * AVG > 5000  # its rests were looked at (AVG rest frames a sample)
    assert L.decisions >= 4  # decided early and again (learned.py FIRST, DECIDE)
    assert len(stream.slow.directions) == 0 and stream.slow.drift.m == 8
    assert 0.0 < L.max_excess < 1.0, L.max_excess  # the noise's own bulk: nothing stands out of its edge
    assert not directions_path(path).exists()


def test_the_directions_file_round_trips_and_a_bad_one_is_refused_with_its_name(tmp_path):
    path = tmp_path / "tare.csv"
    assert read_directions(path) is None  # an older tare: none
    rng = np.random.default_rng(1)
    d = Directions(rng.normal(size=(2, 208)), np.array([0.5, 1.9]))
    write_directions(path, d, comment="test")
    back = read_directions(path)
    assert np.allclose(back.rows, d.rows, rtol=1e-8) and np.allclose(back.per_scale, d.per_scale)
    text = directions_path(path).read_text()
    row = text.splitlines()[-1]
    # the calibration block's check (learned.py Directions.checked): one line naming the file, the part and what
    # was expected
    for damaged, says in [
        (text.replace("restart per scale: 0.5 1.9", "restart per scale: 0.5"),
         r"restart per scale=\['0\.5'\]: expected 2 finite number\(s\) >= 0, one per row"),
        (text.replace("restart per scale: 0.5 1.9", "restart per scale: 0.5 -1"), r"restart per scale=\['0\.5', '-1'\]"),
        (text.replace("# restart per scale: 0.5 1.9\n", ""), "restart per scale missing: expected 2 finite"),
        (f"{text}{row}\n", r"rows of shape \(3, 208\): expected 1 to 2 rows of 208 finite numbers, not all zero"),
        (text.replace(row, ",".join(["0"] * 208)), "rows: row 2 is not finite or all zero"),
    ]:
        directions_path(path).write_text(damaged)
        with pytest.raises(FrameError, match=says) as err:
            read_directions(path)
        assert str(directions_path(path)) in str(err.value) and "\n" not in str(err.value)
    write_directions(path, Directions(np.zeros((0, 208)), np.zeros(0)))
    assert not directions_path(path).exists()  # none learned: no file


def test_a_saved_tare_with_an_unreadable_directions_file_still_starts(tmp_path, caplog):
    from conftest import PIPE

    pipe = Pipeline.build(PipelineConfig(**{**PIPE, "grid": tuple(PIPE["grid"])}))
    path = tmp_path / "tare.csv"
    write_reference(path, pipe.model_reference, None, "test: saved tare", 1)
    directions_path(path).write_text("1,2,3\n")
    stream = FrameStream(pipe, StreamConfig.offline(), tare_file=path)
    assert stream.init_reference(tare_on_start=False) == ""
    assert len(stream.slow.directions) == 0
    assert "learned directions not used" in caplog.text and "directions.csv" in caplog.text


def white_ratios(n: int, p: int, draws: int, rng) -> np.ndarray:
    """The largest over the BULK-th largest component of ``draws`` covariances of ``n`` samples of ``p`` independent
    channels, about their mean and normalised by their diagonal (as the learner's), by scipy's full eigh."""
    from scipy.linalg import eigh

    out = []
    for _ in range(draws):
        X = rng.normal(size=(n, p))
        X -= X.mean(axis=0)
        C = X.T @ X / n
        d = np.sqrt(C.diagonal())
        lam = eigh(C / np.outer(d, d), eigvals_only=True)
        out.append(lam[-1] / lam[-BULK])
    return np.array(out)


def test_the_noise_edge_holds_for_few_samples_and_many():
    rng = np.random.default_rng(11)
    p = 200
    for n in (30, 50, 200, 600):
        r = white_ratios(n, p, 150, rng)
        edge = noise_edge(n, p)
        assert (r < edge).all(), (n, r.max(), edge)  # noise alone stays below it (about 1e-4 per decision)
        # ... and the edge is the noise's, not a wide margin: within 15 % of its 99th percentile
        assert edge < 1.15 * np.percentile(r, 99), (n, edge, np.percentile(r, 99))
    assert noise_edge(50, p) > noise_edge(200, p) > noise_edge(2000, p) > 1.0  # fewer samples: a higher edge


@pytest.mark.parametrize("n", [40, 400])
def test_the_amortised_decomposition_is_the_full_ones(n):
    """The learner's decomposition, a Lanczos step per frame, gives the BULK largest components of the normalised
    covariance as scipy's eigh of it does (fewer samples than channels: a covariance of low rank, too)."""
    from scipy.linalg import eigh

    rng = np.random.default_rng(n)
    p = 120
    keep = np.ones(p, bool)
    keep[[3, 50]] = False
    X = rng.normal(size=(n, p)) + np.outer(rng.normal(size=n), rng.normal(size=p)) * 0.5  # noise and one direction
    X[:, ~keep] = 0.0
    run = _Lanczos(X.T @ X, X.sum(axis=0), n, keep, ())
    frames = 1
    while not run.step(STEPS):
        frames += 1
    lam, vec = run.result()
    assert frames <= 2 + min(n, keep.sum()) + 1  # two frames form it, then a step per rank (and the null space), at most its size
    mu = X[:, keep].mean(axis=0)
    C = X[:, keep].T @ X[:, keep] / n - np.outer(mu, mu)
    d = np.sqrt(C.diagonal())
    ref, rvec = eigh(C / np.outer(d, d))
    assert np.allclose(lam, ref[-BULK:], rtol=1e-8, atol=1e-10 * ref[-1])
    assert abs(abs(vec.dot(rvec[:, -1])) - 1.0) < 1e-8


@pytest.mark.slow
def test_a_load_held_for_minutes_is_not_learned(device, tmp_path):
    """A load held for two minutes on a device that changes as the model says (nothing to learn): its frames never
    feed the learner (a load comes in a step; only a rest frame clears it), so it is never a direction."""
    hold = (10.0, 130.0)
    spec = TimelineSpec(duration=140.0, temperature=Profile(((0.0, 0.0), (140.0, 3.0))), resistivity_per_k=0.008,
                        contact_per_k=0.008, load_times=hold, load_forces=((1.5, -1.0, -4.0), (0.0, 0.0, 0.0)))
    stream, path = learning_session(device, tmp_path, spec)
    L = stream.slow.learner
    unloaded_frames = 100 * (140.0 - (hold[1] - hold[0]))
    print(f"held load: learned {len(stream.slow.directions)} from {L.fed} frames ({L.decisions} decisions, "
          f"{L.max_excess:.3f} x the noise's edge)")
    assert 0 < L.fed <= unloaded_frames  # the unloaded frames only
    assert len(stream.slow.directions) == 0 and stream.slow.drift.m == 8
    assert not directions_path(path).exists()


def test_the_chain_of_clear_frames_follows_a_slow_phantom_and_breaks_at_a_load():
    """Unloaded (learned.py): after a rest frame, frames the rest test refuses stay clear while the force moves as
    a device's change does (a phantom growing 1.5 N in 30 s, noise 0.27 N per axis at 100 frames/s); a load's step
    (0.5 N in 0.1 s), a known load or a refused frame ends it, and only a rest frame begins it again."""
    rng = np.random.default_rng(4)
    sigma, dt = 0.27, 0.01
    u = Unloaded()

    def frames(force_of_t, n, rest=False, known=False, t0=0.0):
        return [u.step(force_of_t(t0 + i * dt) + rng.normal(0, sigma, 3), rest, sigma, dt, known) for i in range(n)]

    assert not any(frames(lambda t: np.zeros(3), 300))  # no rest frame yet: nothing is clear
    assert all(frames(lambda t: np.zeros(3), 5, rest=True))
    phantom = lambda t: np.array([0.05 * t, -0.02 * t, 0.0])  # noqa: E731
    assert all(frames(phantom, 3000))  # 30 s of a slow phantom, refused by the rest test: clear throughout
    f0 = phantom(30.0)
    step = frames(lambda t: f0 + np.array([0.0, 0.0, -min(t, 0.1) * 5.0]), 300)  # a 0.5 N load put on in 0.1 s
    assert not step[-1] and sum(step) < 40  # the step ends the chain within 0.4 s ...
    assert not any(frames(lambda t: f0 + np.array([0.0, 0.0, -0.5]), 2000))  # ... and the held load stays out
    assert all(frames(lambda t: np.zeros(3), 300, rest=True))  # rest frames (fed as ever) begin it again ...
    assert all(frames(lambda t: np.zeros(3), 100))  # ... once the load's step has passed
    assert not any(frames(lambda t: np.zeros(3), 5, known=True))  # a controller's load beyond the rest force
    assert all(frames(lambda t: np.zeros(3), 5, rest=True))
    assert not u.step(None, False, sigma, dt, False)  # a refused frame (no force)
    assert not any(frames(lambda t: np.zeros(3), 5))


def test_frames_on_one_stamp_neither_raise_nor_move_the_chains_means():
    """Frames that share a stamp (a simulated clock at 20 Hz under 100 frames/s, a coarse host clock): the frame
    period is 0 s for most of them. The chain takes them without an error (a ZeroDivisionError dropped every such
    frame in the node) and still sees a load's step on the frames that advance the clock."""
    rng = np.random.default_rng(5)
    sigma, u = 0.27, Unloaded()
    dts = [0.05 if i % 5 == 0 else 0.0 for i in range(4000)]  # a 20 Hz clock under 100 frames/s
    assert all(u.step(rng.normal(0, sigma, 3), True, sigma, dt, False) for dt in dts[:20])  # rest frames
    fast = list(u.fast)
    assert u.step(np.array([9.0, 9.0, 9.0]), False, sigma, 0.0, False)  # no time: the means stay ...
    assert u.fast == fast  # ... where they were
    clear = [u.step(rng.normal(0, sigma, 3), False, sigma, dt, False) for dt in dts[20:1000]]
    assert all(clear)  # no load: the chain holds
    load = [u.step(np.array([0.0, 0.0, -3.0]) + rng.normal(0, sigma, 3), False, sigma, dt, False) for dt in dts[:200]]
    assert not load[-1] and sum(load) < 40  # a 3 N load's step ends it within a few clock ticks
