"""A live restart on a device whose change the model's uniform scale does not describe (issue 34): the rubber
warmed with a 30 % gradient along x and its contacts moved while the node was stopped with SIGINT; the
node restarts from its saved tare (``tare_on_start:=false``), at rest and under a held 20 N. Before, it read
a phantom force along -x of 2-7 N at rest and 7-11 N under the load, for ever, with status OK.

Everything real: ``cstomo board-sim`` playing timeline scenes on a pseudo-terminal (the truth on its own
4 mm mesh, not the node's model), ``cstomo_sensor_node`` as a process stopped with SIGINT, the tare file it
wrote, and the wrenches it published. The judge is the same node restarted on the unchanged device, side
by side with the warmed one (each node in a namespace of its own, on a board of its own; the issue's aims:
the zero's p99 from 1 s within 1.25 x of the unchanged device's, the held load's error within 1.5 x angle
and 1.6 x magnitude), and the load the scene applies."""
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from conftest import PIPE, wait_for

pytestmark = pytest.mark.slow

NODE = dict(PIPE, estimator="model", creep_per_decade=0.0, stale_timeout=0.5)
RATE = 50
#: s: the restarted node's rest, then its held load of LOAD along -z. 6 s each (were 10): the zero is judged from
#: 1 s to 5.5 s (225 frames), the load over its last 5 s minus 0.3 (235 frames), after its first second; the
#: per-second medians of both devices were flat from the first second of each (0.10-0.14 N at rest, 19.81-19.90 N
#: under the load, at 10 s each), and the phantom force this test guards against (2-7 N at rest, 7-11 N under
#: the load, for ever) shows in any window of these.
REST_S, LOAD_S = 6.0, 6.0
LOAD = (0.0, 0.0, -20.0)
WARMED = dict(temperature=3.0, resistivity_per_k=0.008, contact_per_k=-0.01, gradient=0.3)  # +2.4 %, 30 %, -3 %
UNCHANGED = dict(temperature=0.0, resistivity_per_k=0.008, contact_per_k=0.0, gradient=0.0)


def scene(path: Path, duration: float, device: dict, load: bool) -> Path:
    loads = (f"  loads: [{{time: 0, force: [0, 0, 0]}}, {{time: {REST_S}, force: {list(LOAD)}}}]\n" if load else "")
    path.write_text(
        "sensor: cuboid_joint\nsnr_db: 60\nseed: 3\ntruth_mesh_size: 0.004\ntimeline:\n"
        f"  duration: {duration}\n  rate_hz: {RATE}\n"
        f"  temperature: [[0, {device['temperature']}]]\n  resistivity_per_k: {device['resistivity_per_k']}\n"
        f"  contact_per_k: {device['contact_per_k']}\n"
        + (f"  gradient: [[0, {device['gradient']}]]\n" if device["gradient"] else "") + loads)
    return path


@pytest.fixture(scope="module")
def model_built():
    from cstomo_sensor.frame_path.config import PipelineConfig
    from cstomo_sensor.frame_path.pipeline import Pipeline

    return Pipeline.build(PipelineConfig(**{k: (tuple(v) if k == "grid" else v) for k, v in PIPE.items()
                                            if k != "estimator"}, estimator="model"))


_TRUTHS: dict = {}


def prepare(path: Path) -> None:
    """The scene's frames into the cache the board reads, its device shared with the scenes before it
    of the same device (the three scenes here: one sensor, seed and mesh): the held load's mechanics
    are solved once, not once per scene (each a factorisation of the elasticity, 10-30 s); the entry is
    the one ``cstomo board-sim --scene`` reads (the same key)."""
    from dataclasses import replace

    from cstomo_sensor.model.simulate import Scene
    from cstomo_sensor.model.timeline import Timeline, TimelineSpec

    scene = Scene.load(path)
    truth = _TRUTHS.setdefault(replace(scene, timeline=None, snr_db=None), scene.truth())
    tl = Timeline(TimelineSpec.from_dict(scene.timeline), snr_db=scene.snr_db, seed=scene.seed, truth=truth)
    assert tl.cache_key() == Timeline.from_scene(path).cache_key()
    tl.prepare()


def board(path: Path, link: Path, duration: float, wait: bool = True) -> subprocess.Popen:
    """``cstomo board-sim`` playing the scene ``path`` (its timeline from the node's first START), once its
    pty is there (``wait`` False: started only, :func:`ready` waits); the scene's frames computed here first
    (into the cache the board reads)."""
    prepare(path)
    exe = Path(sys.executable).parent / "cstomo"
    p = subprocess.Popen([str(exe), "board-sim", "--scene", str(path), "--rate", str(RATE), "--duration",
                          str(duration), "--link", str(link)], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                         text=True, env=dict(os.environ, OPENBLAS_NUM_THREADS="1"))
    return ready(p) if wait else p


