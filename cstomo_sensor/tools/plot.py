"""``cstomo plot``: the forces over time as a picture (PNG, drawn off screen): estimated beside true,
with the estimate's 1-sigma band.

The estimated forces come from a forces file (``cstomo estimate --out``, ``cstomo replay --forces``),
from a rosbag2 recording of the node's ``wrench`` and ``wrench_sigma`` topics (``cstomo record``,
``cstomo replay --out``) or from the running node (``--live``: its topics for ``--seconds``). The true
forces, optional, from a forces file (``truth.csv`` of ``cstomo simulate``) or, in a bag, a reference
sensor's wrench topic. Six panels: fx, fy, fz, the magnitude, the elevation and the azimuth (degrees,
computed from the force components as in docs/physics.md#force-angles). The band is the published
per-axis 1-sigma (``wrench_sigma``); a forces file holds only ``sigma_n``, the rms of the error's norm,
which bounds each axis' 1-sigma from above and is drawn as the band of every panel. An estimate below
2 sigma_n shows no direction, and no azimuth when its horizontal part is below 2 sigma_n.
"""
from __future__ import annotations

import argparse
import io
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..angles import force_angles
from ..errors import ConfigError, CstomoError
from ..frames_io import atomic_write, check_out_file, read_forces_table
from .common import ToolParser, bag_typestore, help_text

#: An estimate is shown without a direction when its magnitude is below this many times its 1-sigma
#: ``sigma_n`` (the rms of its error's norm): its direction is then the noise's.
DIRECTION_SIGMAS = 2.0
NODE_WRENCH = "/cstomo_sensor/wrench"
BIG_FILE, BIG_SERIES = 2_000_000, 20_000  # bytes, forces: said before reading, before drawing
WRENCH_TYPE, VECTOR_TYPE = "geometry_msgs/msg/WrenchStamped", "geometry_msgs/msg/Vector3Stamped"


@dataclass
class Forces:
    """Forces over time: ``t`` (n,) in seconds (frames when ``unit`` is ``'frame'``), ``force`` (n, 3) N
    (NaN: no force), and their 1-sigma: ``sigma`` (n, 3) per axis, or only ``sigma_n`` (n,) the norm's
    (either or both None: unknown)."""

    t: np.ndarray
    force: np.ndarray
    sigma: np.ndarray | None = None
    sigma_n: np.ndarray | None = None
    unit: str = "s"

    def band(self) -> np.ndarray | None:
        """(n, 4) the 1-sigma of fx, fy, fz and |F| (per axis when known, else ``sigma_n``), or None."""
        if self.sigma is not None:
            mag = np.linalg.norm(self.force, axis=1)
            unit = self.force / np.where(mag > 0, mag, np.nan)[:, None]  # a diagonal covariance projected
            s_mag = np.sqrt(np.nansum((unit * self.sigma) ** 2, axis=1))
            return np.column_stack([self.sigma, np.where(mag > 0, s_mag, np.linalg.norm(self.sigma, axis=1))])
        if self.sigma_n is not None:
            return np.repeat(self.sigma_n[:, None], 4, axis=1)
        return None

    def norm_sigma(self) -> np.ndarray:
        """(n,) sigma_n (from the per-axis sigma when that is what is known; 0 when unknown)."""
        if self.sigma_n is not None:
            return np.nan_to_num(self.sigma_n)
        if self.sigma is not None:
            return np.linalg.norm(self.sigma, axis=1)
        return np.zeros(len(self.t))


def angles_deg(f: Forces) -> tuple[np.ndarray, np.ndarray]:
    """(elevation, azimuth) in degrees of ``f``'s forces; NaN where the direction is within the noise
    (magnitude below :data:`DIRECTION_SIGMAS` sigma_n, or zero) and, for the azimuth, where the
    horizontal part is (or the force is vertical)."""
    mag, el, az = force_angles(np.nan_to_num(f.force))
    h = np.hypot(f.force[:, 0], f.force[:, 1])
    s = DIRECTION_SIGMAS * f.norm_sigma()
    no_dir = ~(mag > np.maximum(s, 1e-12)) | np.isnan(f.force).any(axis=1)
    el = np.where(no_dir, np.nan, np.degrees(el))
    az = np.where(no_dir | ~(h > np.maximum(s, 1e-6 * mag)), np.nan, np.degrees(az))
    return el, az


