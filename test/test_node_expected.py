"""A controller's expected load is an input to check, not to trust (issue 34 item 5; force/checks/expected.py):
every bad kind of ``~/expected_wrench`` through a real node (rclpy, the simulated board on an in-process
virtual link, the ``model`` estimator: the one whose joint fit uses an expected load), in sequence on
one node: none moves the published wrench beyond what the frames support, the output never stops,
each kind is refused, counted and said once (the log, ``/diagnostics``).

The device: the committed bag's honest frames (its own simulator's mesh, 60 dB), unloaded for a tare,
then its (10, 0, -10) N load (14.1 N at 45 deg) held, its 50 noisy frames looping."""
from __future__ import annotations

import math
import subprocess
import sys
import time

import numpy as np
import pytest
from conftest import BAG_RATE, diag, start, wait_for

rclpy = pytest.importorskip("rclpy")

NAME = "cstomo_expected"  # a node name of its own: one /rosout publisher per logger name in a process
TRUE = (10.0, 0.0, -10.0)


class HeldLoad:
    """The bag's unloaded frames for ``still`` s (a tare), then its 14.1 N load's 50 frames, looping."""

    def __init__(self, bag, still: float = 1.5):
        self.rest, self.load, self.still = bag.frames[:20], bag.frames[70:120], still
        assert np.allclose(bag.forces[70:120], TRUE)

    def frame(self, t, rng):
        k = int(round(t * BAG_RATE))
        return self.rest[k % 20] if t < self.still else self.load[k % 50]

    def truth(self, t):
        return np.zeros(3) if t < self.still else np.array(TRUE)


#: The flooding controller: publishes for 1 s at up to 10 kHz once the node subscribes; prints when it began
#: (time.time()) and its rate.
FLOOD = """
import sys, time
import rclpy
from geometry_msgs.msg import WrenchStamped
rclpy.init()
node = rclpy.create_node("flood")
pub = node.create_publisher(WrenchStamped, sys.argv[1], 10)
t = time.monotonic() + 10.0
while pub.get_subscription_count() < 1 and time.monotonic() < t:
    time.sleep(0.01)
time.sleep(0.3)
msgs = []
for z in (-1e9, -10.0):
    m = WrenchStamped()
    m.header.frame_id = "cstomo_socket"
    m.wrench.force.x, m.wrench.force.z = (10.0 if z == -10.0 else 0.0), z
    msgs.append(m)
began, t0, n = time.time(), time.monotonic(), 0
while time.monotonic() - t0 < 1.0:
    m = msgs[n % 2]
    m.header.stamp.sec, m.header.stamp.nanosec = divmod(time.time_ns(), 10**9)
    pub.publish(m)
    n += 1
    while time.monotonic() < t0 + n * 1e-4:
        pass
print(began, n / (time.monotonic() - t0))
node.destroy_node()
rclpy.shutdown()
"""


def _msg(force, stamp_ns, frame_id="cstomo_socket"):
    from geometry_msgs.msg import WrenchStamped

    m = WrenchStamped()
    m.header.frame_id = frame_id
    m.header.stamp.sec, m.header.stamp.nanosec = divmod(int(stamp_ns), 10**9)
    m.wrench.force.x, m.wrench.force.y, m.wrench.force.z = (float(v) for v in force)
    return m


#: (kind the node must say, force, stamp relative to now (s), frame_id) of each bad message; None: no stamp (0)
BAD = [
    ("not_finite", (0.0, 0.0, math.nan), 0.0, "cstomo_socket"),
    ("not_finite", (math.inf, 0.0, -10.0), 0.0, "cstomo_socket"),
    ("beyond_range", (0.0, 0.0, -1e9), 0.0, "cstomo_socket"),
    ("beyond_range", (0.0, 0.0, -100.0), 0.0, "cstomo_socket"),  # 100 N against the true 14.1 N
    ("far", (0.0, 0.0, -40.0), 0.0, "cstomo_socket"),  # within the range, far from the frames
    ("stale", TRUE, None, "cstomo_socket"),  # a stamp of 0
    ("stale", TRUE, -1e6, "cstomo_socket"),
    ("future", TRUE, 1e6, "cstomo_socket"),
    ("other_frame", TRUE, 0.0, "world"),
]


