"""Device calibration on known loads (cstomo_sensor.force.reference.calibration, ``cstomo calibrate``).

The device is scenes/devices/cuboid_joint_device_a.yaml (material and electrode placement inside
docs/physics.md#real-devices), simulated honestly by the scene file scenes/cuboid_device_a_60db.yaml
(independent 3 mm mesh, +-30 % contact impedance, 60 dB); the models are the nominal cuboid_joint's.
Calibration loads and held-out loads are different random forces with different noise.

Stated tolerances on 12 held-out loads, both estimators (nominal sensor today: `model` 0.5 deg and
0.8 %, `linear` 0.8 deg and 2.0 %):
- uncalibrated: the magnitude error is large (median > 20 %) and the cross-validated table says so;
- 20 loads: angle median < 1.0 deg and p90 < 2.5 deg, magnitude median < 2.5 % and p90 < 5 %;
- 5 loads: angle median < 1.5 deg and p90 < 4 deg, magnitude median < 4 % and p90 < 8 %.
"""
from pathlib import Path

import numpy as np
import pytest
from conftest import MODEL_H

from cstomo_sensor.errors import ConfigError, ModelMismatchError
from cstomo_sensor.force.reference.calibration import DeviceCalibration, calibrate, summary
from cstomo_sensor.force.reference.files import reference_of
from cstomo_sensor.frame_path.config import PipelineConfig
from cstomo_sensor.frame_path.pipeline import Pipeline
from cstomo_sensor.model.simulate import Load, Scene, add_noise

pytestmark = pytest.mark.slow  # calibration effort: the held-out device's frames (~47 s) and node runs

SCENES = Path(__file__).resolve().parent.parent / "scenes"


def random_forces(n, rng):
    mag = rng.uniform(5, 40, n)
    el, az = np.radians(rng.uniform(20, 90, n)), rng.uniform(-np.pi, np.pi, n)
    return np.column_stack([mag * np.cos(el) * np.cos(az), mag * np.cos(el) * np.sin(az), -mag * np.sin(el)])


@pytest.fixture(scope="module")
def device():
    """(tare frames, calibration frames, their forces, held-out frames, their forces) at 60 dB."""
    scene = Scene.load(SCENES / "cuboid_device_a_60db.yaml")
    truth = scene.truth()
    assert truth.geometry.material.E == 0.8e6 and truth.geometry.name == "cuboid_joint_device_a"
    rng = np.random.default_rng(1101)
    F_cal, F_held = random_forces(20, rng), random_forces(12, rng)
    ref = truth.reference
    noisy = lambda v: add_noise(v, ref, scene.snr_db, rng)  # noqa: E731
    tare = noisy(np.repeat(ref[None], 50, 0))
    cal = noisy(np.array([truth.voltages(Load("socket", force=tuple(f))) for f in F_cal]))
    held = noisy(np.array([truth.voltages(Load("socket", force=tuple(f))) for f in F_held]))
    return tare, cal, F_cal, held, F_held


@pytest.fixture(scope="module", params=["linear", "model"])
def pipe(request):
    return Pipeline.build(PipelineConfig(estimator=request.param, mesh_size=MODEL_H))


def held_out(pipe, frames, forces):
    return summary(np.array([pipe.process(v, with_field=False).force for v in frames]), forces)


@pytest.mark.parametrize("n, tol", [(20, (1.0, 2.5, 2.5, 5.0)), (5, (1.5, 4.0, 4.0, 8.0))])
def test_calibration_meets_the_stated_tolerances_on_held_out_loads(pipe, device, n, tol):
    tare, frames, forces, held, F_held = device
    pipe.set_calibration(None)
    report = pipe.set_reference(*reference_of(tare))
    assert report.factor > 1.5  # the batch is 1.7 x as resistive: named, and normalised out
    before = held_out(pipe, held, F_held)
    cal = calibrate(pipe, frames[:n], forces[:n])
    assert cal.cv["before"]["magnitude_pct_median"] > 20 and before["magnitude_pct_median"] > 20, (cal.cv, before)
    assert cal.cv["after"]["magnitude_pct_median"] < tol[2]  # the table says what the held-out loads find
    pipe.set_calibration(cal)
    try:
        after = held_out(pipe, held, F_held)
    finally:
        pipe.set_calibration(None)
    a_med, a_p90, m_med, m_p90 = tol
    assert after["angle_deg_median"] < a_med and after["angle_deg_p90"] < a_p90, (n, before, after)
    assert after["magnitude_pct_median"] < m_med and after["magnitude_pct_p90"] < m_p90, (n, before, after)


