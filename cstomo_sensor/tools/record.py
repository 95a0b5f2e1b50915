"""``cstomo record``: the running node's topics to a rosbag2 recording, without a ROS install's
``ros2 bag``: rclpy subscriptions (each topic taken as its publisher offers it, reliable or best
effort) and the ``rosbags`` writer.

Records the node's outputs and its raw frames (``raw_voltages``, which ``cstomo replay`` and
``cstomo calibrate --bag`` read) for ``--seconds`` or until Ctrl-C, each message as published, at
its receive time; ``cstomo plot BAG`` draws the forces. The stress fields are left out unless
``--topics`` names them: subscribing to them makes the node compute its image. The bag is written
beside ``--out`` and moved there when complete; a recording without a single message is not kept.
Ends with one line: the messages per topic.
"""
from __future__ import annotations

import argparse
import shutil
import signal
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

from ..errors import ConfigError, CstomoError
from ..frame_path.outputs import OUTPUTS, TOPIC_TYPES
from .common import ToolParser, bag_typestore, help_text

STORAGES = ("sqlite3", "mcap")
#: The topics recorded unless ``--topics`` says otherwise: every output but the heavy stress fields.
DEFAULT_TOPICS = tuple(n for n in TOPIC_TYPES if not (n in OUTPUTS and OUTPUTS[n].heavy))
DEPTH = 200  # messages kept per subscription while the recorder writes (a bag write is ~20 us)


@dataclass(frozen=True)
class RecordSummary:
    """What a recording holds: messages per full topic name (those with none left out) and its seconds."""

    counts: dict[str, int]
    seconds: float
    missing: tuple[str, ...]

    def line(self, out: str | Path) -> str:
        total = sum(self.counts.values())
        prefix = next(iter(self.counts)).rsplit("/", 1)[0] if self.counts else ""
        parts = ", ".join(f"{t.rsplit('/', 1)[1]} {n}" for t, n in self.counts.items())
        none = f"; nothing on {', '.join(t.rsplit('/', 1)[1] for t in self.missing)}" if self.missing else ""
        return f"recorded {total} messages of {prefix} in {self.seconds:.1f} s to {out}: {parts}{none}"


def _qos_of(node, topic: str):
    """The QoS to subscribe ``topic`` with, from its publishers (None: no publisher yet): reliable
    when every publisher is, else best effort (a reliable subscriber never hears a best-effort one)."""
    from rclpy.qos import QoSProfile, ReliabilityPolicy

    infos = node.get_publishers_info_by_topic(topic)
    if not infos:
        return None
    reliable = all(i.qos_profile.reliability == ReliabilityPolicy.RELIABLE for i in infos)
    return QoSProfile(depth=DEPTH, reliability=ReliabilityPolicy.RELIABLE if reliable else ReliabilityPolicy.BEST_EFFORT)


def record(out: str | Path, node_name: str = "/cstomo_sensor", topics: tuple[str, ...] = DEFAULT_TOPICS,
           seconds: float = 0.0, storage: str = "sqlite3", status=None, stop=None, wait: float = 10.0) -> RecordSummary:
    """Record the topics ``node_name/<topic>`` of the running node into a new rosbag2 ``out`` for
    ``seconds`` from the first message (0: until Ctrl-C, SIGTERM, or ``stop()`` returns True), waiting
    at most ``wait`` s for that first message (0: without end); ``status(text)`` is told the progress
    about once a second. Raises :class:`ConfigError` when nothing was received (no bag kept)."""
    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.signals import SignalHandlerOptions
    from rosbags.rosbag2 import StoragePlugin, Writer  # optional: the [full] extra

    out = Path(out)
    if out.exists():
        raise ConfigError(f"--out {out}: exists; expected a new directory")
    if not out.parent.is_dir():
        raise ConfigError(f"--out {out}: its directory {out.parent} does not exist")
    unknown = [t for t in topics if t not in TOPIC_TYPES]
    if unknown:
        raise ConfigError(f"--topics {unknown}: expected names of {sorted(TOPIC_TYPES)}")
    prefix = "/" + node_name.strip("/") + "/"
    store = bag_typestore()
    plugin = StoragePlugin.MCAP if storage == "mcap" else StoragePlugin.SQLITE3
    work = Path(tempfile.mkdtemp(prefix=f".{out.name}.partial", dir=out.parent))
    partial = work / out.name  # a bag's files are named after its directory
    ctx = rclpy.Context()
    rclpy.init(args=[], context=ctx, signal_handler_options=SignalHandlerOptions.NO)
    counts = {prefix + t: 0 for t in topics}
    previous = signal.signal(signal.SIGTERM, _interrupt)
    try:
        node = rclpy.create_node("cstomo_record", context=ctx)
        executor = SingleThreadedExecutor(context=ctx)
        executor.add_node(node)
        clock = node.get_clock()
        with Writer(partial, version=9, storage_plugin=plugin) as writer:
            conns = {}

            first: list[float] = []  # time.monotonic() of the first message: the recording's clock starts

            def on_msg(topic: str, data: bytes) -> None:
                writer.write(conns[topic], clock.now().nanoseconds, data)
                counts[topic] += 1
                if not first:
                    first.append(time.monotonic())

            pending = dict.fromkeys(counts)  # topics not yet subscribed: each once its publisher shows
            started = time.monotonic()
            next_look = next_say = started

            def going(now: float) -> bool:
                if stop and stop():
                    return False
                if not first:  # discovery takes a few seconds: the --seconds count from the first message
                    return not wait or now - started < wait
                return not seconds or now - first[0] < seconds

            try:
                while going(time.monotonic()):
                    now = time.monotonic()
                    if pending and now >= next_look:
                        for topic in list(pending):
                            qos = _qos_of(node, topic)
                            if qos is not None:
                                msg_type = TOPIC_TYPES[topic[len(prefix):]]
                                conns[topic] = writer.add_connection(topic, msg_type, typestore=store)
                                node.create_subscription(_msg_class(msg_type), topic,
                                                         lambda m, t=topic: on_msg(t, m), qos, raw=True)
                                del pending[topic]
                        next_look = now + 0.5
                    if status is not None and now >= next_say:
                        status(f"recording {now - first[0]:5.1f} s: {sum(counts.values())} messages on "
                               f"{sum(1 for n in counts.values() if n)} of {len(counts)} topics" if first else
                               f"waiting for the node's topics ({now - started:.0f} s)")
                        next_say = now + 1.0
                    executor.spin_once(timeout_sec=0.05)
            except KeyboardInterrupt:
                pass
            elapsed = time.monotonic() - (first[0] if first else started)
            executor.shutdown(timeout_sec=1.0)
            node.destroy_node()
        if not any(counts.values()):
            raise ConfigError(f"no message on {prefix}* in {elapsed:.0f} s: is the node running and active, on this "
                              "ROS_DOMAIN_ID (and ROS_AUTOMATIC_DISCOVERY_RANGE)? nothing written")
        partial.rename(out)
    finally:
        signal.signal(signal.SIGTERM, previous)
        rclpy.try_shutdown(context=ctx)
        shutil.rmtree(work, ignore_errors=True)
    got = {t: n for t, n in counts.items() if n}
    return RecordSummary(got, elapsed, tuple(t for t, n in counts.items() if not n))