@pytest.mark.slow
@pytest.mark.alone  # judges the output's gaps (< 0.5 s) under a 10 kHz flood in real time: no neighbour (setup.cfg)
def test_bad_expected_wrenches_are_refused_counted_and_said_once(ros, tmp_path, source, warm_model):
    from diagnostic_msgs.msg import DiagnosticArray
    from geometry_msgs.msg import WrenchStamped
    from rcl_interfaces.msg import Log

    h, board = start(ros, tmp_path, HeldLoad(source), name=NAME, estimator="model", tare_on_start=True,
                     tare_frames=10, creep_per_decade=0.0)
    try:
        wr = h.record(f"/{NAME}/wrench", WrenchStamped)
        filt = h.record(f"/{NAME}/wrench_filtered", WrenchStamped)
        rosout = h.record("/rosout", Log)
        diags = h.record("/diagnostics", DiagnosticArray)
        pub = h.probe.create_publisher(WrenchStamped, f"/{NAME}/expected_wrench", 10)
        assert wait_for(lambda: pub.get_subscription_count() == 1, 5.0)
        board.start()
        assert wait_for(lambda: len(wr) >= 100, 20.0), len(wr)  # tared, then 1.5 s of the held load
        stream = h.node.stream
        t0 = time.monotonic()
        time.sleep(1.0)
        scale0, sd0 = stream.slow.drift.scale, math.sqrt(stream.slow.drift.P[0, 0])
        phases = [("baseline", t0, time.monotonic())]

        def send(force, rel, frame_id="cstomo_socket"):
            pub.publish(_msg(force, 0 if rel is None else time.time_ns() + rel * 1e9, frame_id))

        # a true expectation, at the frames' rate: accepted and used
        ta = time.monotonic()
        for _ in range(25):
            send(TRUE, 0.0)
            time.sleep(1.0 / BAG_RATE)
        phases.append(("true", ta, time.monotonic()))
        used = stream.slow.expected.used_frames
        for kind, force, rel, frame_id in BAD:
            ta = time.monotonic()
            for _ in range(5):
                send(force, rel, frame_id)
                time.sleep(0.05)
            time.sleep(0.2)
            phases.append((kind, ta, time.monotonic()))
        # a flood: 10 kHz for 1 s from another process (a controller is one; in this one its loop would take
        # the GIL from the in-process board), the true expectation and 1e9 N alternately
        ta = time.monotonic()
        flood = subprocess.run([sys.executable, "-c", FLOOD, f"/{NAME}/expected_wrench"], capture_output=True,
                               text=True, timeout=60)
        assert flood.returncode == 0, flood.stderr
        ta, flood_rate = float(flood.stdout.split()[0]) - time.time() + time.monotonic(), float(flood.stdout.split()[1])
        time.sleep(0.3)
        phases.append(("flood", ta, time.monotonic()))
        time.sleep(1.5)  # the diagnostics of the flood's period
        scale1 = stream.slow.drift.scale
        refused, accepted = dict(stream.slow.expected.refused), stream.slow.expected.accepted
    finally:
        board.close()
        h.close()

    forces = np.array([[m.wrench.force.x, m.wrench.force.y, m.wrench.force.z] for _, m in wr])
    arrived = np.array([t for t, _ in wr])
    base = (arrived >= phases[0][1]) & (arrived < phases[0][2])
    f0 = forces[base].mean(axis=0)
    noise = np.linalg.norm(forces[base] - f0, axis=1).max()
    print(f"baseline {f0.round(3)} N (true {TRUE}), largest per-frame deviation {noise:.3f} N; flood "
          f"{flood_rate:.0f} msg/s; accepted {accepted}, refused {refused}; used for {used} frames; scale {scale0:.6f} -> {scale1:.6f} "
          f"(1-sigma {sd0:.2e})")
    assert used > 0  # the true expectation was used
    after = arrived >= phases[0][1]
    before = f0
    for name, a, b in phases:
        sel = (arrived >= a) & (arrived < b)
        dev = np.linalg.norm(forces[sel] - f0, axis=1)
        mean = forces[sel].mean(axis=0)
        rate = sel.sum() / (b - a)
        print(f"  {name:12s} {b - a:.2f} s: {sel.sum()} wrenches ({rate:.0f}/s), mean moved {np.linalg.norm(mean - f0):.3f} N "
              f"({np.linalg.norm(mean - before):.3f} N from the phase before), largest {dev.max():.3f} N")
        assert sel.sum() > 0, name  # the output never stops (its rate: over all phases, below)
        assert dev.max() < max(2.0 * noise, 1.0), name  # no wrench beyond what the frames support
        # no message moves the reading (100 N against 14.1 N had moved it 0.7 N); the tracker's own slow
        # change under the held load moved it 0.13 N in 8 s, 0.04 N at most from one phase to the next
        assert np.linalg.norm(mean - before) < 0.1, name
        before = mean
    # the output never stops: no gap a stop would leave, and the board's rate over all phases (a loaded CI host
    # once stalled one 0.45 s phase to 14 wrenches/s: judged per phase, a host's stall failed it)
    gaps = np.diff(arrived[after])
    assert gaps.max() < 0.5, gaps.max()
    during = after & (arrived < phases[-1][2])
    assert during.sum() / (phases[-1][2] - phases[0][1]) > 0.7 * BAG_RATE
    fl = np.array([[m.wrench.force.x, m.wrench.force.y, m.wrench.force.z] for t, m in filt if t >= phases[0][1]])
    assert np.linalg.norm(fl - f0, axis=1).max() < 1.0
    assert flood_rate > 2000  # the flood did flood (10 kHz asked; a loaded host publishes fewer)
    assert refused["beyond_range"] > 10  # ... and reached the node (5 + 5 before it)
    # each kind refused, counted, said once in the log (naming the input) and in the diagnostics
    kinds = sorted({k for k, *_ in BAD})
    for k in kinds:
        assert refused[k] >= 1, (k, refused)
    said = [m.msg for _, m in rosout if m.name == NAME and "~/expected_wrench refused, not used" in m.msg]
    print("\n".join(said))
    assert len(said) == len(kinds), said
    from cstomo_sensor.force.checks.expected import KINDS

    for k in kinds:
        assert sum(KINDS[k] in s for s in said) == 1, k
    statuses = [diag(m) for _, m in diags if m.status[0].name.endswith(f"{NAME}: sensor")]
    final = statuses[-1][2]["expected_refused"]
    assert all(f"{k} " in final for k in kinds), final
    said_diag = " ".join(msg for _, msg, _ in statuses)
    for k in kinds:
        assert f"({k})" in said_diag, k
    assert all("~/expected_wrench" in msg for _, msg, _ in statuses if "refused, not used" in msg)
