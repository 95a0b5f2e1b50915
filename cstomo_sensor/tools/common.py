"""What the command-line tools share: the flags that mirror a node setting, the ROS environment of
the tools that start rclpy, finding the package's executables, and starting the node together with
a simulated board (what a launch starts is decided in :mod:`.launching`).

A flag that mirrors a node setting takes its default, choices, range and help from the setting's one
declaration (:mod:`cstomo_sensor.settings`, :func:`add_setting_arg`); every length is in metres, as
in the node's parameters and the files.
"""
from __future__ import annotations

import argparse
import atexit
import contextlib
import logging
import math
import os
import shutil
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import IO

import yaml

from ..errors import CstomoError
from ..frame_path.config import PipelineConfig
from ..settings import SETTING, text_of

_SAME = object()


class HelpFormatter(argparse.RawDescriptionHelpFormatter):
    """The ``--help`` of every ``cstomo`` command: descriptions as written, and every option's help
    ending with its default (``(default: X)``) unless the help says its default itself; options
    without a value (``--flag``), required ones and those whose default is None show none."""

    def _get_help_string(self, action: argparse.Action) -> str:
        text = action.help or ""
        if ("default" in text.lower() or action.required or any(action.default is v for v in (None, False, argparse.SUPPRESS))
                or not action.option_strings or action.nargs == 0 and not isinstance(action, argparse.BooleanOptionalAction)):
            return text
        return f"{text} (default: {_shown(action.default)})".lstrip()


def _shown(value: object) -> str:
    """A default as a person types it: ``8 8 4`` for a list, ``''`` for the empty string."""
    if isinstance(value, (list, tuple)):
        return " ".join(map(str, value))
    if isinstance(value, bool):
        return str(value).lower()
    return "''" if value == "" else str(value).replace("%", "%%")


class ToolParser(argparse.ArgumentParser):
    """The argument parser of a ``cstomo`` command: :class:`HelpFormatter`, and :meth:`fail`, the one
    error line of every command, ``PROG: error: ...`` as argparse's own (its subparsers are ToolParsers too).
    A ``description`` given as a function is written when the help is asked for: building the parser
    loads nothing that only the help needs."""

    def __init__(self, *args, **kwargs) -> None:
        kwargs.setdefault("formatter_class", HelpFormatter)
        super().__init__(*args, **kwargs)

    def format_help(self) -> str:
        if callable(self.description):
            self.description = self.description()
        return super().format_help()

    def error(self, message: str):
        """A bad command line: one line, ``PROG: error: MESSAGE``, exit 2 (argparse's own adds the usage).
        No command given (``cstomo``, ``cstomo model``): the commands it expects, not argparse's
        ``the following arguments are required: cmd``."""
        for action in self._actions:
            if (isinstance(action, argparse._SubParsersAction)
                    and message == f"the following arguments are required: {action.metavar or action.dest}"):
                message = f"no command given; expected one of {', '.join(action.choices)} ({self.prog} --help)"
        self.exit(2, f"{self.prog}: error: {message}\n")

    def fail(self, err: object, code: int = 2) -> int:
        """Print ``PROG: error: ERR`` on stderr; ``code``."""
        print(f"{self.prog}: error: {err}", file=sys.stderr, flush=True)
        return code


def positive(what: str = "a number > 0", *, zero: bool = False, kind: type = float):
    """An argparse ``type`` for a finite number > 0 (>= 0 with ``zero``), refused at parsing as
    ``argument --flag: VALUE: expected WHAT``."""

    def parse(word: str):
        try:
            v = kind(word)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{word!r}: expected {what}") from None
        if not (v >= 0 if zero else v > 0) or not math.isfinite(v):
            raise argparse.ArgumentTypeError(f"{word}: expected {what}")
        return v

    parse.__name__ = what
    return parse


#: A command prints one log message (one template of one logger) at most this many times; then it
#: counts the rest and says how many at its end (:class:`RepeatFilter`).
MAX_REPEATS = 3


