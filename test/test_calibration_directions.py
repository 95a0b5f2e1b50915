"""The device's own directions learned from a calibration recording and kept in the calibration file (issue 34
item 1; force/slow_states/learned.py, force/reference/calibration.py, ``cstomo calibrate``).

A calibration recorded while the device changes in a way none of the model's directions describe (the rests
between its loads see it): ``cstomo calibrate`` runs the whole recording through the stream of the calibration it
fitted, the frames the reference sensor says are unloaded feeding the drift tracker's learner, and writes the
directions it learned into the calibration file (``learned_directions``). A stream started from that calibration
(no saved tare: the calibration's own unloaded reference, as a node's first start) tracks them from its first
frame. Judged on a device outside the estimator's model (device_c's own coarse mesh, 60 dB; test_learned.py's
device and change: the rubber warming by 2.4 % with a 30 % gradient along a diagonal, contacts -1 %/K, one
electrode's contact +90 %), by the truth: a restart's zero p99 from 1 s with the calibration's directions against
the same calibration without them and against the device unchanged. Precedence, an old file and a damaged block
are checked on the small linear pipeline."""
import time

import numpy as np
import pytest
import yaml
from test_learned import LOOSE, SNR_DB, device, local_change  # noqa: F401 - device: the module's fixture

from cstomo_sensor.errors import ConfigError
from cstomo_sensor.force.reference.calibration import DeviceCalibration, model_hash
from cstomo_sensor.force.reference.files import write_reference
from cstomo_sensor.force.slow_states.learned import Directions, directions_path, write_directions
from cstomo_sensor.frame_path.config import PipelineConfig, StreamConfig
from cstomo_sensor.frame_path.loop import Trace, run
from cstomo_sensor.frame_path.pipeline import Pipeline
from cstomo_sensor.frame_path.sources import ArraySource
from cstomo_sensor.frame_path.stream import FrameStream
from cstomo_sensor.frames_io import write_forces, write_frames
from cstomo_sensor.model.timeline import Timeline, TimelineSpec
from cstomo_sensor.tools.bench import robot
from cstomo_sensor.tools.bench.scenes import random_forces

RATE = 100.0
HOLD_S, REST_S, FIRST_S, RAMP_S = 2.0, 5.0, 3.0, 55.0
#: The calibration's loads (N, wrench frame): four into the socket in independent directions (15-27 N), each held
#: twice: four of the robot bench's calibration loads of this device (robot.calibrated_pipes: their mechanics are
#: in the cache once test_robot_bench_change calibrated device_c, so the recording solves no new load: on a fresh
#: clone one factorisation of the device's elasticity less, 15-20 s)
LOADS = tuple(tuple(map(float, f)) for f in random_forces(robot.CAL_LOADS, robot.CAL_SEED)[[7, 10, 11, 9]]) * 2
RESTART_S = 20.0
AGE_S = 8 * 3600.0
CONFIG = StreamConfig.offline(creep_per_decade=0.0)  # the simulated rubber does not creep
PIPE_ARGS = ["--sensor", "cuboid_joint", "--mesh-size", "0.004", "--grid", "6", "6", "3", "--iterations", "0",
             "--damping", "0", "--estimator", "model"]  # conftest's PIPE with the model estimator: test_learned's


def recording_spec() -> TimelineSpec:
    """The calibration recording: rest, then each load held HOLD_S with REST_S of rest after it, while the device
    changes as test_learned's local_change (reached at RAMP_S)."""
    times, forces, t = [], [], FIRST_S
    for f in LOADS:
        times += [t, t + HOLD_S]
        forces += [f, (0.0, 0.0, 0.0)]
        t += HOLD_S + REST_S
    spec = local_change(RAMP_S, t)
    return TimelineSpec(**{**spec.__dict__, "load_times": tuple(times), "load_forces": tuple(forces)})


def calibrated(pipe, path) -> Pipeline:
    pipe.set_calibration(DeviceCalibration.load(path, pipe.n_meas))
    return pipe


