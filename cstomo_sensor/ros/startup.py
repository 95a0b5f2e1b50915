"""The node's entry point and its helpers: ``--help`` (:func:`usage`), the parameters' checks before
the node starts (:func:`as_double`, :func:`refuse_unknown`, :func:`check_inputs`), ``rclpy.init`` on a
command line (:func:`init_ros`), ``cstomo_sensor_node``'s :func:`main` and the one-line cause of a
refused configure (:func:`failure_cause`); shared by :mod:`.node` and :mod:`.host`.
"""
from __future__ import annotations

import difflib
import os
import signal
import sys

import rclpy
from rclpy._rclpy_pybind11 import RCLError
from rclpy.exceptions import InvalidParameterTypeException, InvalidParameterValueException
from rclpy.executors import ExternalShutdownException, MultiThreadedExecutor
from rclpy.parameter import Parameter

from ..errors import ConfigError, CstomoError
from ..frame_path.outputs import help_lines
from ..settings import SETTING
from .params import PARAMETERS

NODE_DOC = "cstomo_sensor_node: the sensor's managed (lifecycle) ROS 2 node, publishing the joint's force."


def failure_cause(err: BaseException) -> str:
    """One line naming what failed at configure and what to do."""
    if isinstance(err, CstomoError):
        return str(err)
    if isinstance(err, ImportError):
        from ..errors import install_hint

        return (f"missing optional dependency '{err.name or err}' ({err}): {install_hint(err.name)}; "
                "or choose settings that do not need it")
    if isinstance(err, OSError):
        where = f"{err.filename}: " if err.filename else ""
        return f"{where}{err.strerror or err} ({type(err).__name__}): check the file or device and its permissions"
    return f"{type(err).__name__}: {err} (unexpected: please report it with the debug log)"


#: Parameters rclpy declares later (QoS overrides of publishers): not unknown to the node.
_RCLPY_PREFIXES = ("qos_overrides.",)


def as_double(p: Parameter) -> Parameter:
    """An integer given for a parameter whose default is a float, as that float (``rate_hz:=200``)."""
    default = PARAMETERS.get(p.name, (None,))[0]
    if isinstance(default, float) and p.type_ == Parameter.Type.INTEGER:
        return Parameter(p.name, Parameter.Type.DOUBLE, float(p.value))
    return p


def declare_all(node, overrides: dict) -> None:
    """Declare every parameter; an override rclpy refuses (out of the declared range, of another
    type) is refused in the words of every other refusal, :class:`ConfigError` ``parameter
    'rate_hz'=-5.0: expected 0..10000 frames/s`` (rclpy's own names the value, then the parameter)."""
    for name, (default, desc) in PARAMETERS.items():
        try:
            node.declare_parameter(name, default, desc)
        except (InvalidParameterTypeException, InvalidParameterValueException) as err:
            value = overrides[name].value if name in overrides else None
            SETTING[name].check(value)  # raises the one-line refusal
            raise ConfigError(f"parameter '{name}'={value!r}: {err}") from None


def build_progress(context, log):
    """``Pipeline.build``'s progress callback: each step logged; a shutdown (SIGINT/SIGTERM) during a
    long first build stops it at its next step instead of after it."""
    def progress(msg: str) -> None:
        if not context.ok():
            raise RuntimeError("shut down while the model was being built")
        log.info(f"model: {msg}")
    return progress


def refuse_unknown(node, overrides: dict) -> None:
    """A parameter given to the node (file, launch, -p) that it does not have is a mistake
    (``tare_on_star``): refused with the nearest known name."""
    unknown = sorted(n for n in overrides if n not in PARAMETERS and not n.startswith(_RCLPY_PREFIXES)
                     and not node.has_parameter(n))
    if unknown:
        hints = []
        for n in unknown:
            near = difflib.get_close_matches(n, list(PARAMETERS), n=1)
            hints.append(f"'{n}'" + (f" (did you mean '{near[0]}'?)" if near else ""))
        raise ConfigError(f"unknown parameter{'s' if len(hints) > 1 else ''} {', '.join(hints)}: expected names "
                          f"from config/cstomo_sensor.yaml ({', '.join(PARAMETERS)})")


def usage() -> str:
    """``cstomo_sensor_node --help``: how to run it, what it publishes and every parameter with its default."""
    lines = ["usage: cstomo_sensor_node [-h] [--ros-args [-p NAME:=VALUE ...] [--params-file FILE] [-r __ns:=/NS]]",
             "", NODE_DOC, "", "publishes (in the node's namespace):"]
    lines += help_lines()
    lines += [f"  {'/diagnostics':<21} diagnostic_msgs/DiagnosticArray, status named '<namespace>/<node>: sensor'",
              "services:", f"  {'~/tare':<21} std_srvs/Trigger: a new reference on the next tare_frames frames "
              "(refused under load)", f"  {'~/tare_forced':<21} std_srvs/Trigger: the same, taken even when it looks "
              "loaded (the answer says what it overrode)",
              "subscribes:", f"  {'~/joint_free':<21} std_msgs/Empty: a controller's hint that the joint is free "
              "now: re-zero at once (a tare with its rules, refused under load)",
              f"  {'~/expected_wrench':<21} geometry_msgs/WrenchStamped: the load a controller expects now (to "
              "expected_wrench_sigma), a measurement of the device's change under load",
              f"  {'~/raw_voltages_in':<21} sensor_msgs/Image, as ~/raw_voltages (input: topic)",
              "(docs/node.md)", "", "parameters (default):"]
    width = max(map(len, PARAMETERS))
    for name, (default, desc) in PARAMETERS.items():
        lines.append(f"  {name:<{width}} {default!r:<16} {desc.description}")
    return "\n".join(lines)