def from_csv(path: str | Path, rate: float | None = None) -> Forces:
    """A forces file's forces: on its ``time`` column if it has one, else its ``frame`` numbers (its
    rows' order without) divided by ``rate`` (frames per second; None: on frames)."""
    force, cols = read_forces_table(path)
    if "time" in cols and not np.isnan(cols["time"]).any():
        return Forces(cols["time"], force, None, cols.get("sigma_n"))
    frame = cols["frame"] if "frame" in cols and not np.isnan(cols["frame"]).any() else np.arange(len(force), dtype=float)
    if rate is None:
        return Forces(frame, force, None, cols.get("sigma_n"), unit="frame")
    return Forces(frame / rate, force, None, cols.get("sigma_n"))


def wrench_topic_of(topics: dict[str, str], given: str | None, path) -> str:
    """The estimated wrench's topic of a bag (``topics``: name -> type): ``given``, else the one
    WrenchStamped topic ending in ``cstomo_sensor/wrench`` (the node's, in any namespace)."""
    if given is not None:
        if topics.get(given) != WRENCH_TYPE:
            raise ConfigError(f"bag {path}: no {WRENCH_TYPE} topic {given!r}; it holds {sorted(topics)}")
        return given
    found = [n for n, ty in topics.items() if ty == WRENCH_TYPE and n.endswith("cstomo_sensor/wrench")]
    if len(found) != 1:
        raise ConfigError(f"bag {path}: {len(found)} topics of the node's wrench ({', '.join(sorted(found)) or 'none'}) "
                          f"among {sorted(topics)}; expected one */cstomo_sensor/wrench (or name it with --wrench-topic)")
    return found[0]


def from_bag(path: str | Path, wrench_topic: str | None = None, truth_topic: str | None = None
             ) -> tuple[Forces, Forces | None, str]:
    """(the estimated forces, the true ones of ``truth_topic`` or None, the wrench topic) of a rosbag2
    recording: the wrench topic's messages with the ``_sigma`` topic beside it (matched by stamp), on
    the seconds since the bag's start, by their header stamps."""
    from rosbags.rosbag2 import Reader  # optional: the [full] extra

    from ..ros.sources import bag_path

    store = bag_typestore()
    with Reader(bag_path(path)) as reader:
        topics = {c.topic: c.msgtype for c in reader.connections}
        topic = wrench_topic_of(topics, wrench_topic, path)
        if truth_topic is not None and topics.get(truth_topic) != WRENCH_TYPE:
            raise ConfigError(f"bag {path}: no {WRENCH_TYPE} topic {truth_topic!r} for --truth-topic; it holds "
                              f"{sorted(topics)}")
        sigma_topic = topic + "_sigma" if topics.get(topic + "_sigma") == VECTOR_TYPE else None
        wanted = {topic, sigma_topic, truth_topic} - {None}
        series: dict[str, dict[int, tuple]] = {t: {} for t in wanted}
        for conn, _t, raw in reader.messages(connections=[c for c in reader.connections if c.topic in wanted]):
            m = store.deserialize_cdr(bytes(raw), conn.msgtype)
            v = m.wrench.force if conn.msgtype == WRENCH_TYPE else m.vector
            series[conn.topic][m.header.stamp.sec * 1_000_000_000 + m.header.stamp.nanosec] = (v.x, v.y, v.z)
        start = reader.start_time
    if not series[topic]:
        raise ConfigError(f"bag {path}: no message on {topic}")
    est = _stamped(series[topic], series.get(sigma_topic), start)
    truth = _stamped(series[truth_topic], None, start) if truth_topic is not None else None
    if truth is not None and not len(truth.t):
        raise ConfigError(f"bag {path}: no message on {truth_topic}")
    return est, truth, topic


def _stamped(values: dict[int, tuple], sigmas: dict[int, tuple] | None, start_ns: int) -> Forces:
    """Forces of {stamp ns: (x, y, z)} in stamp order, with the sigma of the same stamp (NaN: none)."""
    stamps = np.array(sorted(values), dtype=np.int64)
    force = np.array([values[s] for s in stamps], float).reshape(-1, 3)
    sigma = None
    if sigmas is not None:
        sigma = np.array([sigmas.get(int(s), (np.nan,) * 3) for s in stamps], float).reshape(-1, 3)
    return Forces((stamps - start_ns) * 1e-9, force, sigma)