def restart_p99(pipe, truth, spec, tmp_path) -> tuple[float, FrameStream]:
    """The zero's p99 (N) from 1 s of a first start from the calibration ``pipe`` uses (no saved tare: its unloaded
    reference, recorded AGE_S ago) on the device changed by ``spec``; the stream, started before its first frame."""
    stream = FrameStream(pipe, CONFIG, tare_file=tmp_path / "no_tare.csv")
    assert stream.init_reference(tare_on_start=False) == ""
    assert stream.slow.age_s == pytest.approx(AGE_S, abs=120.0)  # the calibration's reference: a restart
    started = (len(stream.slow.directions), stream.slow.drift.m)
    tl = Timeline(spec, snr_db=SNR_DB, seed=9, truth=truth).prepare()
    times, frames, forces, _ = tl.frames(RATE, rng=np.random.default_rng(9))
    trace = Trace(lambda: stream.slow.scale)
    run(ArraySource(frames, (1e9 * (1 + times)).astype(np.int64)), stream, [trace])
    est = np.array(trace.forces, float).reshape(-1, 3)
    assert not forces.any()  # at rest
    err = np.linalg.norm(est - forces, axis=1)[times >= 1.0]
    assert np.isfinite(err).all()
    stream.started = started
    return float(np.percentile(err, 99)), stream


@pytest.mark.slow
def test_a_calibration_recording_teaches_the_devices_directions_and_a_start_from_it_tracks_them(
        device, tmp_path, capsys):  # noqa: F811 - the imported fixture
    from cstomo_sensor.tools.calibrate import main

    truth, pipe, tare = device
    t0 = time.monotonic()
    spec = recording_spec()
    tl = Timeline(spec, snr_db=SNR_DB, seed=5, truth=truth).prepare()
    times, frames, forces, _ = tl.frames(RATE, rng=np.random.default_rng(5))
    t_sim = time.monotonic() - t0
    recorded = time.strftime("%Y-%m-%dT%H:%M:%S%z", time.localtime(time.time() - AGE_S))
    write_reference(tmp_path / "ref.csv", tare.mean(0), tare.std(0, ddof=1), f"test: the device's tare, {recorded}",
                    len(tare))
    write_frames(tmp_path / "frames.csv", frames)
    write_forces(tmp_path / "forces.csv", forces)  # a row per frame: 0 N at the rests
    out = tmp_path / "device.yaml"
    t1 = time.monotonic()
    assert main([*PIPE_ARGS, "--reference", str(tmp_path / "ref.csv"), "--frames", str(tmp_path / "frames.csv"),
                 "--forces", str(tmp_path / "forces.csv"), "--rate", str(RATE), "--creep-per-decade", "0",
                 "--out", str(out)]) == 0
    t_cal = time.monotonic() - t1
    said = [line for line in capsys.readouterr().out.splitlines() if line.startswith("directions:")]
    print(said)
    assert len(said) == 1 and " of the device's own learned from the recording" in said[0], said
    doc = yaml.safe_load(out.read_text())
    block = doc["learned_directions"]
    k = len(block["rows"])
    assert 1 <= k <= 2 and len(block["restart_per_scale"]) == k and all(len(r) == 208 for r in block["rows"])
    cal = DeviceCalibration.load(out)
    assert len(cal.directions) == k and "cstomo calibrate" in cal.directions_note

    # the same calibration without the block: a file as written before the directions (it still loads)
    old = tmp_path / "old.yaml"
    old.write_text(yaml.safe_dump({key: v for key, v in doc.items() if key != "learned_directions"}, sort_keys=False))
    old.with_name("old.reference.csv").write_bytes(out.with_name("device.reference.csv").read_bytes())
    assert DeviceCalibration.load(old).directions is None

    restart = local_change(0.0, RESTART_S)
    try:
        with_p99, node = restart_p99(calibrated(pipe, out), truth, restart, tmp_path)
        assert node.started == (k, 8 + k)  # the calibration's directions, tracked from the first frame
        without_p99, node = restart_p99(calibrated(pipe, old), truth, restart, tmp_path)
        assert node.started == (0, 8)
        unchanged_p99, _ = restart_p99(calibrated(pipe, out), truth, TimelineSpec(duration=RESTART_S,
                                                                                 contact_per_k=0.0), tmp_path)
    finally:
        pipe.set_calibration(None)
    print(f"first start from the calibration's reference 8 h old, zero p99 from 1 s: {with_p99:.3f} N with its {k} "
          f"learned direction(s), {without_p99:.3f} N without, {unchanged_p99:.3f} N on the device unchanged "
          f"(simulation {t_sim:.1f} s, cstomo calibrate {t_cal:.1f} s)")
    # with the calibration's directions the zero is the unchanged device's (issue 34's aim: within 1.25 x) and never
    # worse than without them; how much worse it is without depends on the truth mesh (test_learned.py): printed
    assert with_p99 < 1.25 * unchanged_p99, (with_p99, unchanged_p99)
    assert with_p99 < 1.05 * without_p99 + 0.02, (with_p99, without_p99)


