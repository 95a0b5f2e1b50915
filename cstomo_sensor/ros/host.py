"""``cstomo_sensor_host``: several sensors in one process, one
:class:`~cstomo_sensor.ros.node.CstomoSensorNode` per namespace on one executor.

    cstomo_sensor_host /left_knee /right_knee --ros-args --params-file sensors.yaml

Each sensor is the node ``cstomo_sensor`` in its namespace, with the same topics, service,
diagnostics and parameters as ``cstomo_sensor_node`` run in that namespace. Parameters come from the
usual ROS sources matched by each node's full name: the sections ``/left_knee/cstomo_sensor:`` of a
``--params-file`` (``/**:`` or ``/**/cstomo_sensor:`` for every sensor), and ``-p name:=value`` for
every sensor. Do not remap ``__ns`` (it would put every sensor in one namespace).

Why one process: a sensor in a process of its own pays the interpreter, rclpy and a DDS participant of
its own; in one process they are shared (``cstomo bench-node --sensors N --hosted`` measures both).
The price: every sensor's Python work shares one interpreter lock, so the sensors' frames are
processed one at a time (one core for all of them), and one failing process takes every sensor down.

The library's log records (driver, stream) go to ``/rosout`` once, under the logger
``cstomo_sensor_host`` (the driver's records name their port); each node's own records stay under
its name. If any sensor's configure is refused the host exits with 1, as the node does, naming it.
"""
from __future__ import annotations

import signal
import sys

import rclpy
from rclpy.executors import ExternalShutdownException, MultiThreadedExecutor
from rclpy.task import Future

from ..errors import ConfigError
from . import log as ros_log
from .node import CstomoSensorNode
from .startup import init_ros, own_args


def usage() -> str:
    return ("usage: cstomo_sensor_host NAMESPACE [NAMESPACE ...] [--ros-args [-p NAME:=VALUE ...] "
            "[--params-file FILE]]\n\n" + __doc__.split("\n\n", 1)[1].split("\n\nWhy", 1)[0].strip()
            + "\n\n(the topics and parameters of each sensor: cstomo_sensor_node --help)")


def namespaces_of(args: list[str]) -> list[str]:
    """The sensors' namespaces (``/name``, leading slash added), in order; :class:`ConfigError` if none,
    repeated or not a ROS namespace."""
    out = []
    for a in args:
        ns = "/" + a.strip("/")
        if ns == "/" or not all(part and (part[0].isalpha() or part[0] == "_") and part.replace("_", "").isalnum()
                                for part in ns[1:].split("/")):
            raise ConfigError(f"namespace {a!r}: expected a ROS namespace such as /left_knee")
        if ns in out:
            raise ConfigError(f"namespace {ns} given twice: each sensor needs a namespace of its own")
        out.append(ns)
    if not out:
        raise ConfigError("no namespace: give one per sensor, e.g. cstomo_sensor_host /left_knee /right_knee")
    return out


def sensor_of(_record) -> str:
    """``/left_knee: `` for a record logged while that sensor's frames or tare were handled (the
    tare, the driver, the frame path), else ''."""
    name = ros_log.current_sensor()
    return f"{name}: " if name else ""


def main(argv: list[str] | None = None) -> int:
    """Entry point of ``cstomo_sensor_host``."""
    argv, own = own_args(argv)
    if "-h" in own or "--help" in own:
        print(usage())
        return 0
    try:
        namespaces = namespaces_of(own)
    except ConfigError as err:
        print(f"cstomo_sensor_host: {err}\n\n{usage()}", file=sys.stderr)
        return 2
    if not init_ros("cstomo_sensor_host", argv):
        return 2
    nodes: list[CstomoSensorNode] = []
    handler, code = None, 0
    try:  # once rclpy is up, a Ctrl-C is the sensors' normal end (exit 0), also before they spin
        for ns in namespaces:
            try:
                nodes.append(CstomoSensorNode(namespace=ns))
            except ConfigError as err:
                print(f"cstomo_sensor_host: {ns}: {err}", file=sys.stderr)
                return 2  # (the sensors made before it are destroyed below)
        # one route for the library's records (each node attached its own: every record N times)
        for node in nodes:
            ros_log.detach(node._log_handler)
        handler = ros_log.attach(rclpy.logging.get_logger("cstomo_sensor_host"), nodes[0].context.ok,
                                 label=sensor_of)
        failed = Future()
        for node in nodes:
            node.autostart_failed.add_done_callback(lambda _f, node=node: failed.done() or failed.set_result(node))
        # a thread per sensor beside one for the timers: a tare (a service call that waits for its frames)
        # never holds up another sensor's diagnostics
        executor = MultiThreadedExecutor(num_threads=len(nodes) + 1)
        for node in nodes:
            executor.add_node(node)
        executor.spin_until_future_complete(failed)
        if failed.done():
            code = 1  # the refused node logged why; say which one, then stop every sensor
            print(f"cstomo_sensor_host: {failed.result().get_fully_qualified_name()} refused to start: stopping "
                  f"all {len(nodes)} sensors", file=sys.stderr)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        signal.signal(signal.SIGINT, signal.SIG_IGN)  # as the node's main: no traceback from the joins
        for node in nodes:
            node._release()
        for node in nodes:
            node.destroy_node()
        if handler is not None:
            ros_log.detach(handler)
        rclpy.try_shutdown()
    return code


if __name__ == "__main__":
    sys.exit(main())