def from_live(wrench_topic: str, seconds: float, say=print, wait: float = 10.0) -> Forces:
    """The running node's wrenches (``wrench_topic`` and its ``_sigma``) for ``seconds`` s from the
    first one (waiting at most ``wait`` s for it), on the seconds since the first one's stamp. Ctrl-C
    ends the listening early."""
    import rclpy
    from geometry_msgs.msg import Vector3Stamped, WrenchStamped
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from rclpy.signals import SignalHandlerOptions

    values: dict[int, tuple] = {}
    sigmas: dict[int, tuple] = {}

    def keep(into, msg, v):
        into[msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec] = (v.x, v.y, v.z)

    ctx = rclpy.Context()  # the user's ROS_DOMAIN_ID: where the node runs
    rclpy.init(args=[], context=ctx, signal_handler_options=SignalHandlerOptions.NO)  # Ctrl-C: KeyboardInterrupt
    try:
        node = rclpy.create_node("cstomo_plot", context=ctx)
        executor = SingleThreadedExecutor(context=ctx)
        executor.add_node(node)
        qos = QoSProfile(depth=200, reliability=ReliabilityPolicy.BEST_EFFORT)  # matches either kind of publisher
        node.create_subscription(WrenchStamped, wrench_topic, lambda m: keep(values, m, m.wrench.force), qos)
        node.create_subscription(Vector3Stamped, wrench_topic + "_sigma", lambda m: keep(sigmas, m, m.vector), qos)
        say(f"listening to {wrench_topic} for {seconds:g} s from its first message (Ctrl-C ends it early)")
        started, first = time.monotonic(), None
        try:
            while True:  # discovery takes a few seconds: the seconds count from the first message
                now = time.monotonic()
                if first is None and values:
                    first = now
                if (first is None and now - started >= wait) or (first is not None and now - first >= seconds):
                    break
                executor.spin_once(timeout_sec=0.1)
        except KeyboardInterrupt:
            pass
        executor.shutdown(timeout_sec=1.0)
        node.destroy_node()
    finally:
        rclpy.try_shutdown(context=ctx)
    if not values:
        raise ConfigError(f"no message on {wrench_topic} in {wait:g} s: is the node running and active, on "
                          "this ROS_DOMAIN_ID?")
    return _stamped(values, sigmas, min(values))


PANELS = (("fx", "N"), ("fy", "N"), ("fz", "N"), ("|F|", "N"), ("elevation", "deg"), ("azimuth", "deg"))
#: The angle panels' ranges (deg) when no frame has a direction (:func:`angles_deg`).
ANGLE_RANGES = {"elevation": (-90.0, 90.0), "azimuth": (-180.0, 180.0)}


def _columns(f: Forces) -> list[np.ndarray]:
    el, az = angles_deg(f)
    return [f.force[:, 0], f.force[:, 1], f.force[:, 2], np.linalg.norm(f.force, axis=1), el, az]


def same_branch(az: np.ndarray, t: np.ndarray, true_az: np.ndarray, true_t: np.ndarray) -> np.ndarray:
    """Azimuths ``az`` (deg) at times ``t``, each moved by whole turns to lie within 180 deg of the true
    azimuth in force at its time (the true sample at or before it; unchanged where there is none)."""
    order = np.argsort(true_t, kind="stable")
    tt, ta = true_t[order], true_az[order]
    i = np.clip(np.searchsorted(tt, t, side="right") - 1, 0, len(tt) - 1)
    ref = ta[i] if len(tt) else np.full(len(t), np.nan)
    turns = np.where(np.isfinite(ref) & np.isfinite(az), np.round((ref - az) / 360.0), 0.0)
    return az + 360.0 * turns