class RepeatFilter(logging.Filter):
    """Lets at most :data:`MAX_REPEATS` records of each message template (logger and format string,
    whatever its arguments) through; :meth:`summary` says what was held back. A benchmark that runs
    hundreds of streams would otherwise print each stream's own once-per-run message hundreds of times."""

    def __init__(self, limit: int = MAX_REPEATS, level: int = logging.NOTSET) -> None:
        super().__init__()
        self.limit = limit
        self.level = level  # records below it are not shown, so not counted either
        self.seen: dict[tuple[str, str], int] = {}

    def filter(self, record: logging.LogRecord) -> bool:
        if getattr(record, "progress", None) is not None:  # a progress line updates itself
            return True
        if record.levelno < self.level:
            return False
        key = (record.name, str(record.msg))
        self.seen[key] = self.seen.get(key, 0) + 1
        return self.seen[key] <= self.limit

    def say(self) -> None:
        """Print :meth:`summary` on stderr (at the command's end)."""
        for line in self.summary():
            print(f"(log) {line}", file=sys.stderr)

    def summary(self) -> list[str]:
        """One line per message held back: its template and how often it came."""
        return [f"{name.partition('.')[2] or name}: {msg!r} came {n} times; the {n - self.limit} after the first "
                f"{self.limit} not shown" for (name, msg), n in self.seen.items() if n > self.limit]


class _ToolHandler(logging.StreamHandler):
    """stderr for a command: records at ``level`` and above; progress records (``extra={"progress":
    (i, n)}``, :mod:`cstomo_sensor.progress`) as one line updated in place on a terminal, none
    elsewhere (a log file, CI)."""

    def __init__(self, level: int) -> None:
        super().__init__(sys.stderr)
        self.threshold = level
        self.tty = sys.stderr.isatty()
        self.open_line = False  # a progress line is on the terminal, not yet ended

    def emit(self, record: logging.LogRecord) -> None:
        progress = getattr(record, "progress", None)
        if progress is None and record.levelno < self.threshold:
            return
        if progress is not None and not self.tty:
            return
        try:
            if progress is not None:
                i, n = progress
                self.stream.write(f"\r{record.getMessage()}\x1b[K" + ("\n" if i >= n else ""))
                self.open_line = i < n
            else:
                if self.open_line:
                    self.stream.write("\n")
                    self.open_line = False
                self.stream.write(self.format(record) + "\n")
            self.flush()
        except Exception:  # noqa: BLE001 - logging must never raise into the code that logs
            self.handleError(record)


def setup_logging(verbose: bool = False, fmt: str = "%(levelname)s %(name)s: %(message)s",
                  force: bool = False) -> RepeatFilter:
    """The log of a ``cstomo`` command on stderr: WARNING and above (INFO with ``verbose``), each
    message at most :data:`MAX_REPEATS` times, what was held back said once at the process's end;
    progress of long steps as one updating line on a terminal (:class:`_ToolHandler`). As
    :func:`logging.basicConfig`, nothing is changed when the root logger has handlers of another's
    (a program or a test harness that calls the command's ``main``), unless ``force``."""
    level = logging.INFO if verbose else logging.WARNING
    handler = _ToolHandler(level)
    handler.setFormatter(logging.Formatter(fmt))
    repeats = RepeatFilter(level=level)
    handler.addFilter(repeats)
    root = logging.getLogger()
    if not force and any(not getattr(h, "_cstomo", False) for h in root.handlers):
        return repeats
    for old in [h for h in root.handlers if getattr(h, "_cstomo", False)]:
        root.removeHandler(old)
    handler._cstomo = True
    root.addHandler(handler)
    root.setLevel(logging.INFO)  # the handler decides: progress records are INFO
    atexit.register(repeats.say)
    return repeats


@contextlib.contextmanager
def ticking(what: str, stream: IO | None = None, every: float = 1.0):
    """While the block runs, ``WHAT: N s`` updated in place every ``every`` s on a terminal (nothing
    when ``stream``, default stdout, is not one): a wait on another process that says nothing itself."""
    stream = stream or sys.stdout
    if not stream.isatty():
        yield
        return
    done = threading.Event()
    t0 = time.monotonic()

    def tick() -> None:
        while not done.wait(every):
            stream.write(f"\r{what}: {time.monotonic() - t0:.0f} s\x1b[K")
            stream.flush()

    thread = threading.Thread(target=tick, daemon=True)
    thread.start()
    try:
        yield
    finally:
        done.set()
        thread.join()
        if time.monotonic() - t0 >= every:
            stream.write(f"\r{what}: done in {time.monotonic() - t0:.0f} s\x1b[K\n")
            stream.flush()


