"""Two sensors from one list, run as a launch runs them: the plan of a two-sensor list
(:func:`cstomo_sensor.tools.launching.launch_plan`) started with real processes, its simulated boards
(``cstomo board-sim``) and two ``cstomo_sensor_node`` in their namespaces with their parameters (a
parameter file keyed by the node's full name, as launch_ros writes one), and a probe with real rclpy:
each publishes its wrench in its own namespace, in its own frame, and saves its tare in its own file.
(launch itself does not install from the package index; test_launch.py checks the launch file's lines.)
"""
from __future__ import annotations

import os
import shutil
import subprocess
import time
from pathlib import Path

import pytest
import yaml
from conftest import PIPE, prepare_board, wait_for

rclpy = pytest.importorskip("rclpy")

pytestmark = pytest.mark.slow  # two nodes and boards as processes (~17 s)

ROOT = Path(__file__).resolve().parent.parent
CONFIG = ROOT / "config" / "cstomo_sensor.yaml"


def _stop(procs: list[subprocess.Popen]) -> None:
    from cstomo_sensor.tools.common import interrupt

    interrupt(procs, timeout=10.0)  # nodes first, then their boards (the list's order)


def test_two_sensors_of_a_list_publish_in_their_namespaces_frames_and_tare_files(tmp_path, warm_model):
    from geometry_msgs.msg import WrenchStamped
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.qos import QoSProfile, ReliabilityPolicy

    from cstomo_sensor.tools.common import executable
    from cstomo_sensor.tools.launching import launch_plan

    small = {k: v for k, v in PIPE.items() if k != "sensor"}  # the suite's small model (warm_model built it)
    listing = tmp_path / "sensors.yaml"
    listing.write_text(yaml.safe_dump({"sensors": [
        {"namespace": "left_knee", "sim": True, "sensor": "cuboid_joint", "frame_id": "left_knee_socket",
         "parent_frame": "left_shank", "pose": {"z": 0.12}, "tare_on_start": True,
         "parameters": dict(small, stress_field_every=0)},
        {"namespace": "right_knee", "sim": True, "sensor": "cuboid_joint", "frame_id": "right_knee_socket",
         "parent_frame": "right_shank", "pose": {"z": 0.12, "yaw": 3.14159}, "tare_on_start": True,
         "parameters": dict(small, stress_field_every=0)}]}))
    plan = launch_plan({"config": str(CONFIG), "sensors": str(listing), "sim": "false"})
    left, right = plan.sensors
    env = dict(os.environ, OPENBLAS_NUM_THREADS="1")
    boards, nodes, logs = [], [], []
    ctx = rclpy.Context()
    rclpy.init(context=ctx)
    probe = rclpy.create_node("launch_probe", context=ctx)
    try:
        for sensor in plan.sensors:  # each board's frames computed here first, into the cache the boards read
            prepare_board(sensor.board)
        for i, sensor in enumerate(plan.sensors):
            log = open(tmp_path / f"board{i}.log", "w+")
            logs.append(log)
            boards.append(subprocess.Popen(sensor.board, stdout=subprocess.PIPE, stderr=log, text=True, env=env,
                                           start_new_session=True))
        for i, sensor in enumerate(plan.sensors):  # beside the boards, as a launch starts them: a node opens its
            # board's pty once the board shows it
            params = tmp_path / f"params{i}.yaml"  # as launch_ros hands parameters=[config, overrides] to a node
            params.write_text(yaml.safe_dump({sensor.node: {"ros__parameters": sensor.overrides}}))
            log = open(tmp_path / f"node{i}.log", "w+")
            logs.append(log)
            nodes.append(subprocess.Popen(
                [executable("cstomo_sensor_node"), "--ros-args", "-r", f"__ns:=/{sensor.namespace}",
                 "-r", "__node:=cstomo_sensor", "--params-file", sensor.config, "--params-file", str(params),
                 "--log-level", "warn"], stdout=log, stderr=subprocess.STDOUT, env=env, start_new_session=True))
        for b in boards:  # each reads its loads' frames from the cache (prepare_board), then shows its device
            line = b.stdout.readline()
            assert line.startswith("device:"), line + Path(logs[boards.index(b)].name).read_text()
        got: dict[str, list] = {s.node: [] for s in plan.sensors}
        qos = QoSProfile(depth=50, reliability=ReliabilityPolicy.RELIABLE)
        for sensor in plan.sensors:
            probe.create_subscription(WrenchStamped, sensor.topic("wrench"), got[sensor.node].append, qos)
        ex = SingleThreadedExecutor(context=ctx)
        ex.add_node(probe)
        deadline = time.monotonic() + 180
        while min(len(v) for v in got.values()) < 5 and time.monotonic() < deadline:
            assert all(p.poll() is None for p in nodes + boards), [Path(f.name).read_text() for f in logs]
            ex.spin_once(timeout_sec=0.2)
        assert all(got.values()), ({k: len(v) for k, v in got.items()}, [Path(f.name).read_text() for f in logs])
        # the graph's node names come by discovery of their own, after the data may have (seen: wrenches of
        # both, the names not yet): wait for them as for the wrenches
        expected = {("cstomo_sensor", "/left_knee"), ("cstomo_sensor", "/right_knee")}
        assert wait_for(lambda: expected <= set(probe.get_node_names_and_namespaces()), 20.0), \
            probe.get_node_names_and_namespaces()
        # each in its own frame, never the other's
        assert {m.header.frame_id for m in got[left.node]} == {"left_knee_socket"}
        assert {m.header.frame_id for m in got[right.node]} == {"right_knee_socket"}
        # each saved its tare in its own file
        tares = [Path(s.overrides["tare_file"]) for s in plan.sensors]
        assert tares[0] != tares[1] and tares[0].parent != tares[1].parent
        assert wait_for(lambda: all(t.is_file() for t in tares), 10.0), tares
        ex.shutdown()
    finally:
        probe.destroy_node()
        rclpy.try_shutdown(context=ctx)
        _stop(nodes + boards)
        for f in logs:
            f.close()
        shutil.rmtree(plan.work, ignore_errors=True)
    for i, p in enumerate(nodes):
        out = (tmp_path / f"node{i}.log").read_text()
        assert p.returncode == 0 and "Traceback" not in out, out