def figure(est: Forces, truth: Forces | None = None, title: str = "", size: tuple[int, int] = (1200, 800)):
    """The picture (a matplotlib ``Figure`` on the off-screen Agg canvas, ``size`` pixels at 100 dpi):
    a panel per quantity of :data:`PANELS` (fx, fy, fz, |F| on the left column's and the right
    column's first; elevation, azimuth), the true line (label ``true``) under the estimated one
    (label ``estimated``) with its 1-sigma band (label ``1-sigma``)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg  # optional, heavy: only when drawn
    from matplotlib.figure import Figure

    fig = Figure(figsize=(size[0] / 100, size[1] / 100), dpi=100)
    FigureCanvasAgg(fig)
    axes = fig.subplots(3, 2, sharex=True).T.ravel()  # fx, fy, fz down the left; |F|, el, az down the right
    band = est.band()
    band = None if band is None or np.isnan(band).all() else band
    columns, true_cols = _columns(est), _columns(truth) if truth is not None else None
    if true_cols is not None:  # the azimuth on the branch of the true one (179 deg beside 180, not -181)
        columns[5] = same_branch(columns[5], est.t, true_cols[5], truth.t)
    for k, (ax, (name, unit)) in enumerate(zip(axes, PANELS)):
        if true_cols is not None:
            ax.plot(truth.t, true_cols[k], color="black", lw=1.2, label="true")
        ax.plot(est.t, columns[k], color="tab:blue", lw=1.0, label="estimated")
        if band is not None and k < 4:
            ax.fill_between(est.t, columns[k] - band[:, k], columns[k] + band[:, k], color="tab:blue",
                            alpha=0.25, lw=0, label="1-sigma")
        ax.set_ylabel(f"{name} [{unit}]")
        ax.grid(True, alpha=0.3)
        if k >= 4 and not np.isfinite(columns[k]).any() and (true_cols is None or not np.isfinite(true_cols[k]).any()):
            # no direction in any frame (an unloaded recording): the angle's whole range and why it is empty
            ax.set_ylim(*ANGLE_RANGES[name])
            ax.text(0.5, 0.5, f"no direction: |F| within {DIRECTION_SIGMAS:g} sigma_n in every frame",
                    transform=ax.transAxes, ha="center", va="center", color="gray")
    axes[0].legend(loc="best", fontsize="small")
    for ax in (axes[2], axes[5]):
        ax.set_xlabel("frame" if est.unit == "frame" else "time [s]")
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    return fig


def save_png(fig, path: str | Path) -> None:
    """Write ``fig`` as a PNG (atomically: a failed write leaves no half picture)."""
    buf = io.BytesIO()
    fig.savefig(buf, format="png")
    with atomic_write(path) as f:
        f.write(buf.getvalue())


def _size(text: str) -> tuple[int, int]:
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r}: expected WIDTHxHEIGHT in pixels, e.g. 1200x800") from None
    if not (100 <= w <= 10000 and 100 <= h <= 10000):
        raise argparse.ArgumentTypeError(f"{text!r}: expected each side 100..10000 pixels")
    return w, h


def parser() -> argparse.ArgumentParser:
    """This command's argument parser (cli.subcommand_parser)."""
    p = ToolParser(prog="cstomo plot", description=help_text(__doc__.split("\n\n")[0]),
                                epilog=help_text(__doc__.split("\n\n", 1)[1]))
    p.add_argument("forces_or_bag", nargs="?", metavar="FORCES_OR_BAG",
                   help="a forces file (CSV, docs/formats.md#forces-file) or a rosbag2 directory; none with --live")
    p.add_argument("--live", action="store_true", help="listen to the running node instead (default: off)")
    p.add_argument("--out", required=True, metavar="PNG", help="picture to write (PNG)")
    p.add_argument("--truth", metavar="CSV", help="the true forces, a forces file (default: none)")
    p.add_argument("--truth-topic", metavar="TOPIC",
                   help="with a bag: a reference sensor's WrenchStamped topic as the true forces (default: none)")
    p.add_argument("--truth-shift", type=float, default=0.0, metavar="S",
                   help="seconds (frames, on a frame axis) added to the truth file's times, e.g. to align a "
                        "replayed bag, whose first wrench follows the tare (default %(default)g)")
    p.add_argument("--rate", type=float, metavar="HZ",
                   help="frames per second of a forces file without a time column: its frames on a time axis "
                        "(default: none, the axis counts frames)")
    p.add_argument("--wrench-topic", metavar="TOPIC",
                   help=f"the node's wrench topic (default: a bag's one */cstomo_sensor/wrench; live: {NODE_WRENCH})")
    p.add_argument("--seconds", type=float, default=10.0, metavar="S",
                   help="with --live: how long to listen, from the first message (default %(default)g)")
    p.add_argument("--wait", type=float, default=10.0, metavar="S",
                   help="with --live: how long to wait for the first message (finding a node takes a few "
                        "seconds) (default %(default)g)")
    p.add_argument("--size", type=_size, default=(1200, 800), metavar="WxH",
                   help="picture size in pixels (default 1200x800)")
    p.add_argument("--title", help="the picture's title (default: the input's name)")
    return p