def ready(p: subprocess.Popen) -> subprocess.Popen:
    """The board ``p`` once it has shown its device (its pty is there)."""
    line = p.stdout.readline()
    assert line.startswith("device: "), line + stop(p)
    return p


def node(link: Path, tare: Path, tare_on_start: bool, ns: str) -> subprocess.Popen:
    exe = Path(sys.executable).parent / "cstomo_sensor_node"
    args = [str(exe), "--ros-args", "-r", f"__ns:=/{ns}"]
    for k, v in dict(NODE, port=str(link), tare_file=str(tare), tare_on_start=tare_on_start).items():
        args += ["-p", f"{k}:={str(v).lower() if isinstance(v, bool) else v}"]
    return subprocess.Popen(args, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
                            env=dict(os.environ, OPENBLAS_NUM_THREADS="1"))


class Probe:
    """The wrenches (receive time, force) of the nodes in the namespaces ``tags`` (one list each) and the
    diagnostics' messages, on a probe of its own."""

    def __init__(self, ctx, tags):
        from diagnostic_msgs.msg import DiagnosticArray
        from geometry_msgs.msg import WrenchStamped
        from rclpy.executors import SingleThreadedExecutor
        from rclpy.node import Node

        self.node = Node("restart_probe", context=ctx)
        self.wrenches, self.levels, self.lock = {tag: [] for tag in tags}, [], threading.Lock()
        for tag in tags:
            self.node.create_subscription(WrenchStamped, f"/{tag}/cstomo_sensor/wrench",
                                          lambda msg, tag=tag: self._wrench(tag, msg), 1000)
        self.node.create_subscription(DiagnosticArray, "/diagnostics", self._diag, 100)
        self.ex = SingleThreadedExecutor(context=ctx)
        self.ex.add_node(self.node)
        self.thread = threading.Thread(target=self.ex.spin, daemon=True)
        self.thread.start()

    def _wrench(self, tag, msg):
        f = msg.wrench.force
        with self.lock:
            self.wrenches[tag].append((time.monotonic(), f.x, f.y, f.z))

    def _diag(self, msg):
        with self.lock:
            self.levels += [(time.monotonic(), s.level[0] if isinstance(s.level, bytes) else s.level, s.message)
                            for s in msg.status if s.name.startswith("cstomo_sensor")]

    def close(self):
        self.ex.shutdown(timeout_sec=2.0)
        self.thread.join(5.0)
        self.node.destroy_node()


def stop(p: subprocess.Popen, sig=signal.SIGINT, signalled: bool = False) -> str:
    """Stop ``p`` with ``sig`` (``signalled``: sent already) and return what it said on stderr."""
    if p.poll() is None:
        if not signalled:
            p.send_signal(sig)
        try:
            p.wait(20)
        except subprocess.TimeoutExpired:
            p.kill()
            p.wait()
    return p.stderr.read() if p.stderr else ""


def restart_boards(tmp_path, devices: dict) -> dict:
    """{tag: ``cstomo board-sim`` started on the device ``devices[tag]`` (a rest, then the held load)}, each
    waiting for its node's first START (its timeline starts then): started while the tare's node runs, their
    processes' start-up is not waited for after it."""
    duration = REST_S + LOAD_S
    boards = {}
    try:
        for tag, device in devices.items():
            boards[tag] = board(scene(tmp_path / f"{tag}.yaml", duration, device, True), tmp_path / f"board_{tag}",
                                duration, wait=False)
    except BaseException:
        for b in boards.values():
            stop(b, signal.SIGTERM)
        raise
    return boards


def restart(probe, tmp_path, tare: Path, boards: dict) -> dict:
    """The node restarted from ``tare`` on the boards ``boards`` (:func:`restart_boards`), side by side (a node
    and a board each, in the namespace ``tag``, from a copy of the tare each: every node saves its tare when
    it stops): {tag: its wrenches as (seconds since its board's start, fx, fy, fz)}."""
    duration = REST_S + LOAD_S
    devices, nodes, errs = list(boards), {}, {}
    try:
        for b in boards.values():
            ready(b)
        for tag in devices:
            own = tmp_path / f"tare_{tag}.csv"
            own.write_bytes(tare.read_bytes())
            nodes[tag] = node(tmp_path / f"board_{tag}", own, False, tag)
        # each board's timeline starts at its node's first START, and ends its duration later
        assert wait_for(lambda: all(len(probe.wrenches[t]) > 0 for t in devices), 60.0, 0.05), "no wrench"
        for b in boards.values():
            b.wait(duration + 30.0)
        time.sleep(0.3)
    finally:
        for n in nodes.values():  # both at once, then each waited for
            if n.poll() is None:
                n.send_signal(signal.SIGINT)
        for tag, n in nodes.items():
            errs[tag] = stop(n, signalled=True)
        for b in boards.values():
            stop(b, signal.SIGTERM)
    out = {}
    for tag in devices:
        assert "saved tare" in errs[tag], errs[tag][-3000:]
        with probe.lock:
            out[tag] = np.array(probe.wrenches[tag], float).reshape(-1, 4)
    return out


