"""Shared fixtures and the ROS harness: one on-disk cache per checkout (empty on a fresh machine),
expensive models built once per run, DDS kept on this host (set here, before any test starts rclpy;
a ROS_DOMAIN_ID the caller set is kept)."""
import contextlib
import os
import threading
import time
import uuid
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parent.parent
os.environ.setdefault("CSTOMO_CACHE_DIR", str(ROOT / ".cache" / "test"))
os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
CALLER_DOMAIN = os.environ.get("ROS_DOMAIN_ID")  # a domain the caller chose: every test and tool keeps it
# Parallel workers (pytest-xdist, `make test`: gw0, gw1, ...): each worker its own domain, the caller's
# plus the worker's number, so the nodes, probes and /diagnostics of two workers never meet.
_WORKER = int(os.environ.get("PYTEST_XDIST_WORKER", "gw0")[2:] or 0)
if CALLER_DOMAIN is not None and _WORKER:
    CALLER_DOMAIN = str((int(CALLER_DOMAIN) + _WORKER) % 233)  # 0..232: the domain ids DDS accepts
    os.environ["ROS_DOMAIN_ID"] = CALLER_DOMAIN
# none chosen: one from the run's process (xdist's workers share their parent), plus the worker's number;
# 20..99, as the Makefile's: above 101 a domain's DDS ports fall among Linux's ephemeral ports
os.environ.setdefault("ROS_DOMAIN_ID", str(20 + (os.getppid() if "PYTEST_XDIST_WORKER" in os.environ else os.getpid())
                                           % 40 * 2 + _WORKER))

# --- the two tiers (docs/design.md#tests) ----------------------------------------------------------
# The fast tier (`make test-fast`, `pytest -m "not slow"`) is pure computation in this process: a test
# not marked `slow` that starts a process (subprocess, fork, multiprocessing, a pty's child) or a ROS
# context (hence a node) fails here, in both tiers, with one line naming what it started. Mark it
# `@pytest.mark.slow` (or the module: `pytestmark = pytest.mark.slow`) or make it start nothing.


class FastTierError(AssertionError):
    """A test of the fast tier (not marked ``slow``) started a process or a ROS context."""


_FAST_TEST: list[str | None] = [None]  # the node id of the fast test running now (None: a slow one, or none)


def _guard(what: str, original):
    def guarded(*args, **kwargs):
        if _FAST_TEST[0] is not None:
            raise FastTierError(f"{_FAST_TEST[0]} is in the fast tier (not marked slow) and started {what}: "
                                f"mark it @pytest.mark.slow or start nothing (test/conftest.py)")
        return original(*args, **kwargs)

    guarded.__wrapped__ = original
    return guarded


def _install_guards() -> None:
    import multiprocessing.process
    import subprocess

    subprocess.Popen._execute_child = _guard("a process", subprocess.Popen._execute_child)
    multiprocessing.process.BaseProcess.start = _guard("a process", multiprocessing.process.BaseProcess.start)
    for name in ("fork", "forkpty", "posix_spawn", "posix_spawnp"):
        if hasattr(os, name):
            setattr(os, name, _guard(f"a process (os.{name})", getattr(os, name)))
    try:
        from rclpy.context import Context
    except ImportError:  # no rclpy here: the tests that need it skip
        return
    Context.init = _guard("a ROS context (rclpy.init: a node needs one)", Context.init)


_install_guards()


# --- the mechanics' factors, kept by each worker -----------------------------------------------------
# A batch of socket loads (an honest simulation's frames, a timeline, the estimators' training) assembles
# the body's stiffness and factorises it once (model/elastic_fem.problem: 10-40 s a mesh), then frees it
# (elasticity.release: a long-running process keeps no hundreds of MB). On a fresh clone file after file
# computes such a batch: each worker keeps its problems instead (elastic_fem's cache, at most 2), and the
# next batch on the same mesh and material reuses the factor (the same matrix: the same numbers). Only
# the code's call after a batch is skipped; elastic_fem.release itself still frees them (test_mechanics).
def _keep_mechanics() -> None:
    from cstomo_sensor.model import elasticity

    elasticity.release = lambda: None


_keep_mechanics()