@pytest.fixture(scope="module")
def small():
    from conftest import PIPE

    pipe = Pipeline.build(PipelineConfig(**{**PIPE, "grid": tuple(PIPE["grid"])}))
    rows = np.random.default_rng(3).normal(size=(2, pipe.n_meas)) * 1e-3
    return pipe, Directions(rows, np.array([0.4, 1.9]))


def a_calibration(pipe, directions=None) -> DeviceCalibration:
    return DeviceCalibration(pipe.geometry.name, model_hash(pipe.model), "linear", np.eye(3),
                             np.zeros((pipe.n_meas, 3)), directions=directions, directions_note="test")


def test_a_stream_starts_with_its_calibrations_directions_and_a_saved_tares_own_come_first(small, tmp_path, caplog):
    pipe, dirs = small
    path = tmp_path / "device.yaml"
    a_calibration(pipe, dirs).save(path)
    back = DeviceCalibration.load(path, pipe.n_meas)
    assert np.allclose(back.directions.rows, dirs.rows, rtol=1e-8) and np.allclose(back.directions.per_scale,
                                                                                  dirs.per_scale)
    pipe.set_calibration(back)
    try:
        tare = tmp_path / "tare.csv"
        write_reference(tare, pipe.model_reference * 1.001, None, "test: saved tare", 20)
        # a saved tare without directions beside it: the calibration's
        s = FrameStream(pipe, StreamConfig.offline(), tare_file=tare)
        assert s.init_reference(tare_on_start=False) == ""
        assert len(s.slow.directions) == 2 and s.slow.drift.m == 10
        assert np.allclose(s.slow.directions.rows, dirs.rows, rtol=1e-8)
        # ... kept over a fresh tare
        s.set_reference(pipe.model_reference * 1.002, None, 20, "a fresh tare")
        assert len(s.slow.directions) == 2 and s.slow.drift.m == 10
        # a saved tare's own directions are newer: they take the calibration's place
        own = Directions(dirs.rows[:1] * -2.0, np.array([0.7]))
        write_directions(tare, own)
        s = FrameStream(pipe, StreamConfig.offline(), tare_file=tare)
        assert s.init_reference(tare_on_start=False) == ""
        assert len(s.slow.directions) == 1 and np.allclose(s.slow.directions.rows, own.rows, rtol=1e-8)
        assert s.slow.drift.m == 9
        # an unreadable one beside the tare: said once, the calibration's used
        directions_path(tare).write_text("1,2,3\n")
        s = FrameStream(pipe, StreamConfig.offline(), tare_file=tare)
        assert s.init_reference(tare_on_start=False) == ""
        assert len(s.slow.directions) == 2 and "the calibration's 2 direction(s)" in caplog.text
        # no saved tare: the calibration's own reference isn't there either, a tare on the first frames: the calibration's
        s = FrameStream(pipe, StreamConfig.offline(), tare_file=tmp_path / "none.csv")
        s.init_reference(tare_on_start=True)
        assert s.tares.pending and len(s.slow.directions) == 2
    finally:
        pipe.set_calibration(None)
    # the nominal model: none
    s = FrameStream(pipe, StreamConfig.offline())
    s.set_reference(pipe.model_reference * 1.001, None, 20, "a tare")
    assert len(s.slow.directions) == 0 and s.slow.drift.m == 8