def _msg_class(type_name: str):
    from ..ros.sinks import msg_class

    return msg_class(type_name)


def _interrupt(*_: object) -> None:
    raise KeyboardInterrupt


def parser() -> argparse.ArgumentParser:
    """This command's argument parser (cli.subcommand_parser)."""
    p = ToolParser(prog="cstomo record", description=help_text(__doc__.split("\n\n")[0]),
                                epilog=help_text(__doc__.split("\n\n", 1)[1]))
    p.add_argument("--out", required=True, metavar="DIR", help="bag directory to write (must not exist)")
    p.add_argument("--node", default="/cstomo_sensor", metavar="NAME",
                   help="the node's full name, namespace included: its topics are NAME/<topic> (default %(default)s)")
    p.add_argument("--seconds", type=float, default=0.0, metavar="S",
                   help="how long to record, from the first message (default %(default)g: until Ctrl-C)")
    p.add_argument("--wait", type=float, default=10.0, metavar="S",
                   help="how long to wait for the node's first message (finding a node takes a few seconds) "
                        "before giving up; 0: without end (default %(default)g)")
    p.add_argument("--topics", nargs="+", default=list(DEFAULT_TOPICS), metavar="TOPIC",
                   help=f"the node's topics to record, of {', '.join(TOPIC_TYPES)} (default: all but the stress "
                        "fields)")
    p.add_argument("--storage", default="sqlite3", choices=STORAGES, help="the bag's storage (default %(default)s)")
    return p


def main(argv: list[str] | None = None) -> int:
    a = parser().parse_args(argv)
    tty = sys.stderr.isatty()

    def status(text: str) -> None:  # one updating line on a terminal; the end's summary line only otherwise
        print(f"\r{text}", end="", file=sys.stderr, flush=True)

    try:
        if not (0 <= a.seconds < float("inf")):
            raise ConfigError.bad_value("--seconds", a.seconds, "seconds >= 0 (0: until Ctrl-C)")
        if not (0 <= a.wait < float("inf")):
            raise ConfigError.bad_value("--wait", a.wait, "seconds >= 0 (0: without end)")
        print(f"recording {a.node.rstrip('/')}/* to {a.out}" + (f" for {a.seconds:g} s from the first message"
              if a.seconds else "") + "; Ctrl-C stops", file=sys.stderr, flush=True)
        s = record(a.out, a.node, tuple(dict.fromkeys(a.topics)), a.seconds, a.storage, status if tty else None,
                   wait=a.wait)
    except ImportError as err:
        from ..errors import install_hint

        print(("\n" if tty else "") + f"cstomo record: error: {err.name or err} is missing: {install_hint(err.name)}",
              file=sys.stderr)
        return 2
    except (CstomoError, OSError) as err:
        print(("\n" if tty else "") + f"cstomo record: error: {err}", file=sys.stderr)
        return 2
    if tty:
        print("", file=sys.stderr)
    print(s.line(a.out))
    return 0


if __name__ == "__main__":
    sys.exit(main())