# --- the order of the files: the longest first ------------------------------------------------------
# `make test` runs two workers (pytest-xdist, --dist loadfile --no-loadscope-reorder): each takes the next
# file of the collection when it is almost done with its own. The files that take longest (a minute or
# more on a fresh clone: honest simulations over time, benches, nodes in real time) go first, so neither
# worker starts one of them while the other has nothing left. Only the order changes; a file not named
# keeps its place, and every file's tests keep theirs.
LONGEST_FIRST = (  # every file of 10 s or more, by its sum in the fresh-clone CI's per-test times (main 62fd31b,
    # --durations=0; 170 s .. 11 s), test_sigma and test_calibration_directions as their cheaper set-ups make them.
    # test_robot_bench and test_robot_bench_change solve the loads that test_sigma's baseline and
    # test_calibration_directions' recording then read from the cache: they come first. Simulated on those times
    # (xdist's loadfile scheduling), the two workers end 1-4 s apart, the last files being small.
    # test_device reads test_scene_field's loads from the cache: it is left out (the unlisted files run last).
    "test_robot_bench.py", "test_tools.py", "test_creep.py", "test_drift.py", "test_node_restart_gradient.py",
    "test_calibration.py", "test_node_time.py", "test_node.py", "test_colcon_install.py", "test_launch_sensors.py",
    "test_robot_bench_change.py", "test_board_pty.py", "test_creep_defaults.py", "test_bench.py",
    "test_reproducible.py", "test_scene_field.py", "test_docs.py", "test_first_tare.py",
    "test_plot_record.py", "test_sigma.py", "test_learned.py", "test_force.py", "test_node_startup.py",
    "test_mechanics.py", "test_calibration_directions.py", "test_tare_load.py", "test_bench_node.py",
    "test_node_faults.py", "test_firmware_fuzz.py", "test_replay.py", "test_frame_path.py", "test_forward.py",
    "test_firmware.py", "test_taring.py",
)


def pytest_collection_modifyitems(config, items):
    rank = {name: i for i, name in enumerate(LONGEST_FIRST)}
    items.sort(key=lambda item: rank.get(item.path.name, len(rank)))  # stable: the rest keep their order


def pytest_ignore_collect(collection_path, config):
    """`make test`'s second run, ``-m alone`` (setup.cfg): a test file that never writes ``mark.alone`` holds
    no test of it and is not imported (its imports, ~10 s of the run's start for the 9 tests of 4 files)."""
    if (config.getoption("markexpr", "") == "alone" and collection_path.suffix == ".py"
            and collection_path.name.startswith("test_")):
        return "mark.alone" not in collection_path.read_text(encoding="utf-8")
    return None


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_protocol(item, nextitem):
    """The fast tier's guard is on through the set-up, the call and the tear-down of a test not marked
    slow (so a fixture that starts a node counts too)."""
    _FAST_TEST[0] = None if item.get_closest_marker("slow") else item.nodeid
    try:
        yield
    finally:
        _FAST_TEST[0] = None


# Mesh sizes of the test suite (metres): the model that reconstructs, and an independent finer
# mesh that simulates the truth (docs/physics.md#honest-simulation).
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


#: s: the longest a node process a test starts may take to refuse its arguments and exit. A hang guard, not a
#: figure judged: it starts cold (the interpreter, numpy and scipy, rclpy and a DDS participant) before it
#: can refuse, 6-12 s on this 2-core host at load 7; a bound of 60 s was once overrun under CI's heaviest load.
PROCESS_TIMEOUT = 300.0


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

    def call_tare(self, timeout: float = 20.0, service: str = "tare"):
        """Call ``~/tare`` (or ``~/tare_forced``: ``service="tare_forced"``) and return its answer."""
        from std_srvs.srv import Trigger

        cli = self.probe.create_client(Trigger, f"{self.node.get_fully_qualified_name()}/{service}")
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


# --- a simulated board playing the committed bag, and the node reading it (test_node*) -----------

DATA = os.path.join(os.path.dirname(os.path.abspath(__file__)), "data")
BAG_RATE = 50.0  # frames per second of the committed bag (test/data/make_bag.py)


class BagSource:
    """The simulated board measures the committed bag's frames (honest simulation of a scripted
    load, test/data/make_bag.py) at their own time, looping; ``truth`` is the scripted force."""

    def __init__(self):
        from rclpy.serialization import deserialize_message
        from rosbags.rosbag2 import Reader
        from std_msgs.msg import Float32MultiArray

        from cstomo_sensor.frames_io import read_forces

        with Reader(os.path.join(DATA, "raw_voltages_bag")) as r:
            self.frames = np.array([deserialize_message(bytes(raw), Float32MultiArray).data
                                    for _, _, raw in r.messages()], dtype=float)
        self.forces = read_forces(os.path.join(DATA, "raw_voltages_truth.csv"))

    def _i(self, t):
        return int(round(t * BAG_RATE)) % len(self.frames)

    def frame(self, t, rng):
        return self.frames[self._i(t)]

    def truth(self, t):
        return self.forces[self._i(t)]


