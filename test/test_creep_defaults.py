"""The defaults agree (issue 25 items 3 and 8): the simulated board's default rubber creeps as the
node's default compensation assumes (one declaration, settings.py TYPICAL_CREEP_PER_DECADE),
so the node with every default reads a held load of ``cstomo board-sim`` with every default
constant; ``cstomo demo`` judges each line at its wrench's frame time; board-sim's sensor and rate
default to the pipeline's sensor and the launch's rate."""
from __future__ import annotations

import threading
import time

import numpy as np
import pytest

from cstomo_sensor.settings import TYPICAL_CREEP_PER_DECADE


def test_one_declaration_of_the_typical_creep_and_of_the_simulated_boards_rate_and_sensor(tmp_path):
    from cstomo_sensor.board.sim import DEFAULT_RATE_HZ
    from cstomo_sensor.force.slow_states.creep import DEFAULT_CREEP
    from cstomo_sensor.frame_path.config import PipelineConfig, StreamConfig
    from cstomo_sensor.model.timeline import held_load_creep
    from cstomo_sensor.tools import board_sim
    from cstomo_sensor.tools.launching import _sim_board

    a = board_sim.parser().parse_args(["--load-script", "x.csv"])
    assert a.creep == TYPICAL_CREEP_PER_DECADE == DEFAULT_CREEP == StreamConfig().creep_per_decade
    assert held_load_creep().creep == TYPICAL_CREEP_PER_DECADE
    assert a.sensor == PipelineConfig().sensor and a.rate == DEFAULT_RATE_HZ
    cmd, _, _ = _sim_board(tmp_path, "cuboid_joint", None)
    assert float(cmd[cmd.index("--rate") + 1]) == DEFAULT_RATE_HZ and "--creep" not in cmd


@pytest.mark.parametrize("c", ["-0.01", "1", "nan"])
def test_a_creep_that_is_no_fraction_per_decade_is_refused_naming_the_option(tmp_path, capsys, c):
    from cstomo_sensor.tools import board_sim

    script = tmp_path / "load.csv"
    script.write_text("time,fx,fy,fz\n0,0,0,0\n")
    assert board_sim.main(["--load-script", str(script), "--creep", c, "--link", str(tmp_path / "b")]) == 2
    assert "--creep" in capsys.readouterr().err


def test_the_demo_judges_a_line_against_the_load_at_its_frames_time():
    """At a load change (20 N down at 3 s, then 20 N at 30 deg at 5 s): the wrench of a frame measured
    just after the change is judged against the new load (the demo's own clock, which lags the
    script, would still be before it), one just before against the old; a line counts in the
    summary only after 0.6 s of its load."""
    from cstomo_sensor.tools.demo import judge

    times = np.array([0.0, 3.0, 5.0])
    forces = np.array([[0, 0, 0], [0, 0, -20.0], [17.32, 0, -10.0]])
    labels = ["unloaded", "down", "tilted"]
    est = np.array([17.0, 0.0, -10.2])  # the estimate of the tilted load
    line, counted = judge(times, forces, labels, 5.02, est)
    assert "tilted" in line and counted is None  # judged against the new load; not settled yet
    assert float(line.split()[-1]) < 2.0, line  # the angle error, degrees
    line, counted = judge(times, forces, labels, 4.99, np.array([0.1, 0.0, -20.1]))
    assert "down" in line and counted is not None and counted[0] < 1.0 and counted[1] < 0.01
    line, counted = judge(times, forces, labels, 5.7, est)
    assert "tilted" in line and counted is not None and counted[0] < 2.0
    line, counted = judge(times, forces, labels, 1.0, np.zeros(3))
    assert "unloaded" in line and counted is None  # a zero load has no angle


@pytest.mark.slow
def test_the_node_with_every_default_reads_a_held_load_of_the_default_simulated_board(ros, tmp_path):
    """``cstomo_sensor_node`` with every default (but its port, a tare file in tmp and a tare at start)
    on ``cstomo board-sim`` with every default (its rubber creeps at the typical 4 % per decade): 20 N
    straight down from 3 s, held; over 12-13 s (9-10 s of hold, 2 decades of creep: +8 % of strain
    uncompensated) the median force reads within 2 % of 20 N, and already within 2 % at 5-6 s. (It was read at 19-20
    s of hold, +9 % uncompensated: the bound is a quarter of the creep either way, for 10 s less of real time.)"""
    from geometry_msgs.msg import WrenchStamped
    from rclpy.executors import SingleThreadedExecutor

    from cstomo_sensor.tools.common import NodeWithBoard

    script = tmp_path / "load.csv"
    # unloaded 3 s: the node reaches the board up to 2 s after it appears and tares on its first frames
    script.write_text("time,fx,fy,fz\n0,0,0,0\n3,0,0,-20\n")
    got: list[tuple[float, float]] = []
    ros_node = None
    executor = SingleThreadedExecutor(context=ros)
    try:
        import rclpy

        ros_node = rclpy.create_node("creep_defaults_probe", context=ros)
        ros_node.create_subscription(
            WrenchStamped, "/cstomo_sensor/wrench",
            lambda m: got.append((m.header.stamp.sec + 1e-9 * m.header.stamp.nanosec,
                                  float(np.linalg.norm([m.wrench.force.x, m.wrench.force.y, m.wrench.force.z])))), 50)
        executor.add_node(ros_node)
        spinner = threading.Thread(target=executor.spin, daemon=True)
        spinner.start()
        params = {"tare_file": tmp_path / "tare.csv", "tare_on_start": "true"}
        with open(tmp_path / "board.log", "w") as err, open(tmp_path / "node.log", "w") as out, \
                NodeWithBoard(tmp_path / "board", params, ["--load-script", str(script)], node_out=out,
                              board_err=err) as node:
            node.start()
            t0 = node.wait_streaming()
            assert t0 is not None
            deadline = time.monotonic() + 60
            while not any(s - t0 > 13.0 for s, _ in got):
                assert time.monotonic() < deadline and node.node.poll() is None, \
                    (tmp_path / "node.log").read_text() + (tmp_path / "board.log").read_text()
                time.sleep(0.2)
    finally:
        executor.shutdown(timeout_sec=1.0)
        if ros_node is not None:
            ros_node.destroy_node()
    t = np.array([s for s, _ in got]) - t0
    m = np.array([f for _, f in got])
    early, late = np.median(m[(t > 5.0) & (t < 6.0)]), np.median(m[(t > 12.0) & (t < 13.0)])
    assert abs(late / 20.0 - 1) < 0.02 and abs(early / 20.0 - 1) < 0.02, (early, late)
    print(f"held 20 N, node and board-sim with their defaults: {early:.3f} N at 2-3 s of hold, "
          f"{late:.3f} N at 9-10 s ({100 * (late / 20 - 1):+.2f} %)")
