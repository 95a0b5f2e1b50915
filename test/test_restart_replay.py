"""Restarts replay (issue 34 item 4): the node restarted from a saved tare 8 hours old (its restart path:
the tare's age widens the slow states, force/slow_states/drift.py ``widen``), fed the committed bag's frames in topic
mode, publishes the forces and sigmas that ``cstomo replay`` with that tare file (its age from the file's
stamp against the bag's first frame) writes, and that ``cstomo estimate --reference-age`` (the node's age)
reads from the same frames; every topic equal. Without the age, estimate reads other sigmas: the test tells
them apart."""
from __future__ import annotations

import time

import numpy as np
import pytest
from conftest import PIPE, Harness, wait_for

rclpy = pytest.importorskip("rclpy")
pytest.importorskip("rosbags")

AGE_H = 8.0
TARE = 10  # the bag's first frames, unloaded: the saved tare's


@pytest.fixture(scope="module")
def config():
    from cstomo_sensor.frame_path.config import PipelineConfig

    return PipelineConfig(**{**PIPE, "grid": tuple(PIPE["grid"]), "estimator": "model"})


def _saved_tare(path, frames, saved: float) -> None:
    """The tare file the node writes (force/reference/tare_transaction.py): the mean of ``frames``, their noise beside it, the
    time ``saved`` (s since the epoch) ending its comment."""
    from cstomo_sensor.force.reference.files import write_reference

    stamp = time.strftime("%Y-%m-%dT%H:%M:%S%z", time.localtime(saved))
    write_reference(path, frames.mean(axis=0), frames.std(axis=0, ddof=1), frames=len(frames),
                    comment=f"cstomo_sensor tare of 'cuboid_joint': mean of {len(frames)} frames, {stamp}")


#: The node's topics but the stress fields (replay writes none unless asked; test_replay.py compares them).
TOPICS = ("wrench", "wrench_sigma", "wrench_filtered", "force_magnitude", "force_elevation", "force_azimuth", "consistency")


def _numbers(m) -> list[float]:
    if hasattr(m, "wrench"):
        return [m.wrench.force.x, m.wrench.force.y, m.wrench.force.z, m.wrench.torque.x, m.wrench.torque.y,
                m.wrench.torque.z]
    return [m.vector.x, m.vector.y, m.vector.z] if hasattr(m, "vector") else [m.data]


def _forces(path) -> dict:
    """The forces file's (docs/formats.md#forces-file) forces (n, 3) and sigma_n (n,)."""
    import csv

    with open(path) as f:
        rows = list(csv.DictReader(line for line in f if not line.startswith("#")))
    return {"force": np.array([[float(r[k]) for k in ("fx", "fy", "fz")] for r in rows]),
            "sigma_n": np.array([float(r["sigma_n"]) for r in rows])}


