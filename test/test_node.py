"""cstomo_sensor_node with real rclpy and a simulated board on a real pseudo-terminal.

Also holds the small ROS harness that test_replay and test_launch import (ros_env, Harness).
DDS stays on this host: ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST and a domain per process, set here
before rclpy starts.
"""
from __future__ import annotations

import os
import threading
import time

os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
os.environ["ROS_DOMAIN_ID"] = str(100 + os.getpid() % 100)

import numpy as np  # noqa: E402
import pytest  # noqa: E402

from cstomo_sensor.errors import ConfigError  # noqa: E402
from cstomo_sensor.messages import ClockMapper  # noqa: E402

rclpy = pytest.importorskip("rclpy")

# Small, fast reconstruction settings for every ROS test (the model is cached after the first build).
PIPE = dict(sensor="cuboid_joint", estimator="linear", mesh_size=4.0e-3, grid=[6, 6, 3], iterations=0, damping=0.0)


# --- harness ---------------------------------------------------------------------------------------


def wait_for(pred, timeout: float = 10.0, step: float = 0.02) -> bool:
    deadline = time.monotonic() + timeout
    while not pred():
        if time.monotonic() > deadline:
            return False
        time.sleep(step)
    return True


class Harness:
    """The node under test plus a probe node, spun by one MultiThreadedExecutor in a thread."""

    def __init__(self, context, params: dict, name: str = "cstomo_sensor") -> None:
        from rclpy.executors import MultiThreadedExecutor
        from rclpy.node import Node
        from rclpy.parameter import Parameter

        from cstomo_sensor.node import CstomoSensorNode

        self.node = CstomoSensorNode(name, context=context,
                                     parameter_overrides=[Parameter(k, value=v) for k, v in params.items()])
        self.probe = Node("probe", context=context)
        self.executor = MultiThreadedExecutor(num_threads=3, context=context)
        self.executor.add_node(self.node)
        self.executor.add_node(self.probe)
        self._thread = threading.Thread(target=self.executor.spin, daemon=True)
        self._thread.start()
        self._lock = threading.Lock()

    def record(self, topic: str, msg_type, depth: int = 1000) -> list:
        """Record ``topic`` (reliable); returns the list that receives (monotonic time, msg)."""
        from rclpy.qos import QoSProfile, ReliabilityPolicy

        out: list = []

        def cb(msg):
            with self._lock:
                out.append((time.monotonic(), msg))

        self.probe.create_subscription(msg_type, topic, cb, QoSProfile(depth=depth, reliability=ReliabilityPolicy.RELIABLE))
        return out

    def state(self) -> str:
        return self.node._state_machine.current_state[1]

    def call_tare(self, timeout: float = 20.0):
        from std_srvs.srv import Trigger

        cli = self.probe.create_client(Trigger, f"{self.node.get_fully_qualified_name()}/tare")
        assert cli.wait_for_service(5.0)
        fut = cli.call_async(Trigger.Request())
        assert wait_for(fut.done, timeout)
        return fut.result()

    def close(self) -> None:
        self.executor.shutdown(timeout_sec=2.0)
        self._thread.join(5.0)
        self.node._release()
        self.node.destroy_node()
        self.probe.destroy_node()


@pytest.fixture(scope="module")
def ros():
    ctx = rclpy.Context()
    rclpy.init(context=ctx)
    yield ctx
    rclpy.try_shutdown(context=ctx)


# --- ClockMapper (pure) ----------------------------------------------------------------------------