def figures(w: np.ndarray) -> dict:
    """The zero's p99 over the rest from the timeline's 1 s (found by the load's step); the held load's median angle
    (deg) and magnitude (%) errors over its last 5 s (the load's first second after the step is the converging)."""
    # the load's step (the timeline's REST_S): the first wrench may come later than the first frame
    step = w[np.argmax(np.linalg.norm(w[:, 1:], axis=1) > 0.5 * np.linalg.norm(LOAD)), 0] - REST_S
    rest = w[(w[:, 0] >= step + 1.0) & (w[:, 0] < step + REST_S - 0.5)]
    load = w[(w[:, 0] >= step + REST_S + LOAD_S - 5.0) & (w[:, 0] < step + REST_S + LOAD_S - 0.3)]
    assert len(rest) > 5 * RATE * 0.5 and len(load) > 3 * RATE * 0.5, (len(rest), len(load), step)
    f = load[:, 1:]
    cos = f @ np.array(LOAD) / (np.linalg.norm(f, axis=1) * np.linalg.norm(LOAD))
    return {"zero_p99": float(np.percentile(np.linalg.norm(rest[:, 1:], axis=1), 99)),
            "angle": float(np.median(np.degrees(np.arccos(np.clip(cos, -1, 1))))),
            "magnitude": float(np.median(np.abs(np.linalg.norm(f, axis=1) / np.linalg.norm(LOAD) - 1) * 100)),
            "first_wrench_s": float(w[0, 0] - step),
            "per_s": [per_second(w, step + k) for k in range(int(REST_S + LOAD_S))]}


def per_second(w: np.ndarray, t0: float) -> float | None:
    """The median |F| (N) of the wrenches in the second from ``t0`` (None before the first wrench came)."""
    sec = w[(w[:, 0] >= t0) & (w[:, 0] < t0 + 1.0), 1:]
    return round(float(np.median(np.linalg.norm(sec, axis=1))), 2) if len(sec) else None


def test_a_restart_after_warming_with_a_gradient_recovers_at_rest_and_under_load(ros, tmp_path, model_built):
    tare = tmp_path / "tare.csv"
    probe = Probe(ros, ("tare", "warm", "still"))
    boards = {}
    try:
        # the device as tared: the node tares on start and writes its tare file; then SIGINT
        link = tmp_path / "board_tare"
        b = board(scene(tmp_path / "tare.yaml", 30.0, UNCHANGED, False), link, 30.0, wait=False)
        n = node(link, tare, True, "tare")  # starting beside its board: it opens the board's pty once it is there
        try:
            # the restart's boards (warmed; unchanged) start now, each waiting for its node
            boards = restart_boards(tmp_path, {"warm": WARMED, "still": UNCHANGED})
            ready(b)
            assert wait_for(lambda: tare.exists() and len(probe.wrenches["tare"]) > 20, 60.0, 0.1), "no tare written"
        finally:
            err = stop(n)
            stop(b, signal.SIGTERM)
        assert n.returncode == 0 and "Traceback" not in err, err[-3000:]
        # it warmed by 2.4 % with a 30 % gradient along x, contacts -3 %; the node restarts from its tare,
        # beside the same node restarted on the unchanged device (the judge; its own board and namespace)
        w = restart(probe, tmp_path, tare, boards)
        warm, still = figures(w["warm"]), figures(w["still"])
    finally:
        for rb in boards.values():  # after a failure before the restart
            stop(rb, signal.SIGTERM)
        probe.close()
    print("warmed", warm, "unchanged", still)
    assert still["zero_p99"] < 0.5 and still["magnitude"] < 10, still  # the judge itself reads right
    assert warm["zero_p99"] <= 1.25 * still["zero_p99"], (warm, still)
    assert warm["angle"] <= max(1.5 * still["angle"], 1.0), (warm, still)
    assert warm["magnitude"] <= max(1.6 * still["magnitude"], 1.0), (warm, still)
