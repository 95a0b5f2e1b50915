"""The console scripts setup.py installs: ``cstomo``, ``cstomo_sensor_node`` and ``cstomo_sensor_host``.

Each loads its module only when called, inside one guard: a Ctrl-C that the command does not handle
itself (while rclpy, numpy and scipy still load, a second or more on a busy computer, or in the middle of
a long ``cstomo bench``) ends the process with one line and exit status 130 (the shell's 128 + SIGINT),
not with a traceback of whatever line it interrupted. A running node handles its own Ctrl-C and exits 0,
as before.
"""
from __future__ import annotations

import importlib
import os
import sys

#: The exit status of a command stopped by a Ctrl-C it did not handle: 128 + SIGINT, as a shell reports it.
INTERRUPTED = 130


def _run(module: str) -> None:
    try:
        code = importlib.import_module(module).main()
    except KeyboardInterrupt:
        print(f"{os.path.basename(sys.argv[0])}: stopped by Ctrl-C", file=sys.stderr)
        code = INTERRUPTED
    sys.exit(code)


def cstomo() -> None:
    """``cstomo``: the command line (:mod:`cstomo_sensor.tools.cli`)."""
    _run("cstomo_sensor.tools.cli")


def node() -> None:
    """``cstomo_sensor_node`` (:mod:`cstomo_sensor.ros.node`)."""
    _run("cstomo_sensor.ros.node")


def host() -> None:
    """``cstomo_sensor_host`` (:mod:`cstomo_sensor.ros.host`)."""
    _run("cstomo_sensor.ros.host")
