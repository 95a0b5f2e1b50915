"""The floor of a Python rclpy node: the lean loop of issue 27, for ``cstomo bench-node --lean``.

A measuring instrument, not a product path: it estimates nothing. One thread (named as the node's frame
thread, so bench-node's per-thread figures compare) waits on the board's port, reads, decodes the frame
(the project's wire decoder), stamps it (the node's clock mapping), does two matrix products of the
size of the linear estimator's (a fixed 3 x 208 map times the frame less a reference, and one
208-vector product), and publishes one ``geometry_msgs/WrenchStamped`` of self-serialised CDR bytes
(:class:`~cstomo_sensor.ros.messages.OutputMessages`) on ``~/wrench``, as the node publishes it. Once a
second it publishes the node's diagnostics counters that bench-node reads (frames, gaps, corrupt,
messages published, processing time): no executor, no timers, no parameters, no tare.

    python -m cstomo_sensor.tools.bench.lean PORT --rate HZ [--ros-args -r __ns:=/s0]
"""
from __future__ import annotations

import argparse
import os
import select
import sys
import time
import tty

import numpy as np
import rclpy
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from geometry_msgs.msg import WrenchStamped
from rclpy.qos import QoSProfile, ReliabilityPolicy

from ...board.clock import ClockMapper
from ...board.driver import set_os_thread_name
from ...board.wire import N_VALUES, DataFrame, Decoder, Identify, Start, encode
from ...ros.messages import OutputMessages
from ...ros.node import FRAME_THREAD


def diagnostics(name: str, counts: dict, now_ns: int) -> DiagnosticArray:
    """The counters as the node's diagnostics carry them (bench-node's ``_sensor_figures``)."""
    arr = DiagnosticArray()
    arr.header.stamp.sec, arr.header.stamp.nanosec = divmod(now_ns, 1_000_000_000)
    arr.status = [DiagnosticStatus(name=name, message="lean loop", values=[
        KeyValue(key=k, value=str(v)) for k, v in counts.items()])]
    return arr


def run(port: str, rate: float) -> int:
    node = rclpy.create_node("cstomo_sensor")
    qos = QoSProfile(depth=10, reliability=ReliabilityPolicy.SYSTEM_DEFAULT)  # the node's defaults
    pub = node.create_publisher(WrenchStamped, "~/wrench", qos)
    diag_pub = node.create_publisher(DiagnosticArray, "/diagnostics", 10)
    name = f"{node.get_namespace().rstrip('/')}/cstomo_sensor: sensor"
    rng = np.random.default_rng(0)  # the products' cost depends on their sizes, not their values
    gain, ref = rng.normal(size=(3, N_VALUES)), rng.normal(size=N_VALUES)
    out, clock, dec = OutputMessages(np.zeros((1, 3)), "cstomo_socket"), ClockMapper(), Decoder()
    fd = os.open(port, os.O_RDWR | os.O_NOCTTY)  # a pty: raw, as pyserial opens it for the driver
    tty.setraw(fd)
    os.write(fd, encode(Identify()) + encode(Start(rate)))
    frames = gaps = published = period_frames = busy_ns = 0
    last_seq, handle = None, pub.handle
    next_diag = time.monotonic()
    try:
        while rclpy.ok():  # until SIGINT
            if select.select((fd,), (), (), 0.1)[0]:
                t0 = time.perf_counter_ns()
                for msg in dec.feed(os.read(fd, 65536)):
                    if not isinstance(msg, DataFrame):
                        continue
                    frames += 1
                    period_frames += 1
                    if last_seq is not None:
                        gaps += (msg.seq - last_seq - 1) & 0xFFFFFFFF
                    last_seq = msg.seq
                    stamp = clock.stamp_ns(msg.board_time_us, time.time_ns())
                    d = msg.values - ref
                    force = gain @ d
                    force *= 1.0 / (1.0 + d @ d)  # the 208-vector product, used
                    with handle:
                        handle.publish_raw(out.wrench(force, stamp))
                    published += 1
                busy_ns += time.perf_counter_ns() - t0
            if time.monotonic() >= next_diag:  # 1 Hz, as the node's diagnostics
                next_diag += 1.0
                counts = {"frames": frames, "seq_gaps": gaps, "corrupt": dec.stats.corrupt, "dropped_overflow": 0,
                          "late_dropped": 0, "frames_rejected": 0, "implausible": 0,
                          "processing_time_mean_ms": busy_ns * 1e-6 / max(period_frames, 1),  # this second's
                          "messages_published": f"wrench={published}"}
                diag_pub.publish(diagnostics(name, counts, time.time_ns()))
                busy_ns = period_frames = 0
    except KeyboardInterrupt:
        pass
    except OSError as err:  # the board's pty closed under the loop
        print(f"lean loop: {port}: {err}", file=sys.stderr)
        return 1
    finally:
        os.close(fd)
        node.destroy_node()
    return 0


def main(argv: list[str] | None = None) -> int:
    args = rclpy.utilities.remove_ros_args(sys.argv if argv is None else ["lean"] + argv)[1:]
    p = argparse.ArgumentParser(prog="python -m cstomo_sensor.tools.bench.lean", description=__doc__.splitlines()[0])
    p.add_argument("port", help="the board's port (a pty link)")
    p.add_argument("--rate", type=float, required=True, help="frame rate asked of the board, Hz")
    a = p.parse_args(args)
    set_os_thread_name(FRAME_THREAD)  # the main thread is the frame thread: no other Python thread
    rclpy.init(args=sys.argv if argv is None else ["lean"] + argv)
    try:
        return run(a.port, a.rate)
    finally:
        rclpy.try_shutdown()


if __name__ == "__main__":
    sys.exit(main())