def test_file_round_trip_other_model_refused_and_damage_named(tmp_path, device):
    import dataclasses

    tare, frames, forces, *_ = device
    pipe = Pipeline.build(PipelineConfig(estimator="linear", mesh_size=MODEL_H))
    pipe.set_reference(*reference_of(tare))
    cal = calibrate(pipe, frames[:8], forces[:8], fitted_on={"frames": "test"})
    path = tmp_path / "device.yaml"
    cal.save(path)
    back = DeviceCalibration.load(path)
    np.testing.assert_allclose(back.correction, cal.correction, rtol=1e-8, atol=1e-15)
    np.testing.assert_allclose(back.force_map, cal.force_map, rtol=1e-11)
    assert back.fitted_on["loads"] == 8 and back.sensor == "cuboid_joint" and back.estimator == "linear"
    assert "pickle" not in path.read_text() and "!!python" not in path.read_text()
    # another model (another mesh: its unloaded prediction differs): refused, naming both hashes
    other = dataclasses.replace(pipe.model, model_reference=pipe.model.model_reference * (1 + 1e-4))
    other_pipe = Pipeline(pipe.geometry, other, pipe.base_estimator)
    with pytest.raises(ModelMismatchError) as err:
        other_pipe.set_calibration(back)
    from cstomo_sensor.force.reference.calibration import model_hash

    assert cal.model_hash in str(err.value) and model_hash(other) in str(err.value)
    same = dataclasses.replace(pipe.model, model_reference=pipe.model.model_reference * (1 + 1e-13))
    Pipeline(pipe.geometry, same, pipe.base_estimator).set_calibration(back)  # rounding only: accepted
    # damaged files: a clear error naming the file
    text = path.read_text()
    cases = {"truncated": text[: len(text) // 2], "empty": "", "not yaml": "format: [unclosed\n",
             "other format": text.replace("device calibration 1", "device calibration 9"),
             "nan": text.replace("correction_per_newton:\n- [", "correction_per_newton:\n- [.nan, 0, 0]\n- [", 1),
             "wrong shape": text.replace("force_map:\n- [", "force_map:\n- [1, ", 1)}
    for name, body in cases.items():
        bad = tmp_path / f"{name.replace(' ', '_')}.yaml"
        bad.write_text(body)
        with pytest.raises(ConfigError) as err:
            DeviceCalibration.load(bad)
        assert str(bad) in str(err.value), (name, err.value)
        assert name != "nan" or "finite" in str(err.value)
    with pytest.raises(ConfigError, match="cannot be read"):
        DeviceCalibration.load(tmp_path / "missing.yaml")


def test_the_node_refuses_to_start_with_a_damaged_calibration(ros, capfd, tmp_path):
    from conftest import PIPE, Harness
    from rclpy.lifecycle import TransitionCallbackReturn

    bad = tmp_path / "device.yaml"
    bad.write_text("format: cstomo_sensor device calibration 1\nsensor: cuboid_joint\nmodel_hash: x\n")
    capfd.readouterr()
    h = Harness(ros, dict(PIPE, input="topic", autostart=False, calibration_file=str(bad)), name="bad_cal")
    try:
        assert h.node.trigger_configure() == TransitionCallbackReturn.FAILURE
    finally:
        h.close()
    err = capfd.readouterr().err
    line = next(ln for ln in err.splitlines() if "refusing to start" in ln)
    assert str(bad) in line and "truncated" in line, err


HOLD = 4        # frames per held load in the bag (50 frames/s)
MOVING = 2      # frames while the load changes to the next one


def test_a_rosbag_with_load_changes_calibrates_as_the_csv_files(tmp_path, device):
    """A recording as a robot makes it: the node's stamped raw frames (50 frames/s) and a reference
    F/T sensor's wrenches (100/s, header stamps jittered by up to 2 ms, received 1-3 ms later), a load
    held for HOLD frames, then MOVING frames while it changes (the rubber already feels the next load,
    the reference sensor is between the two). Every held frame is paired with its own load, no frame
    of a change is paired at all, and the calibration equals the one from the CSV files of the held
    frames and their forces."""
    pytest.importorskip("rosbags")
    from geometry_msgs.msg import WrenchStamped
    from rclpy.serialization import serialize_message
    from rosbags.rosbag2 import Writer
    from rosbags.typesys import Stores, get_typestore

    from cstomo_sensor.frames_io import write_forces, write_frames
    from cstomo_sensor.ros.messages import TOPIC_TYPES, raw_voltages_msg
    from cstomo_sensor.tools.calibrate import main, read_bag

    tare, frames, forces, *_ = device
    frames, forces = frames[:10], forces[:10]
    held = np.repeat(np.float32(frames), HOLD, axis=0)  # as the bag carries them
    held_f = np.repeat(forces, HOLD, axis=0)
    write_frames(tmp_path / "ref.csv", tare)
    write_frames(tmp_path / "frames.csv", held)
    write_forces(tmp_path / "forces.csv", held_f)
    common = ["--mesh-size", str(MODEL_H), "--estimator", "linear"]
    assert main([*common, "--reference", str(tmp_path / "ref.csv"), "--frames", str(tmp_path / "frames.csv"),
                 "--forces", str(tmp_path / "forces.csv"), "--out", str(tmp_path / "csv.yaml")]) == 0
    # the device's unloaded reference beside the calibration, stamped with the time its frames were recorded
    from cstomo_sensor.force.reference.files import read_reference, saved_at

    written, _, n_written = read_reference(tmp_path / "csv.reference.csv")
    assert n_written == len(tare)
    np.testing.assert_allclose(written, tare.mean(axis=0), rtol=1e-6, atol=0)
    assert abs(saved_at(tmp_path / "csv.reference.csv") - (tmp_path / "ref.csv").stat().st_mtime) < 1.5
    rng = np.random.default_rng(4)
    store = get_typestore(getattr(Stores, "ROS2_KILTED", Stores.LATEST))
    t0 = 1_700_000_000 * 10**9
    period = 20_000_000
    with Writer(tmp_path / "bag", version=9) as w:
        cv = w.add_connection("/cstomo_sensor/raw_voltages", TOPIC_TYPES["raw_voltages"], typestore=store)
        cw = w.add_connection("/ft/wrench", "geometry_msgs/msg/WrenchStamped", typestore=store)
        k = 0

        def put(v, f_start, f_end):
            nonlocal k
            t = t0 + k * period
            w.write(cv, t + int(rng.uniform(1e6, 3e6)), serialize_message(raw_voltages_msg(v, t)))
            for half in (0, 1):  # two wrenches per frame; the force moves from f_start to f_end
                ts = t + half * period // 2 + int(rng.uniform(-2e6, 2e6))
                f = f_start + (f_end - f_start) * half
                m = WrenchStamped()
                m.header.stamp.sec, m.header.stamp.nanosec = divmod(ts, 10**9)
                m.wrench.force.x, m.wrench.force.y, m.wrench.force.z = (float(x) for x in f)
                w.write(cw, ts + int(rng.uniform(1e6, 3e6)), serialize_message(m))
            k += 1

        for v in tare:
            put(v, np.zeros(3), np.zeros(3))
        loads = [np.zeros(3)] + list(forces)
        for n, (v, f) in enumerate(zip(frames, forces)):
            for step in range(MOVING):  # the change from the previous load: the rubber is already at v
                a, b = loads[n] + (f - loads[n]) * step / MOVING, loads[n] + (f - loads[n]) * (step + 1) / MOVING
                put(v, a, b)
            for _ in range(HOLD):
                put(v, f, f)
    got_v, got_f, n_v, n_w = read_bag(tmp_path / "bag", "/cstomo_sensor/raw_voltages", "/ft/wrench", 0.005)
    assert n_v == len(tare) + len(frames) * (HOLD + MOVING) and n_w == 2 * n_v
    loaded = np.linalg.norm(got_f, axis=1) > 0
    assert loaded.sum() == len(held)  # every held frame, and not one frame of a change
    for v, f in zip(got_v[loaded], got_f[loaded]):  # each with its own load
        (i,) = np.flatnonzero((np.float32(frames) == np.float32(v)).all(axis=1))
        np.testing.assert_array_equal(f, forces[i])
    assert main([*common, "--bag", str(tmp_path / "bag"), "--wrench-topic", "/ft/wrench", "--stamp-tolerance",
                 "0.005", "--reference", str(tmp_path / "ref.csv"), "--out", str(tmp_path / "bag.yaml")]) == 0
    a, b = DeviceCalibration.load(tmp_path / "csv.yaml"), DeviceCalibration.load(tmp_path / "bag.yaml")
    assert a.fitted_on["loads"] == b.fitted_on["loads"]
    np.testing.assert_allclose(b.force_map, a.force_map, rtol=0, atol=1e-6)
    # the CSV frames carry 10 significant digits; the correction fits changes ~1e-3 of the voltages
    np.testing.assert_allclose(b.correction, a.correction, rtol=0, atol=1e-5 * np.abs(a.correction).max())
    assert (tmp_path / "csv.cv.csv").read_text().splitlines()[0].startswith("calibration,estimator,method")


def test_the_node_runs_with_a_calibration_and_its_diagnostics_name_it(ros, tmp_path, device):
    from conftest import PIPE, Harness, wait_for

    tare, frames, forces, *_ = device
    cfg = PipelineConfig(**{k: (tuple(v) if k == "grid" else v) for k, v in PIPE.items()})
    pipe = Pipeline.build(cfg)  # the node's own model settings (another grid: the same calibration hash)
    pipe.set_reference(*reference_of(tare))
    path = tmp_path / "device.yaml"
    calibrate(pipe, frames[:6], forces[:6]).save(path)
    h = Harness(ros, dict(PIPE, input="topic", calibration_file=str(path), tare_file=str(tmp_path / "t.csv")),
                name="calibrated")
    try:
        assert wait_for(lambda: h.state() == "active", 20.0)
        kv = {v.key: v.value for v in h.node.diagnostics().values}
        assert kv["calibration"] == str(path) and "leave one load out: angle" in kv["calibration_accuracy"], kv
        assert h.node.pipe.calibration is not None
    finally:
        h.close()


def test_a_one_frame_reference_takes_the_recordings_noise(tmp_path, device, capsys):
    """With a one-frame reference the noise comes from the recording's consecutive frames (loads held
    for 5 frames on a 40 dB board: the estimate says 40 dB, from the documented rms x 10^(-SNR/20));
    a recording too short to tell (fewer than 10 frame pairs) keeps the assumed 60 dB, and says so.
    (A file of distinct loads, one frame each, may pass for noise: on one truth mesh its 19 pairs said
    39 dB at 60 dB, on another they were refused; force/reference/noise_estimate.py's limit, docs/calibration.md.)"""
    from cstomo_sensor.frames_io import write_forces, write_frames
    from cstomo_sensor.tools.calibrate import main

    tare, frames, forces, *_ = device
    rng = np.random.default_rng(8)
    held = add_noise(np.repeat(frames[:10], 5, axis=0), tare[0], 40.0, rng)
    write_frames(tmp_path / "ref1.csv", tare[:1])
    common = ["--mesh-size", str(MODEL_H), "--estimator", "linear", "--reference", str(tmp_path / "ref1.csv")]
    for name, f, F in (("held", held, np.repeat(forces[:10], 5, axis=0)), ("short", frames[:6], forces[:6])):
        write_frames(tmp_path / f"{name}.csv", f)
        write_forces(tmp_path / f"{name}_forces.csv", F)
        assert main([*common, "--frames", str(tmp_path / f"{name}.csv"), "--forces", str(tmp_path / f"{name}_forces.csv"),
                     "--out", str(tmp_path / f"{name}.yaml")]) == 0
    out = capsys.readouterr().out
    said = [line for line in out.splitlines() if line.startswith("noise: estimated from")]
    assert len(said) == 1, out
    db = float(said[0].split("(")[1].split(" dB")[0])
    assert 39.0 < db < 41.0, out
    assert "noise: assumed 60 dB" in out, out


def test_a_first_start_under_a_load_reads_it_from_the_calibrations_reference(ros, tmp_path, device):
    """A node started for the first time (no saved tare) on a joint already loaded: with the device's
    calibration (its unloaded reference beside it, as `cstomo calibrate` writes it) it starts from that
    reference as from a saved tare and reads the load; no tare is taken. Without it the first tare is
    taken under the load and the load reads as zero (the contrast that makes this test able to fail)."""
    import time

    from conftest import PIPE, Harness, wait_for
    from geometry_msgs.msg import WrenchStamped
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import Image

    from cstomo_sensor.force.reference.calibration import reference_path_of
    from cstomo_sensor.force.reference.files import write_reference
    from cstomo_sensor.ros.messages import raw_voltages_msg

    tare, frames, forces, held, held_forces = device
    cfg = PipelineConfig(**{k: (tuple(v) if k == "grid" else v) for k, v in PIPE.items()})
    pipe = Pipeline.build(cfg)
    ref, noise = reference_of(tare)
    pipe.set_reference(ref, noise, len(tare))
    path = tmp_path / "device.yaml"
    calibrate(pipe, frames, forces).save(path)
    k = int(np.argmax(np.linalg.norm(held_forces, axis=1)))  # the largest held-out load, from the first frame
    rng = np.random.default_rng(5)
    loaded = add_noise(np.repeat(held[k][None], 80, 0), tare.mean(axis=0), 60.0, rng)

    def first_start(name):
        params = dict(PIPE, input="topic", calibration_file=str(path), tare_file=str(tmp_path / f"{name}.csv"),
                      tare_frames=10, qos_reliability="reliable", qos_depth=100, stale_timeout=5.0)
        h = Harness(ros, params, name=name)
        try:
            wrench = h.record(f"/{name}/wrench", WrenchStamped)
            pub = h.probe.create_publisher(Image, f"/{name}/raw_voltages_in",
                                           QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE))
            assert wait_for(lambda: h.state() == "active" and pub.get_subscription_count() == 1, 30.0)
            for v in loaded:
                pub.publish(raw_voltages_msg(v))
                time.sleep(0.01)
            assert wait_for(lambda: len(wrench) >= 40, 15.0), len(wrench)
            f = np.array([[m.wrench.force.x, m.wrench.force.y, m.wrench.force.z] for _, m in wrench[-30:]])
            return f.mean(axis=0), h.node.stream.tares.taken, h.node.reference_source
        finally:
            h.close()

    write_reference(reference_path_of(path), ref, noise, frames=len(tare),
                    comment=f"unloaded reference of {path.name}: {time.strftime('%Y-%m-%dT%H:%M:%S%z')}")
    read, taken, source = first_start("calref")
    truth = held_forces[k]
    assert "the calibration's unloaded reference" in source and not taken, (source, taken)
    assert np.linalg.norm(read - truth) < 0.15 * np.linalg.norm(truth), (read, truth)
    reference_path_of(path).unlink()  # the same start without it: the first tare is taken under the load
    read, taken, source = first_start("noref")
    assert taken and np.linalg.norm(read) < 0.2 * np.linalg.norm(truth), (read, truth, taken, source)