def test_clock_mapper_follows_a_drifting_board_clock():
    """Board crystal 200 ppm fast, host delays of 0.2..5 ms and 5 % spikes of up to 80 ms: after the
    first window the stamps stay within 1.5 ms of the true host time of measurement (drift 200e-6 x
    window 5 s = 1 ms, plus the smallest delay) and never after the host time of arrival."""
    rng = np.random.default_rng(3)
    mapper = ClockMapper(window_s=5.0)
    rate, drift, offset_ns = 200.0, 200e-6, 1_700_000_000_000_000_000
    errs, future = [], 0
    for k in range(int(120 * rate)):
        true_host_ns = offset_ns + int(k / rate * 1e9)
        board_us = int(k / rate * (1 + drift) * 1e6) + 12345
        delay = 0.2e-3 + rng.exponential(1e-3) + (rng.random() < 0.05) * rng.uniform(0, 0.08)
        recv_ns = true_host_ns + int(delay * 1e9)
        s = mapper.stamp_ns(board_us, recv_ns)
        future += s > recv_ns
        if k > 5 * rate:
            errs.append((s - true_host_ns) * 1e-9)
    errs = np.abs(errs)
    assert future == 0
    assert errs.max() < 1.5e-3, errs.max()
    # the offset really moved with the drift (120 s x 200 ppm = 24 ms), it was not frozen at the start
    assert abs(mapper.offset_ns - (offset_ns - 12345_000)) > 20e6


def test_clock_mapper_restarts_when_the_board_clock_jumps_back():
    m = ClockMapper(window_s=1.0)
    assert m.stamp_ns(5_000_000, 10_000_000_000) == 10_000_000_000
    m.stamp_ns(5_010_000, 10_010_000_000)
    # the board reset: its clock starts again at 0, the host goes on
    assert m.stamp_ns(0, 10_020_000_000) == 10_020_000_000
    assert m.stamp_ns(10_000, 10_031_000_000) == 10_030_000_000  # 1 ms late frame mapped back
    with pytest.raises(ConfigError, match="window_s"):
        ClockMapper(0.0)


# --- parameters ------------------------------------------------------------------------------------


@pytest.mark.parametrize("name, value", [
    ("protocol", "foo"), ("input", "bluetooth"), ("qos_reliability", "sometimes"),
    ("estimator", "magic"), ("grid", [8, 8]), ("frame_id", ""),
])
def test_bad_parameter_values_are_refused_at_configure(ros, capfd, name, value):
    from rclpy.lifecycle import TransitionCallbackReturn

    h = Harness(ros, {"autostart": False, name: value}, name=f"bad_{name}")
    try:
        assert h.node.trigger_configure() == TransitionCallbackReturn.FAILURE
        assert h.state() == "unconfigured"
    finally:
        h.close()
    err = capfd.readouterr().err
    assert f"parameter '{name}'=" in err and "expected" in err, err


def test_out_of_range_and_wrong_type_values_are_refused_at_declaration(ros):
    from rclpy.exceptions import InvalidParameterTypeException, InvalidParameterValueException
    from rclpy.parameter import Parameter

    from cstomo_sensor.node import CstomoSensorNode

    with pytest.raises(InvalidParameterValueException, match="stale_timeout"):
        CstomoSensorNode("bad_range", context=ros, parameter_overrides=[Parameter("stale_timeout", value=-1.0)])
    with pytest.raises(InvalidParameterTypeException, match="tare_frames"):
        CstomoSensorNode("bad_type", context=ros, parameter_overrides=[Parameter("tare_frames", value="many")])


def test_parameters_are_declared_once_with_descriptions_and_read_only_where_a_restart_is_needed(ros):
    from cstomo_sensor.node import PARAMETERS, CstomoSensorNode

    node = CstomoSensorNode("introspect", context=ros, parameter_overrides=[rclpy.parameter.Parameter("autostart", value=False)])
    try:
        names = set(node._parameters) - {"use_sim_time", "start_type_description_service"}
        assert names == set(PARAMETERS)
        for name in PARAMETERS:
            d = node.describe_parameter(name)
            assert d.description, name
        assert node.describe_parameter("port").read_only and node.describe_parameter("protocol").read_only
        assert node.describe_parameter("stale_timeout").floating_point_range[0].from_value > 0
    finally:
        node.destroy_node()