#: The short value name (metavar) of a setting's flag that takes a string.
_METAVARS = {"sensor": "NAME", "cache_dir": "DIR", "calibration_file": "FILE", "tare_file": "FILE", "port": "URL",
             "frame_id": "FRAME"}


def help_text(doc: str) -> str:
    """A docstring as ``--help`` shows it: reST's double backquotes as single ones."""
    return doc.replace("``", "`")


def add_setting_arg(p: argparse.ArgumentParser, name: str, *, flag: str | None = None, default=_SAME,
                    note: str = "") -> argparse.Action:
    """The flag (``--name-with-dashes`` unless ``flag``) of node setting ``name``: its default (or
    ``default``), choices, range (a value outside is refused naming the flag) and description as
    its help, then ``note``; a boolean one is ``--name``/``--no-name``. ``dest`` is ``name``."""
    s = SETTING[name]
    flag = flag or "--" + name.replace("_", "-")
    value = s.default if default is _SAME else default
    text = s.description.replace("%", "%%") + (f" ({s.range})" if s.range and not s.choices else "")
    text += f"; default {text_of(value) if value is not None else 'none'}" + (f"; {note}" if note else "")
    if isinstance(s.default, bool):
        return p.add_argument(flag, dest=name, default=value, action=argparse.BooleanOptionalAction, help=text)

    def parse(word: str):
        try:
            return s.parse(word)
        except ValueError as err:
            raise argparse.ArgumentTypeError(str(err)) from None

    parse.__name__ = name  # argparse's message names it
    kind = {"nargs": len(s.default), "default": list(value)} if isinstance(s.default, tuple) else {"default": value}
    metavar = ("NX", "NY", "NZ") if name == "grid" else None if s.choices else _METAVARS.get(name) or (
        "N" if isinstance(s.default, int) else "X" if isinstance(s.default, float) else "VALUE")
    return p.add_argument(flag, dest=name, type=None if s.choices else parse, choices=s.choices or None, help=text,
                          metavar=metavar, **kind)


def add_pipeline_args(p: argparse.ArgumentParser, estimator: bool = True) -> None:
    """``--sensor --mesh-size --grid --iterations --damping --cache-dir`` (and ``--estimator
    --calibration --max-force``): the node's settings of the same names."""
    for name in ("sensor", "mesh_size", "grid", "iterations", "damping", "cache_dir"):
        add_setting_arg(p, name)
    if estimator:
        add_setting_arg(p, "estimator")
        add_setting_arg(p, "calibration_file", flag="--calibration")
        add_setting_arg(p, "max_force")


def add_creep_arg(p: argparse.ArgumentParser) -> None:
    """``--creep-per-decade``: the stream's creep compensation, as the node's ``creep_per_decade``."""
    add_setting_arg(p, "creep_per_decade", note="`cstomo estimate` turns it off on frames that are not one "
                                                "recording in time")


def pipeline_config(a: argparse.Namespace) -> PipelineConfig:
    """The :class:`PipelineConfig` of parsed :func:`add_pipeline_args` flags (validated there)."""
    return PipelineConfig(**{name: getattr(a, name) for name in PipelineConfig.__dataclass_fields__
                             if hasattr(a, name)})


def local_ros_env(domain_base: int) -> None:
    """Keep DDS on this host (and on a domain of its own unless the caller chose one) for a tool
    that starts rclpy or ROS processes: ``domain_base`` .. ``domain_base`` + 69, at most 101 (above 101 a domain's
    DDS ports fall among Linux's ephemeral ports)."""
    os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
    os.environ.setdefault("ROS_DOMAIN_ID", str(domain_base + os.getpid() % 70))


PACKAGE = "cstomo_sensor"