@pytest.mark.slow
def test_the_node_restart_is_what_replay_and_estimate_reference_age_read(tmp_path, config, capsys):
    from geometry_msgs.msg import Vector3Stamped, WrenchStamped
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import Image
    from std_msgs.msg import Float64
    from test_replay import BAG, _write_raw_bag, read_bag

    from cstomo_sensor.force.reference.files import saved_at
    from cstomo_sensor.frame_path.outputs import FLOAT64, OUTPUTS, VECTOR, WRENCH
    from cstomo_sensor.frames_io import write_frames
    from cstomo_sensor.ros.messages import raw_voltages_msg
    from cstomo_sensor.tools.cli import main as cli
    from cstomo_sensor.tools.replay import replay

    recorded = read_bag(BAG)["/cstomo_sensor/raw_voltages"]
    frames = np.array([m.data for _, m in recorded], np.float32)
    bag_t = np.array([t for t, _ in recorded], np.int64) - recorded[0][0]
    saved = float(int(time.time() - AGE_H * 3600))
    tare = tmp_path / "tare.csv"
    _saved_tare(tare, frames[:TARE].astype(float), saved)
    assert saved_at(tare) == saved
    # and a direction the device learned (force/slow_states/learned.py) beside it: each reader starts with it
    from cstomo_sensor.force.slow_states.learned import Directions, write_directions
    write_directions(tare, Directions(np.random.default_rng(4).normal(0.0, 0.01, (1, frames.shape[1])), np.array([0.5])))
    ctx = rclpy.Context()
    rclpy.init(context=ctx)
    params = dict(PIPE, estimator="model", input="topic", tare_on_start=False, tare_file=str(tare), creep_per_decade=0.0,
                  qos_reliability="reliable", qos_depth=1000, stale_timeout=2.0)
    h = Harness(ctx, params, name="cstomo_restart")
    types = {WRENCH: WrenchStamped, VECTOR: Vector3Stamped, FLOAT64: Float64}
    try:
        got = {t: h.record(f"/cstomo_restart/{t}", types[OUTPUTS[t].type]) for t in TOPICS}
        wr, sg = got["wrench"], got["wrench_sigma"]
        pub = h.probe.create_publisher(Image, "/cstomo_restart/raw_voltages_in",
                                       QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE))
        assert wait_for(lambda: h.state() == "active" and pub.get_subscription_count() == 1
                        and h.probe.count_publishers("/cstomo_restart/wrench_sigma"), 30.0)
        age = h.node.stream.slow.age_s
        assert age == pytest.approx(AGE_H * 3600, abs=60)  # the node's restart: its saved tare, 8 h old
        assert len(h.node.stream.slow.directions) == 1 and h.node.stream.slow.drift.m == 9  # ... and its learned direction
        # the frames stamped as measured after the restart, the first at the moment the node took the age at
        t0 = int(round((saved + age) * 1e9))
        inputs = [(t0 + int(dt), raw_voltages_msg(f, t0 + int(dt))) for dt, f in zip(bag_t, frames)]
        start = time.monotonic()
        for t_ns, msg in inputs:
            delay = (t_ns - t0) * 1e-9 - (time.monotonic() - start)
            if delay > 0:
                time.sleep(delay)
            pub.publish(msg)
        assert wait_for(lambda: len(wr) >= len(inputs) and len(sg) >= len(inputs), 30.0), (len(wr), len(sg))
    finally:
        h.close()
        rclpy.try_shutdown(context=ctx)
    node_f = np.array([[m.wrench.force.x, m.wrench.force.y, m.wrench.force.z] for _, m in wr])
    node_s = np.array([[m.vector.x, m.vector.y, m.vector.z] for _, m in sg])
    node_sn = np.linalg.norm(node_s, axis=1)
    # replay with the tare file: its age from the file's stamp against the bag's first frame
    _write_raw_bag(tmp_path / "in", inputs)
    replay(tmp_path / "in", tmp_path / "out", config, reference=tare, creep_per_decade=0.0)
    out = read_bag(tmp_path / "out")
    rep_f = np.array([[m.wrench.force.x, m.wrench.force.y, m.wrench.force.z] for _, m in out["/cstomo_sensor/wrench"]])
    # the forces to a thousandth of their 1-sigma (the ages differ by the clock's rounding: nanoseconds); every
    # topic equal to a millionth, stamps exactly
    tol = 1e-3 * node_sn[:, None]
    assert rep_f.shape == node_f.shape and np.all(np.abs(rep_f - node_f) <= tol)
    for t in TOPICS:
        n, r = got[t], out[f"/cstomo_sensor/{t}"]
        assert len(n) == len(r) == len(inputs), t
        np.testing.assert_allclose([_numbers(m) for _, m in r], [_numbers(m) for _, m in n], rtol=1e-6, atol=1e-9,
                                   err_msg=t)
        if hasattr(n[0][1], "header"):
            assert [m.header.stamp for _, m in n] == [m.header.stamp for _, m in r], t
    # estimate --reference-age: the node's age, the frames in a file at the bag's rate
    write_frames(tmp_path / "frames.csv", frames.astype(float))
    common = ["estimate", "--reference", str(tare), "--frames", str(tmp_path / "frames.csv"), "--rate", "50",
              "--creep-per-decade", "0", "--mesh-size", str(PIPE["mesh_size"]), "--grid", *map(str, PIPE["grid"]),
              "--estimator", "model"]
    assert cli([*common, "--out", str(tmp_path / "est.csv"), "--reference-age", repr(age)]) == 0
    assert cli([*common, "--out", str(tmp_path / "fresh.csv")]) == 0
    capsys.readouterr()
    est, fresh = _forces(tmp_path / "est.csv"), _forces(tmp_path / "fresh.csv")
    # the frames file keeps 10 significant digits of the float32 volts, the forces file 6 of sigma_n
    assert np.all(np.abs(est["force"] - node_f) <= tol)
    np.testing.assert_allclose(est["sigma_n"], node_sn, rtol=1e-5)
    # a tare just taken is another device's state: its sigmas are not the restart's
    print(f"sigma_n of the first frames: restart {node_sn[:3].round(3)} N, a tare just taken "
          f"{fresh['sigma_n'][:3].round(3)} N")
    assert np.max(np.abs(fresh["sigma_n"] / node_sn - 1)) > 0.05