def test_a_tare_at_start_is_checked_against_the_calibrations_reference(tmp_path, device):
    """``tare_on_start: true`` with the device's calibration and its unloaded reference beside it (as
    `cstomo calibrate` writes them), no saved tare: the stream starts from that reference and the tare
    on the first frames is judged against it (FrameStream.init_reference, the offline stream a node
    runs). On a joint loaded from the first frame the tare is refused as carrying the load, the
    calibration's reference stays and the load is read; on the unloaded joint the same start takes the
    tare. Without the reference file the loaded tare is taken (nothing to compare it with): the
    reference is what refuses it. A tare saved by an earlier start (the tare file) refuses it the same way."""
    import time

    from conftest import PIPE

    from cstomo_sensor.force.reference.calibration import reference_path_of
    from cstomo_sensor.force.reference.files import write_reference
    from cstomo_sensor.frame_path.config import StreamConfig
    from cstomo_sensor.frame_path.stream import FrameStream

    tare, frames, forces, held, held_forces = device
    cfg = {k: (tuple(v) if k == "grid" else v) for k, v in PIPE.items()}
    pipe = Pipeline.build(PipelineConfig(**cfg))
    ref, noise = reference_of(tare)
    pipe.set_reference(ref, noise, len(tare))
    path = tmp_path / "device.yaml"
    calibrate(pipe, frames, forces).save(path)
    write_reference(reference_path_of(path), ref, noise, frames=len(tare),
                    comment=f"unloaded reference of {path.name}: {time.strftime('%Y-%m-%dT%H:%M:%S%z')}")
    k = int(np.argmax(np.linalg.norm(held_forces, axis=1)))  # the largest held-out load, from the first frame
    truth = held_forces[k]
    rng = np.random.default_rng(6)
    loaded = add_noise(np.repeat(held[k][None], 40, 0), ref, 60.0, rng)
    unloaded = add_noise(np.repeat(ref[None], 40, 0), ref, 60.0, rng)  # the device at rest, new noise

    def start(name, frames_in):
        """(mean force of the last 20 frames (nan: none), tare taken, tare refused, reference source)."""
        stream = FrameStream(Pipeline.build(PipelineConfig(**cfg, calibration_file=str(path))),
                             StreamConfig.offline(tare_frames=10), tare_file=tmp_path / f"{name}.csv")
        why = stream.init_reference(tare_on_start=True)
        assert why == "" or not reference_path_of(path).is_file(), why
        out = [stream.push(v, stamp_ns=int(1e9 * (1.0 + i / 100.0))) for i, v in enumerate(frames_in)]
        assert not stream.tares.pending
        f = np.array([o.result.force for o in out[-20:] if o is not None and o.result.valid])
        stream.close()
        return (f.mean(axis=0) if len(f) else np.full(3, np.nan)), stream.tares.taken, stream.tares.refused, \
            stream.tares.source

    read, taken, refused, source = start("loaded", loaded)
    assert not taken and "carries a load" in refused, (taken, refused)
    assert "the calibration's unloaded reference" in source, source
    assert np.linalg.norm(read - truth) < 0.15 * np.linalg.norm(truth), (read, truth)
    read, taken, refused, source = start("unloaded", unloaded)
    assert taken and not refused and source.startswith("tare"), (taken, refused, source)
    assert np.linalg.norm(read) < 0.5, read
    reference_path_of(path).unlink()  # the loaded start without the reference: the tare is taken under the load
    read, taken, refused, source = start("noref", loaded)
    assert taken and not refused and np.linalg.norm(read) < 0.2 * np.linalg.norm(truth), (read, taken, refused)
    # a tare saved by an earlier run of this device plays the reference's part: the loaded start is refused
    write_reference(tmp_path / "saved.csv", ref, noise, frames=len(tare), comment="tare taken at an earlier start")
    read, taken, refused, source = start("saved", loaded)
    assert not taken and "carries a load" in refused, (taken, refused)
    assert source.startswith("saved tare "), source
    assert np.linalg.norm(read - truth) < 0.15 * np.linalg.norm(truth), (read, truth)