def package_prefixes(package: str = PACKAGE) -> list[Path]:
    """The ``AMENT_PREFIX_PATH`` prefixes that hold ``package`` (its ament index entry), in order."""
    return [Path(prefix) for prefix in os.environ.get("AMENT_PREFIX_PATH", "").split(os.pathsep)
            if prefix and (Path(prefix) / "share" / "ament_index" / "resource_index" / "packages" / package).is_file()]


def package_executable(package: str, name: str) -> str | None:
    """``<prefix>/lib/<package>/<name>`` of the first prefix holding ``package``, where ``ros2 run`` and
    launch_ros's nodes find an executable, or None if it is not there."""
    prefixes = package_prefixes(package)
    place = prefixes[0] / "lib" / package / name if prefixes else None
    return str(place) if place is not None and place.is_file() and os.access(place, os.X_OK) else None


def executable(name: str) -> str:
    """Path of one of the package's console scripts: in a colcon install ``<prefix>/lib/cstomo_sensor/``
    (prefixes from ``AMENT_PREFIX_PATH`` that hold the package), else beside the running interpreter
    (a virtual environment), else on ``PATH``. Raises :class:`CstomoError` naming where it looked."""
    places = [prefix / "lib" / PACKAGE / name for prefix in package_prefixes()]
    places.append(Path(sys.executable).parent / name)
    for place in places:
        if place.is_file() and os.access(place, os.X_OK):
            return str(place)
    found = shutil.which(name)
    if found:
        return found
    raise CstomoError(f"executable {name!r} not found in {[str(p) for p in places]} nor on PATH: "
                      "install the package (pip install . or colcon build) and source its set-up")


def bag_typestore():
    """The rosbags type store of the bags the tools write and read (ROS 2 Kilted's, else the newest)."""
    from rosbags.typesys import Stores, get_typestore  # optional: the [full] extra

    return get_typestore(getattr(Stores, "ROS2_KILTED", None) or Stores.LATEST)


def package_file(path: str) -> tuple[Path | None, list[Path]]:
    """(the file ``path``, or None; the places looked): ``path`` as given (a relative one from the
    current directory), else relative to the installed package's share directory
    (``<prefix>/share/cstomo_sensor/``), so ``config/sensors_example.yaml`` names the installed
    example from anywhere."""
    given = Path(path).expanduser()
    places = [given] if given.is_absolute() else [Path.cwd() / given] + [p / "share" / PACKAGE / given
                                                                         for p in package_prefixes()]
    return next((p for p in places if p.is_file()), None), places


def config_parameter(config_file: str | Path, name: str) -> object | None:
    """The value of node parameter ``name`` in a ROS parameter file (any node key, e.g.
    ``/**/cstomo_sensor``), or None if the file does not set it."""
    with open(config_file, encoding="utf-8") as f:
        doc = yaml.safe_load(f) or {}
    for section in doc.values():
        params = section.get("ros__parameters", {}) if isinstance(section, dict) else {}
        if name in params:
            return params[name]
    return None


