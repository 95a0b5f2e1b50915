"""The plausibility gate (cstomo_sensor.frame_path.pipeline module docstring): frames no load in the rated
range can explain (all-zero, scaled x10, huge finite values) are rejected, honest loads up to 40 N on a
poor 40 dB board never are; ``cstomo estimate`` and the forces file mark rejected frames."""
from __future__ import annotations

import os

import numpy as np
import pytest
from conftest import PIPE

from cstomo_sensor.frame_path.config import PipelineConfig
from cstomo_sensor.frame_path.pipeline import Pipeline

DATA = os.path.join(os.path.dirname(os.path.abspath(__file__)), "data")
CONFIG = PipelineConfig(**{k: (tuple(v) if k == "grid" else v) for k, v in PIPE.items()})


@pytest.fixture(scope="module")
def pipe():
    return Pipeline.build(CONFIG)


@pytest.fixture(scope="module")
def bag_frames():
    """The committed bag's frames (honest simulation at 60 dB): 0..19 unloaded, 20..69 at 20 N."""
    pytest.importorskip("rosbags")
    from rclpy.serialization import deserialize_message
    from rosbags.rosbag2 import Reader
    from std_msgs.msg import Float32MultiArray

    with Reader(os.path.join(DATA, "raw_voltages_bag")) as r:
        return np.array([deserialize_message(bytes(raw), Float32MultiArray).data for _, _, raw in r.messages()],
                        dtype=float)


@pytest.mark.parametrize("kind", ["zeros", "x10", "1e30", "one channel 1e30", "1e308"])
def test_frames_no_rated_load_can_cause_are_invalid(pipe, bag_frames, kind):
    ref = bag_frames[:10].mean(axis=0)
    pipe.set_reference(ref)
    loaded = bag_frames[40]
    assert pipe.process(loaded).valid  # a 20 N frame passes
    frame = {"zeros": np.zeros(208), "x10": 10 * loaded, "1e30": np.full(208, 1e30),
             "one channel 1e30": np.where(np.arange(208) == 17, 1e30, loaded), "1e308": np.full(208, 1e308)}[kind]
    with np.errstate(all="raise"):  # no overflow warning on the way
        r = pipe.process(frame)
    assert not r.valid and r.reason
    assert np.isnan(r.force).all() and np.isnan(r.magnitude) and r.field is None


def test_one_channel_far_out_and_max_force(pipe, bag_frames):
    ref = bag_frames[:10].mean(axis=0)
    pipe.set_reference(ref)
    v = bag_frames[40].copy()
    v[50] = ref[50] * 2.5  # one value off by 150 % (a flipped leading digit): the norm alone lets it pass
    r = pipe.process(v)
    assert not r.valid and "channel 50" in r.reason
    low = Pipeline(pipe.geometry, pipe.model, pipe.estimator, max_force=10.0)
    low.set_reference(ref)
    r = low.process(bag_frames[40])  # 20 N
    assert not r.valid and "max_force" in r.reason
    assert low.process(bag_frames[5]).valid  # unloaded


@pytest.mark.slow
def test_honest_loads_up_to_40_n_at_40_db_stay_valid(pipe, cuboid_truth):
    """Independent finer mesh, mismatched electrodes, 40 dB noise on the frame and on a single-frame
    reference (the worst tare): every load of 5..40 N at elevations 15..90 deg is valid."""
    from cstomo_sensor.angles import force_from_angles
    from cstomo_sensor.model.simulate import Load, add_noise

    rng = np.random.default_rng(40)
    truth = cuboid_truth
    pipe.set_reference(add_noise(truth.reference, truth.reference, 40, rng))
    loads = [(40, 15, 0), (40, 20, 200), (40, 32, 290), (40, 45, 90), (40, 60, 137), (40, 90, 0), (22, 25, 45), (5, 70, 300)]
    worst = 0.0
    for mag, el, az in loads:
        v0 = truth.voltages(Load("socket", force=tuple(force_from_angles(mag, np.radians(el), np.radians(az)))))
        for _ in range(5):
            r = pipe.process(add_noise(v0, truth.reference, 40, rng), with_field=False)
            assert r.valid, (mag, el, az, r.reason)
            worst = max(worst, r.magnitude)
    assert worst < pipe.max_force


