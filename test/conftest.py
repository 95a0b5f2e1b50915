"""Shared fixtures and the ROS harness: one on-disk cache per checkout (empty on a fresh machine),
expensive models built once per run, DDS kept on this host (set here, before any test starts rclpy;
a ROS_DOMAIN_ID the caller set is kept)."""
import os
import threading
import time
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
os.environ.setdefault("CSTOMO_CACHE_DIR", str(ROOT / ".cache" / "test"))
os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
os.environ.setdefault("ROS_DOMAIN_ID", str(100 + os.getpid() % 100))

# Mesh sizes of the test suite (metres): the model that reconstructs, and an independent finer
# mesh that simulates the truth (REFERENCE_SENSOR.md section 7).
MODEL_H = 4.0e-3
TRUTH_H = 3.0e-3


@pytest.fixture(scope="session")
def cuboid():
    from cstomo_sensor.model.geometry import load_sensor

    return load_sensor("cuboid_joint")


@pytest.fixture(scope="session")
def cuboid_forward(cuboid):
    from cstomo_sensor.model.cem import ForwardModel
    from cstomo_sensor.model.mesh import MeshSpec, build_mesh

    return ForwardModel(cuboid, build_mesh(cuboid, MeshSpec(h=MODEL_H)))


@pytest.fixture(scope="session")
def cuboid_solution(cuboid_forward):
    return cuboid_forward.solve()


@pytest.fixture(scope="session")
def cuboid_model(cuboid):
    """The default reconstruction model (h = 4 mm, 8 x 8 x 4 voxels, k by the discrepancy rule)."""
    from cstomo_sensor.inverse.reconstruction import ReconSpec, build_model

    return build_model(cuboid, ReconSpec(mesh_size=MODEL_H))


@pytest.fixture(scope="session")
def cuboid_truth(cuboid):
    """The honestly simulated device: independent finer mesh, mismatched electrodes (seed 3)."""
    from cstomo_sensor.model.simulate import Truth

    return Truth(cuboid, truth_h=TRUTH_H, seed=3)


# --- ROS harness (test_node, test_replay) -------------------------------------------------------

# Small, fast reconstruction settings for every ROS test (the model is cached after the first build).
PIPE = dict(sensor="cuboid_joint", estimator="linear", mesh_size=4.0e-3, grid=[6, 6, 3], iterations=0, damping=0.0)


def wait_for(pred, timeout: float = 10.0, step: float = 0.02) -> bool:
    deadline = time.monotonic() + timeout
    while not pred():
        if time.monotonic() > deadline:
            return False
        time.sleep(step)
    return True


class Harness:
    """The node under test, spun as its own main() spins it (a MultiThreadedExecutor of two threads),
    and a probe node on a SingleThreadedExecutor, each in a thread of its own. (One three-thread
    executor for both spun at 100 % of a core once the probe had two subscriptions, and starved the
    in-process simulated board of the GIL: frames stalled, the driver reopened the port.)"""

    def __init__(self, context, params: dict, name: str = "cstomo_sensor") -> None:
        from rclpy.executors import MultiThreadedExecutor, SingleThreadedExecutor
        from rclpy.node import Node
        from rclpy.parameter import Parameter

        from cstomo_sensor.ros.node import CstomoSensorNode

        self.node = CstomoSensorNode(name, context=context,
                                     parameter_overrides=[Parameter(k, value=v) for k, v in params.items()])
        self.probe = Node("probe", context=context)
        self.executor = MultiThreadedExecutor(num_threads=2, context=context)
        self.executor.add_node(self.node)
        self.probe_executor = SingleThreadedExecutor(context=context)
        self.probe_executor.add_node(self.probe)
        self._threads = [threading.Thread(target=e.spin, daemon=True) for e in (self.executor, self.probe_executor)]
        for t in self._threads:
            t.start()
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
        for e, t in zip((self.executor, self.probe_executor), self._threads):
            e.shutdown(timeout_sec=2.0)
            t.join(5.0)
        self.node._release()
        self.node.destroy_node()
        self.probe.destroy_node()


@pytest.fixture(scope="module")
def ros():
    """A ROS context of its own per test module."""
    import rclpy

    ctx = rclpy.Context()
    rclpy.init(context=ctx)
    yield ctx
    rclpy.try_shutdown(context=ctx)