@pytest.fixture(scope="module")
def source():
    pytest.importorskip("rosbags")
    return BagSource()


@pytest.fixture(scope="module")
def warm_model():
    """Build the Pipeline once (into the test cache); every node below loads it in well under a second."""
    from cstomo_sensor.frame_path.config import PipelineConfig
    from cstomo_sensor.frame_path.pipeline import Pipeline

    return Pipeline.build(PipelineConfig(**{k: (tuple(v) if k == "grid" else v) for k, v in PIPE.items()}))


def board_link(tmp_path, pty: bool = False) -> str:
    """A fresh link for a simulated board: ``virtual://<unique name>`` (in-process, board/links.py),
    or with ``pty`` a symlink in ``tmp_path`` to a real pseudo-terminal."""
    return str(tmp_path / "board") if pty else f"virtual://{Path(tmp_path).name}-{uuid.uuid4().hex[:8]}"


def start(ros, tmp_path, source, faults=None, rate=BAG_RATE, name="cstomo_sensor", pty=False, **params):
    """A simulated board (on a virtual link; ``pty``: on a pty linked in tmp_path) and the node reading
    it, its ``port`` the board's link (``board.device``: a board that replaces it takes the same
    ``link``); returns (harness, board)."""
    from cstomo_sensor.board.sim import FaultConfig, SimulatedBoard

    board = SimulatedBoard(source, rate_hz=rate, link=board_link(tmp_path, pty), faults=faults or FaultConfig(), seed=2)
    p = dict(PIPE, port=board.device, tare_file=str(tmp_path / "tare.csv"), stale_timeout=0.3)
    p.update(params)
    h = Harness(ros, p, name=name)
    assert wait_for(lambda: h.state() == "active", 20.0), h.state()
    return h, board


def prepare_board(cmd: list[str]) -> None:
    """The frames of the board ``cmd`` (``[executable, "board-sim", ...]`` with a load script and the typical creep,
    as a launch's simulated board runs) computed in this process, into the cache the board reads (the same
    Timeline, so the same key: tools/board_sim.py's own call); read from the cache when another test or worker
    computed them. On a fresh clone a board's process would factorise the elasticity for the script's loads
    (15-20 s) before its knots; this one keeps the factor of the tests before (the mechanics' factors kept
    above) and keeps it for those after. test_launch_sensors, test_colcon_install and test_board_pty play the
    launch's own script (tools/launching.py SIM_LOAD): whichever runs first computes it, once."""
    from cstomo_sensor.tools import board_sim

    assert cmd[1] == "board-sim", cmd
    a = board_sim.parser().parse_args(cmd[2:])
    assert a.load_script and a.creep != 0 and not a.scene, cmd  # board_sim._main plays it as script_timeline's
    board_sim.script_timeline(a.load_script, a.creep, sensor=a.sensor, duration=a.duration, snr_db=a.snr,
                              seed=a.seed)


def diag_records(h):
    from diagnostic_msgs.msg import DiagnosticArray

    return h.record("/diagnostics", DiagnosticArray)


@contextlib.contextmanager
def diagnostics_seen(ctx):
    """A probe node on ``ctx``, spun in a thread while the block runs, collecting ``/diagnostics``:
    yields {status name: [its key-values of each message, in order]}."""
    from diagnostic_msgs.msg import DiagnosticArray
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.node import Node

    probe = Node("probe", context=ctx)
    seen: dict[str, list[dict]] = {}
    lock = threading.Lock()

    def cb(msg):
        with lock:
            for s in msg.status:
                seen.setdefault(s.name, []).append({kv.key: kv.value for kv in s.values})

    probe.create_subscription(DiagnosticArray, "/diagnostics", cb, 10)
    ex = SingleThreadedExecutor(context=ctx)
    ex.add_node(probe)
    t = threading.Thread(target=ex.spin, daemon=True)
    t.start()
    try:
        yield seen
    finally:
        ex.shutdown(timeout_sec=2.0)
        t.join(5.0)
        probe.destroy_node()


def diag(msg) -> tuple[int, str, dict]:
    s = msg.status[0]
    return s.level[0], s.message, {kv.key: kv.value for kv in s.values}