def test_cli_estimate_marks_an_all_zero_frame_invalid(tmp_path, bag_frames):
    from cstomo_sensor.frames_io import read_forces, write_frames
    from cstomo_sensor.tools.cli import main

    write_frames(tmp_path / "ref.csv", bag_frames[:10].mean(axis=0))
    write_frames(tmp_path / "frames.csv", np.vstack([bag_frames[40], np.zeros(208), bag_frames[80]]))
    args = ["estimate", "--reference", str(tmp_path / "ref.csv"), "--frames", str(tmp_path / "frames.csv"),
            "--out", str(tmp_path / "forces.csv"), "--mesh-size", str(PIPE["mesh_size"]),
            "--grid", *map(str, PIPE["grid"])]
    assert main(args) == 0
    lines = (tmp_path / "forces.csv").read_text().splitlines()
    assert lines[0] == "frame,fx,fy,fz,magnitude,elevation_deg,azimuth_deg,valid,consistency,foreign_load,sigma_n"
    assert lines[2] == "1,,,,,,,0,,,"  # frame, six empty force fields, valid, no statistic, no sigma
    assert lines[1].split(",")[7] == "1" and lines[3].split(",")[7] == "1"
    forces, valid = read_forces(tmp_path / "forces.csv", with_valid=True)
    assert valid.tolist() == [True, False, True]
    assert np.isnan(forces[1]).all() and np.isfinite(forces[[0, 2]]).all()
    assert 15 < np.linalg.norm(forces[0]) < 25  # the 20 N frame


def test_forces_file_round_trip_and_unknown_columns(tmp_path):
    from cstomo_sensor.frames_io import read_forces, write_forces

    f = np.array([[1.0, 2.0, -3.0], [np.nan, np.nan, np.nan]])
    write_forces(tmp_path / "a.csv", f, valid=[True, False])
    got, valid = read_forces(tmp_path / "a.csv", with_valid=True)
    np.testing.assert_array_equal(got[0], f[0]) and np.testing.assert_array_equal(valid, [True, False])
    (tmp_path / "b.csv").write_text("frame,fx,fy,fz,magnitude,elevation_deg,azimuth_deg,consistency,valid,extra\n"
                                    "0,1,2,3,3.7,0.1,0.2,0.5,1,x\n1,,,,,,,,0,\n")
    got, valid = read_forces(tmp_path / "b.csv", with_valid=True)
    np.testing.assert_array_equal(got[0], [1, 2, 3]) and np.isnan(got[1]).all()
    assert valid.tolist() == [True, False]
    write_forces(tmp_path / "c.csv", f[:1])  # no valid given: the plain seven columns
    assert (tmp_path / "c.csv").read_text().splitlines()[0] == "frame,fx,fy,fz,magnitude,elevation_deg,azimuth_deg"


def test_a_flapping_gate_logs_a_run_of_implausible_frames_at_most_every_few_seconds(caplog):
    """Frames that alternate between plausible and implausible used to log two lines per flip; runs that
    start within LOG_EVERY s of a logged one are counted, not logged, and said with the next logged run."""
    import logging
    from types import SimpleNamespace

    from cstomo_sensor.frame_path import health as health_mod

    h = health_mod.Health(0.0)
    bad, good = SimpleNamespace(valid=False, reason="too large"), SimpleNamespace(valid=True, reason="")
    with caplog.at_level(logging.WARNING, logger="cstomo_sensor.frame_path.health"):
        for _ in range(200):
            h.plausible(bad)
            h.plausible(good)
    lines = [r.getMessage() for r in caplog.records]
    assert len(lines) == 2 and lines[0].startswith("implausible frames") and "again after 1" in lines[1], lines
    assert h.counts.implausible == 200  # every frame counted (the diagnostics)
    h._run_said_at -= health_mod.LOG_EVERY  # LOG_EVERY s later: the next run is said, with the unsaid ones
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="cstomo_sensor.frame_path.health"):
        h.plausible(bad)
    assert "199 shorter runs before it not logged" in caplog.records[0].getMessage(), caplog.records


def test_cli_estimate_names_a_few_implausible_frames_and_counts_the_rest(tmp_path, bag_frames, capsys):
    """Before: one stderr line per implausible frame (a recording with a bad cable: thousands)."""
    from cstomo_sensor.frames_io import write_frames
    from cstomo_sensor.tools.cli import main

    write_frames(tmp_path / "ref.csv", bag_frames[:10].mean(axis=0))
    write_frames(tmp_path / "frames.csv", np.vstack([bag_frames[40], np.zeros((7, 208))]))
    args = ["estimate", "--reference", str(tmp_path / "ref.csv"), "--frames", str(tmp_path / "frames.csv"),
            "--out", str(tmp_path / "forces.csv"), "--mesh-size", str(PIPE["mesh_size"]),
            "--grid", *map(str, PIPE["grid"])]
    assert main(args) == 0
    err = [ln for ln in capsys.readouterr().err.splitlines() if "implausible" in ln]
    assert [ln.split(":")[0] for ln in err[:3]] == ["frame 1", "frame 2", "frame 3"], err
    assert err[3] == f"... and 4 more implausible frames (valid 0 in {tmp_path / 'forces.csv'})" and len(err) == 4, err