def _check(a: argparse.Namespace) -> None:
    if a.live == bool(a.forces_or_bag):
        raise ConfigError("give a forces file or a bag, or --live (one of them)")
    if a.rate is not None and not 0 < a.rate < float("inf"):
        raise ConfigError.bad_value("--rate", a.rate, "frames per second > 0")
    if a.live and not 0 < a.seconds < float("inf"):
        raise ConfigError.bad_value("--seconds", a.seconds, "seconds > 0")
    if a.live and not 0 < a.wait < float("inf"):
        raise ConfigError.bad_value("--wait", a.wait, "seconds > 0")
    if not np.isfinite(a.truth_shift):
        raise ConfigError.bad_value("--truth-shift", a.truth_shift, "a finite number of seconds")
    if a.truth and a.truth_topic:
        raise ConfigError("give --truth or --truth-topic, not both")
    if a.forces_or_bag and not Path(a.forces_or_bag).exists():
        raise ConfigError(f"{a.forces_or_bag}: not found; expected a forces file (CSV) or a rosbag2 directory")
    if a.truth_topic and not (a.forces_or_bag and Path(a.forces_or_bag).is_dir()):
        raise ConfigError("--truth-topic reads a bag: give a rosbag2 directory")
    check_picture(a.out)


def check_picture(path: str) -> None:
    """Refuse a picture's path that is no PNG file name or cannot be written (:class:`ConfigError`)."""
    if not str(path).lower().endswith(".png"):
        raise ConfigError(f"{path}: expected a picture file name ending in .png")
    check_out_file(path)


def run(a: argparse.Namespace, say=print):
    """Draw and write the picture of parsed arguments ``a``; the figure (its data: the tests)."""
    _check(a)
    truth = from_csv(a.truth, a.rate) if a.truth else None  # read before anything slow
    if a.live:
        est = from_live(a.wrench_topic or NODE_WRENCH, a.seconds, say, a.wait)
        what = f"live {a.wrench_topic or NODE_WRENCH}"
    elif Path(a.forces_or_bag).is_dir():
        est, bag_truth, topic = from_bag(a.forces_or_bag, a.wrench_topic, a.truth_topic)
        truth = bag_truth or truth
        what = f"{Path(a.forces_or_bag).name} {topic}"
    else:
        size = Path(a.forces_or_bag).stat().st_size
        if size > BIG_FILE:  # a long recording: reading and drawing take seconds
            say(f"reading {a.forces_or_bag} ({size / 1e6:.0f} MB)")
        est = from_csv(a.forces_or_bag, a.rate)
        what = Path(a.forces_or_bag).name
    if truth is not None:
        if truth.unit != est.unit:
            raise ConfigError(f"--truth {a.truth}: has no time column; give --rate, its frames per second, to put "
                              "it on the time axis of the estimates")
        if a.truth and a.truth_shift:
            truth.t = truth.t + a.truth_shift
    if len(est.t) > BIG_SERIES:
        say(f"drawing {len(est.t)} forces")
    fig = figure(est, truth, a.title if a.title is not None else what, a.size)
    save_png(fig, a.out)
    n = int((~np.isnan(est.force).any(axis=1)).sum())
    say(f"wrote {a.out}: {n} estimated forces" + (f" and {len(truth.t)} true ones" if truth is not None else "")
        + f" over {np.nanmax(est.t) - np.nanmin(est.t):.6g} {'frames' if est.unit == 'frame' else 's'}")
    return fig


def main(argv: list[str] | None = None) -> int:
    a = parser().parse_args(argv)
    try:
        run(a)
    except ImportError as err:
        from ..errors import install_hint

        print(f"cstomo plot: error: {err.name or err} is missing: {install_hint(err.name)}", file=sys.stderr)
        return 2
    except (CstomoError, OSError) as err:
        print(f"cstomo plot: error: {err}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