def test_a_calibration_file_written_before_the_directions_still_loads(small, tmp_path):
    """The format as docs/formats.md gives it without ``learned_directions`` (every file written before them)."""
    pipe, _ = small
    rows = "\n".join("- [1.5e-05, -2.1e-06, 3.3e-06]" for _ in range(pipe.n_meas))
    path = tmp_path / "old.yaml"
    path.write_text(f"""# cstomo_sensor device calibration: y_device(F) = y_model(force_map F) + correction F (README)
format: cstomo_sensor device calibration 1
sensor: cuboid_joint
model_hash: {model_hash(pipe.model)}
estimator: linear
prior_rel: 0.2
fitted_on: {{loads: 8, frames: loaded.csv, date: '2025-01-01T12:00:00', forces: loads.csv, reference: tare.csv}}
force_map:
- [1.08, 0.01, 0.0]
- [0.0, 1.07, 0.02]
- [-0.01, 0.0, 0.93]
correction_per_newton:
{rows}
""")
    cal = DeviceCalibration.load(path, pipe.n_meas)
    assert cal.directions is None and cal.force_map[0, 0] == pytest.approx(1.08)
    pipe.set_calibration(cal)
    try:
        s = FrameStream(pipe, StreamConfig.offline())
        s.set_reference(pipe.model_reference * 1.001, None, 20, "a tare")
        assert len(s.slow.directions) == 0 and s.slow.drift.m == 8  # the model's directions only
    finally:
        pipe.set_calibration(None)
    # ... and one saved without directions has no block
    a_calibration(pipe).save(tmp_path / "none.yaml")
    assert "learned_directions" not in yaml.safe_load((tmp_path / "none.yaml").read_text())


@pytest.mark.parametrize("change, says", [
    (lambda b: b.update(rows=[r[:-1] for r in b["rows"]]),
     r"learned_directions\.rows of shape \(2, 207\): expected 1 to 2 rows of 208 finite numbers"),
    (lambda b: b.update(rows=b["rows"] * 2, restart_per_scale=[1.0] * 4), r"of shape \(4, 208\): expected 1 to 2 rows of 208"),
    (lambda b: b["rows"][0].__setitem__(-1, float("nan")), r"learned_directions\.rows: row 1 is not finite or all zero"),
    (lambda b: b["rows"][1].__setitem__(slice(None), [0.0] * 208), r"row 2 is not finite or all zero"),
    (lambda b: b.update(restart_per_scale=[0.4]),
     r"learned_directions\.restart_per_scale=\[0\.4\]: expected 2 finite number\(s\) >= 0, one per row"),
    (lambda b: b.update(restart_per_scale=[0.4, -1.0]), r"restart_per_scale=\[0\.4, -1\.0\]: expected 2 finite"),
    (lambda b: b.update(rows="damaged"), r"learned_directions\.rows not a table of numbers: expected 1 to 2 rows"),
    (lambda b: b.pop("rows"), r"learned_directions: \['note', 'restart_per_scale'\], expected a mapping with 'rows'"),
])
def test_a_damaged_directions_block_is_refused_naming_it_and_the_shape_expected(small, tmp_path, change, says):
    pipe, dirs = small
    path = tmp_path / "device.yaml"
    a_calibration(pipe, dirs).save(path)
    doc = yaml.safe_load(path.read_text())
    change(doc["learned_directions"])
    path.write_text(yaml.safe_dump(doc, sort_keys=False))
    with pytest.raises(ConfigError, match=says) as err:
        DeviceCalibration.load(path, pipe.n_meas)
    assert str(path) in str(err.value) and "\n" not in str(err.value)


def test_a_recordings_rests_are_its_paired_frames_under_no_load():
    """tools/calibrate.py Recording.rests: the frames of a recording the reference sensor says are unloaded, by their
    place in the whole recording (a bag's unpaired frames, taken while the load changed, are none)."""
    from cstomo_sensor.tools.calibrate import Recording

    rec = Recording(np.zeros((8, 208)), np.arange(8.0), np.array([6, 1, 2, 4]))
    marked = rec.rests(np.array([True, False, True, False]))
    assert marked.rest.tolist() == [False, False, True, False, False, False, True, False]
    assert rec.rest is None  # a new recording, this one unchanged