class NodeWithBoard:
    """``cstomo_sensor_node`` and ``cstomo board-sim`` on one pty link, as subprocesses.

    The board is started first (it computes its loads, then prints its device), then the node on its
    link; :meth:`start` returns the board's device path. :meth:`stop` (and leaving a ``with`` block)
    sends SIGINT to the node first, so it does not report the board's end as a lost port, then to
    the board, and kills what has not ended after 5 s.

    Parameters
    ----------
    link : path
        The symlink the board keeps pointing at its pty; the node's ``port``.
    node_params : dict
        ``-p name:=value`` parameters of the node besides ``port``.
    board_args : list of str
        Arguments of ``cstomo board-sim`` besides ``--link``.
    node_out, board_err : file or None
        Where the node's output and the board's stderr go (None: this process's).
    namespace : str
        The node's namespace (``-r __ns:=``); '' keeps the root namespace.
    """

    def __init__(self, link: str | Path, node_params: dict, board_args: list[str], node_out: IO | None = None,
                 board_err: IO | None = None, log_level: str = "warn", namespace: str = "") -> None:
        self.link = str(link)
        self.node_cmd = [executable("cstomo_sensor_node"), "--ros-args", "-p", f"port:={self.link}"]
        for k, v in node_params.items():
            self.node_cmd += ["-p", f"{k}:={v}"]
        if namespace:
            self.node_cmd += ["-r", f"__ns:={namespace}"]
        self.node_cmd += ["--log-level", log_level]
        self.board_cmd = [executable("cstomo"), "board-sim", *board_args, "--link", self.link]
        self.node_out, self.board_err = node_out, board_err
        self.node: subprocess.Popen | None = None
        self.board: subprocess.Popen | None = None

    def start_board(self) -> None:
        """Start the board alone (it computes its loads meanwhile; its script starts at the node's START)."""
        # sessions of their own: a terminal's Ctrl-C reaches the caller only, which stops them in order
        if self.board is None:
            self.board = subprocess.Popen(self.board_cmd, stdout=subprocess.PIPE, stderr=self.board_err, text=True,
                                          start_new_session=True)

    def start(self) -> str:
        """Start the board (unless :meth:`start_board` did), wait for its device, then start the node
        on its link (so the node never finds the link missing); the board's device path. Raises
        :class:`CstomoError` if the board fails."""
        device = self.wait_device()
        self.node = subprocess.Popen(self.node_cmd, stdout=self.node_out, start_new_session=True,
                                     stderr=subprocess.STDOUT if self.node_out is not None else None)
        return device

    def wait_device(self) -> str:
        """Start the board (unless :meth:`start_board` did) and wait for its device path (its link
        exists from then on). Raises :class:`CstomoError` if the board fails."""
        self.start_board()
        first = self.board.stdout.readline().strip()
        if not first.startswith("device:"):
            raise CstomoError(f"board-sim failed to start ({first!r})")
        return first.split(":", 1)[1].strip()

    def wait_streaming(self) -> float | None:
        """Block until the board's load script starts (the node has connected and sent START); the
        script's t = 0 on the system clock (the node's ROS clock, so a wrench stamped s measured the
        script at s - t0), None if the board did not say. Raises :class:`CstomoError` if the board
        ends first."""
        line = self.board.stdout.readline().strip()
        word, _, rest = line.partition(" ")
        if word != "streaming":
            raise CstomoError(f"board-sim ended before streaming ({line!r})")
        try:
            return float(rest.partition("t0=")[2])
        except ValueError:
            return None

    def stop(self) -> None:
        interrupt([self.node, self.board])  # one after the other: the node ends before its board

    def __enter__(self) -> NodeWithBoard:
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()


#: What SIGINT is left to when a command that handles it itself ends (:func:`restore_signals`): None, the handler
#: the command replaced (a command called in-process, e.g. by the tests), or ``signal.SIG_IGN`` in the `cstomo`
#: process (cli.main: once its command is done the process only exits, and a late SIGINT must not turn that exit
#: into a death by SIGINT or a KeyboardInterrupt traceback; ros2 launch sends its own after the group's Ctrl-C).
SIGINT_AFTER_COMMAND = None


def restore_signals(previous: dict) -> None:
    """Put back the handlers a command replaced (``previous``: signal -> handler), SIGINT as
    :data:`SIGINT_AFTER_COMMAND` says: a command that ignores SIGINT once it begins stopping leaves it ignored
    in the `cstomo` process, with no moment between its own handler and the process's (a SIGINT is held
    back from this thread while its handler changes: one arriving meanwhile is discarded by ``SIG_IGN``)."""
    for sig, handler in previous.items():
        if sig == signal.SIGINT and SIGINT_AFTER_COMMAND is not None:
            held = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})
            try:
                signal.signal(sig, SIGINT_AFTER_COMMAND)
            finally:
                signal.pthread_sigmask(signal.SIG_SETMASK, held)
        else:
            signal.signal(sig, handler)


def interrupt(procs: list, timeout: float = 5.0) -> None:
    """Stop processes one after the other (in the list's order) as Ctrl-C does, killing one that has
    not ended within ``timeout`` s; None and ended ones are skipped."""
    for p in procs:
        if p is not None and p.poll() is None:
            p.send_signal(signal.SIGINT)
            try:
                p.wait(timeout)
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait()