def own_args(argv: list[str] | None) -> tuple[list[str], list[str]]:
    """(the whole command line, the arguments before ``--ros-args``) of an entry point."""
    argv = list(argv if argv is not None else sys.argv)
    return argv, argv[1:argv.index("--ros-args")] if "--ros-args" in argv else argv[1:]


#: The parameter file of an install, as a shell finds it from any directory.
INSTALLED_CONFIG = "$(ros2 pkg prefix cstomo_sensor)/share/cstomo_sensor/config/cstomo_sensor.yaml"


def init_ros(prog: str, argv: list[str]) -> bool:
    """``rclpy.init`` on an entry point's command line; False, having said why in one line on stderr
    (no traceback), when it cannot: a ``--params-file`` that cannot be read (checked first, as rcl's
    own error names neither the directory nor the installed file), or arguments rcl refuses."""
    ros = argv[argv.index("--ros-args"):] if "--ros-args" in argv else []
    for flag, path in zip(ros, ros[1:]):
        if flag == "--params-file" and not (os.path.isfile(path) and os.access(path, os.R_OK)):
            where = "" if os.path.isabs(path) else f" in {os.getcwd()}"
            print(f"{prog}: --params-file {path}: no such readable file{where} (the installed one: "
                  f"{INSTALLED_CONFIG})", file=sys.stderr)
            return False
    try:
        rclpy.init(args=argv)
    except RCLError as err:
        print(f"{prog}: {err}", file=sys.stderr)
        return False
    return True




def check_inputs(cfg, geometry, namespace: str):
    """Refuse, before any model is built, what cannot work (:class:`ConfigError`, one line each): a
    port that is no device, a ``virtual://`` board no part of this process holds, an unwritable model
    cache, a tare file that cannot be saved (a node that cannot would re-tare under any load at every
    restart). Returns the tare file's path."""
    from ..board.driver import check_port
    from ..board.links import holds, is_virtual
    from ..cache import check_writable

    if cfg.input == "serial":
        check_port(cfg.port)  # a file or a directory is no board: said once, not retried for ever
        if is_virtual(cfg.port) and not holds(cfg.port):  # nothing outside this process can make one
            raise ConfigError(f"port {cfg.port!r}: no simulated board of this process holds it (virtual:// "
                              "serves a board made in the node's own process: tests, benchmarks); expected "
                              "a serial device")
    check_writable(cfg.cache_path)  # at once, not after a long model build
    tare_path = cfg.tare_path_for(geometry, namespace)
    check_writable(tare_path.parent, f"the tare file {tare_path}: its directory",
                   "set the parameter 'tare_file' to a path in a writable directory")
    if tare_path.is_dir():
        raise ConfigError(f"parameter 'tare_file'={str(tare_path)!r}: a directory; expected a file path")
    return tare_path


def link_warnings(cfg) -> list[str]:
    """What the node warns about its serial link's settings."""
    from ..board.wire import DATA_WIRE_BYTES, link_frame_rate

    out = []
    if cfg.protocol == "text":
        out.append("protocol 'text' has no checksum: a corrupted line that still parses is taken as "
                   "a frame (only the plausibility gate guards it); use 'binary' (CRC-32) if the board can")
    carried = link_frame_rate(cfg.baudrate)
    if cfg.protocol == "binary" and cfg.rate_hz > carried:
        out.append(f"rate_hz {cfg.rate_hz:g} exceeds what baudrate {cfg.baudrate} carries: at most "
                   f"{carried:.0f} DATA frames/s of {DATA_WIRE_BYTES} bytes (8N1), so a UART link lags and "
                   f"loses frames; use baudrate >= {cfg.rate_hz * 10 * DATA_WIRE_BYTES:.0f} or a USB CDC "
                   "board (which ignores the baud rate: then this warning does not apply); docs/protocol.md")
    return out


def main(node_class, argv: list[str] | None = None) -> int:
    """``cstomo_sensor_node`` (``ros2 run cstomo_sensor cstomo_sensor_node``) with the node ``node_class``."""
    argv, own = own_args(argv)
    if "-h" in own or "--help" in own:
        print(usage())
        return 0
    if not init_ros("cstomo_sensor_node", argv):
        return 2
    node, code = None, 0
    try:  # once rclpy is up, a Ctrl-C is the node's normal end (exit 0), also before it spins
        node = node_class()
        executor = MultiThreadedExecutor(num_threads=2)
        executor.add_node(node)
        executor.spin_until_future_complete(node.autostart_failed)
        if node.autostart_failed.done():
            code = 1  # configure refused (the log says why); the parameters are read-only: restart needed
    except ConfigError as err:  # overrides refused
        print(f"cstomo_sensor_node: {err}", file=sys.stderr)
        code = 2
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        # a second Ctrl-C (or the one rclpy's handler passes on just after shutting the context
        # down) must not interrupt the joins below with a KeyboardInterrupt traceback
        signal.signal(signal.SIGINT, signal.SIG_IGN)
        if node is not None:
            node._release()
            node.destroy_node()
        rclpy.try_shutdown()
    return code
