"""``cstomo demo`` (``make demo``): the simulated board and the node together, live force estimates.

1. builds (or loads from the cache) the sensor's model and force estimator, saying what it does;
2. starts ``cstomo_sensor_node`` (a real ROS 2 node, DDS on this host only) on a pty link, with a
   tare on its first frames;
3. starts ``cstomo board-sim`` on that link, playing a scripted sequence: unloaded, the paper's
   20 N at 30, 90 and 120 degrees, a sweep of azimuths at 60 degrees elevation, and magnitudes from
   5 to 40 N;
4. prints, live, the true and the estimated force (magnitude, elevation, azimuth) and the frame
   rate, from the node's ``~/wrench`` topic (an estimate below :data:`DIRECTION_SIGMAS` times its
   1-sigma ``sigma_n``, from ``~/wrench_sigma``, shows no direction); exits when the sequence ends. Each line judges the
   latest wrench against the load in force when its frame was measured: its stamp (the board's clock
   mapped to the host's) minus the load script's t = 0 on the same clock (from ``board-sim``), not
   the demo's own clock, which lags the script by the board's report and the wrench's transport.

The simulated rubber creeps as a typical rubber does (board-sim's default ``--creep``) and the node
compensates that (its default ``creep_per_decade``): both are settings.py's
``TYPICAL_CREEP_PER_DECADE``.
"""
from __future__ import annotations

import argparse
import math
import shutil
import signal
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np
import rclpy
from geometry_msgs.msg import Vector3Stamped, WrenchStamped

from ..angles import angle_between, force_angles, force_from_angles
from ..errors import CstomoError
from ..frame_path.config import PipelineConfig
from ..frame_path.pipeline import Pipeline
from ..frames_io import force_at, load_index, read_load_script
from ..settings import MAX_LOAD
from .board_sim import COMPUTING
from .common import NodeWithBoard, ToolParser, add_setting_arg, help_text, local_ros_env, positive, ticking
from .plot import DIRECTION_SIGMAS, Forces, check_picture, figure, save_png


def load_script(hold: float = 2.0, lead: float = 3.0) -> tuple[np.ndarray, np.ndarray, list[str]]:
    """(times, forces, labels) of the demo sequence."""
    steps: list[tuple[str, np.ndarray]] = [("unloaded (tare)", np.zeros(3))]
    for gamma in (30, 90, 120):  # the paper's planar cases: gamma = atan2(-Fz, Fx), in the x-z plane
        g = np.radians(gamma)
        steps.append((f"paper {gamma}° in x-z", 20.0 * np.array([np.cos(g), 0.0, -np.sin(g)])))
    for az in range(0, 360, 45):
        steps.append((f"sweep azimuth {az}°", force_from_angles(20.0, np.radians(60), np.radians(az))))
    for mag in (5.0, 15.0, 30.0, 40.0):
        steps.append((f"magnitude {mag:g} N", force_from_angles(mag, np.radians(75), np.radians(30))))
    steps.append(("released", np.zeros(3)))
    times = np.array([0.0] + [lead + hold * i for i in range(len(steps) - 1)])
    return times, np.array([f for _, f in steps]), [s for s, _ in steps]


#: The force columns of a demo line: magnitude, elevation, azimuth (units in the header, :data:`LEGEND`).
FORCE_COLUMNS = f"{'|F| [N]':>7}  {'elev [deg]':>10}  {'azim [deg]':>10}"

#: What the columns of the demo's table are, said once above it.
LEGEND = (
    "elev: elevation, degrees below the horizontal (90: straight down)\n"
    "azim: azimuth, degrees from +x towards +y, 0..360 ('-' straight down: a vertical force has none)\n"
    f"'-' for both: |F| below {DIRECTION_SIGMAS:g} x its 1-sigma (~/wrench_sigma), a direction within the noise\n"
    "'paper G° in x-z': the paper's planar cases, the angle G from +x in the x-z plane")


def _fmt(f: np.ndarray, sigma_n: float = math.nan) -> str:
    """The :data:`FORCE_COLUMNS` of force ``f``: magnitude N, elevation and azimuth in degrees (azimuth
    0..360). No angles for no force, or for a force below :data:`DIRECTION_SIGMAS` x its 1-sigma
    ``sigma_n`` (N; nan: unknown, angles shown); no azimuth for a force straight down, or whose
    horizontal part is below that."""
    m, el, az = force_angles(f)
    if m == 0 or m < DIRECTION_SIGMAS * sigma_n:  # no (meaningful) direction (not "el -0.0  az 0.0")
        return f"{m:7.2f}  {'-':>10}  {'-':>10}"
    horizontal = float(np.hypot(f[0], f[1]))
    if horizontal <= 1e-9 * m or horizontal < DIRECTION_SIGMAS * sigma_n:  # no (meaningful) azimuth
        return f"{m:7.2f}  {np.degrees(el):10.1f}  {'-':>10}"
    azimuth = float(np.degrees(az)) % 360.0
    return f"{m:7.2f}  {np.degrees(el):10.1f}  {0.0 if round(azimuth, 1) == 360.0 else azimuth:10.1f}"


def parser() -> argparse.ArgumentParser:
    """This command's argument parser (cli.subcommand_parser)."""
    p = ToolParser(prog="cstomo demo", description=help_text(__doc__.splitlines()[0]))
    add_setting_arg(p, "sensor")
    add_setting_arg(p, "estimator")
    p.add_argument("--rate", type=positive("frames per second > 0"), default=100.0, metavar="HZ",
                   help="the simulated board's frames per second")
    p.add_argument("--hold", type=positive("seconds > 0"), default=2.0, metavar="S",
                   help="seconds each load is held (with --load-script: the last one)")
    p.add_argument("--load-script", metavar="CSV", help="play this load script (time,fx,fy,fz) instead of the demo's")
    p.add_argument("--plot", metavar="PNG", help="at the end, draw the run's true and estimated forces over time into "
                   "this picture, as `cstomo plot` does (default: none)")
    return p


def main(argv: list[str] | None = None) -> int:
    p = parser()
    a = p.parse_args(argv)
    local_ros_env(30)
    signal.signal(signal.SIGTERM, _interrupt)  # SIGTERM ends the demo as Ctrl-C does
    try:
        return _run(a)
    except (CstomoError, OSError) as err:
        return p.fail(err)
    except KeyboardInterrupt:  # before the board streams (the watch handles its own)
        print("\ncstomo demo: stopped before the board streamed", file=sys.stderr)
        return 0


def _interrupt(*_: object) -> None:
    raise KeyboardInterrupt


def _run(a: argparse.Namespace) -> int:
    started = time.monotonic()  # the summary's times count from here
    if a.plot:  # a picture that cannot be written is said before anything slow
        check_picture(a.plot)
    if a.load_script:  # read before the (slow) model build: a bad file is reported at once
        times, forces = read_load_script(a.load_script, MAX_LOAD)
        labels = [f"script row {i + 1}" for i in range(len(times))]
    else:
        times, forces, labels = load_script(a.hold)
    work = Path(tempfile.mkdtemp(prefix="cstomo_demo_"))
    script = work / "load.csv"
    np.savetxt(script, np.column_stack([times, forces]), delimiter=",", header="time,fx,fy,fz", comments="")
    duration = float(times[-1] + a.hold)
    # the simulated rubber creeps as a typical rubber (board-sim's default) and the node compensates
    # that (its default creep_per_decade): one declaration, settings.py TYPICAL_CREEP_PER_DECADE
    params = {"sensor": a.sensor, "estimator": a.estimator, "tare_on_start": "true", "tare_frames": 50,
              "tare_file": work / "tare.csv", "stress_field_every": 0}
    board_args = ["--sensor", a.sensor, "--load-script", str(script), "--rate", str(a.rate),
                  "--duration", str(duration + 2.0)]  # the board outlives the watch: the node is stopped first
    marks: dict[str, float] = {}
    board_log = work / "board.log"  # the board's messages and final counts, shown (explained) at the end
    view = None
    try:
        with open(board_log, "w", encoding="utf-8") as err, \
                NodeWithBoard(work / "board", params, board_args, board_err=err) as run:
            # the board computes (or reads from the cache) its loads while the model builds; its
            # script starts when the node connects
            print("[1/3] simulated board: its scripted loads on an independent mesh (honest simulation; "
                  "computed once, then read from the cache)", flush=True)
            run.start_board()
            print("[2/3] model and force estimator (built once, then loaded from the cache)", flush=True)
            t = time.perf_counter()
            Pipeline.build(PipelineConfig(sensor=a.sensor, estimator=a.estimator),
                           progress=lambda m: print("      " + m, flush=True))
            print(f"      ready in {time.perf_counter() - t:.1f} s", flush=True)
            with ticking("      the simulated board computes its loads (once; cached)"):
                device = run.start()
            marks["board ready"] = time.monotonic() - started
            print(f"[3/3] board on {device}; waiting for the node to connect", flush=True)
            script_t0 = run.wait_streaming()  # the script's t = 0 on the wrenches' clock (None: unknown)
            t0 = time.monotonic()  # about the load script's t = 0 (a little later): the watch's duration
            view = _View()
            marks["streaming"] = t0 - started
            print("      streaming; the node tares on its first frames\n", flush=True)
            code, summary = _watch(a, t0, duration, times, forces, labels, run.board, view, script_t0)
        # the node and then the board have stopped: the board's final counts are in its log
        _print_summary(a, summary, marks, started, _lines(board_log))
        if a.plot:
            _plot(a.plot, view, times, forces, script_t0)
        return code
    except BaseException:
        for line in _lines(board_log):  # why the board failed, say: never lost
            print(f"board-sim: {line}", file=sys.stderr)
        raise
    finally:
        if view is not None:
            view.close()
        shutil.rmtree(work, ignore_errors=True)  # the load script, the link, the board's log and the demo's own tare


def _plot(path: str, view: _View, times: np.ndarray, forces: np.ndarray, script_t0: float | None) -> None:
    """The run's picture (:mod:`.plot`): every wrench received, on the load script's clock, beside the
    scripted force of its frame, with its 1-sigma (~/wrench_sigma of the same stamp)."""
    if not view.stamps:
        print(f"no picture: no wrench received ({path} not written)")
        return
    n = len(view.stamps)  # the node has stopped: nothing more comes (a snapshot all the same)
    stamps = np.array(view.stamps[:n], dtype=np.int64)
    t = (stamps - stamps[0]) * 1e-9 + (stamps[0] * 1e-9 - script_t0 if script_t0 is not None else 0.0)
    sigma = np.array([view.sigmas.get(int(s), (np.nan,) * 3) for s in stamps], float)
    est = Forces(t, np.array(view.forces[:n], float), sigma)
    # the script's steps, drawn as steps: each row's force from its time to the next row's (the last
    # to the end), zero before the first
    xs = np.column_stack([times, np.append(times[1:], max(t[-1], times[-1]))]).ravel()
    fs = np.repeat(forces, 2, axis=0)
    if t[0] < times[0]:
        xs, fs = np.concatenate([[t[0], times[0]], xs]), np.vstack([np.zeros((2, 3)), fs])
    truth = Forces(xs, fs)
    save_png(figure(est, truth, f"cstomo demo: {len(t)} wrenches of the node, the scripted load as truth"), path)
    print(f"wrote {path}: the true and the estimated forces over time")


def _lines(path: Path) -> list[str]:
    """The board's messages in its log, but the one the demo's step [1/3] has said already."""
    try:
        return [ln.rstrip() for ln in path.read_text(encoding="utf-8", errors="replace").splitlines()
                if ln.strip() and not ln.startswith(COMPUTING)]
    except OSError:
        return []


def _print_summary(a, summary: dict, marks: dict, started: float, board_lines: list[str]) -> None:
    """What the demo measured, each figure said with what it is."""
    first = summary["first"]
    steps = ", ".join(f"{k} at {v:.1f} s" for k, v in marks.items())
    print(f"\nsummary (times from the start of `cstomo demo`, its imports done: {steps})")
    rows = [("first wrench", f"{first - started:.1f} s after the start" if first is not None else "none received"),
            ("wrenches received", f"{summary['count']} on /cstomo_sensor/wrench (the node publishes one per board "
                                  f"frame, {a.rate:g}/s, once it has tared on the first 50)")]
    e = summary["errors"]
    if len(e):
        rows += [("settled lines", f"{len(e)}: the lines above whose load, not zero, had been held over 0.6 s "
                                   "when their wrench's frame was measured; the errors are their medians against "
                                   "the scripted true force at that time"),
                 ("median angle error", f"{np.median(e[:, 0]):.2f} deg (between the estimated and the true force)"),
                 ("magnitude error", f"median {100 * np.median(e[:, 1]):.1f} % (| |F estimated| - |F true| | / "
                                     f"|F true|; {a.estimator} estimator)")]
    rows += [("simulated board" if i == 0 else "", line) for i, line in enumerate(_board_counts(board_lines, a.rate))]
    for name, text in rows:
        print(f"  {name:<19} {text}")


def _board_counts(lines: list[str], rate: float) -> list[str]:
    """board-sim's final counts as the demo's summary says them: its overrun (frames it could not write
    once the demo had stopped the node, which it does first, before the board's last 2 s) as a few
    words on the first line, unless more frames than those 2 s overran (then its own line stays)."""
    overrun = [ln for ln in lines if " overrun: " in ln]
    if not overrun or not lines:
        return lines
    n = int(overrun[0].split()[0]) if overrun[0].split()[0].isdigit() else None
    if n is None or n > 2.5 * rate:
        return lines
    rest = [ln for ln in lines if ln is not overrun[0]]
    return [f"{rest[0]}; {n} more unsent after the node stopped (as expected at the end)", *rest[1:]] if rest else lines


class _View:
    """The demo's subscriber to the node's ``~/wrench``, spun in a thread of its own. Made once the
    board streams, when the node's participant exists: its first wrench then came 0.4-0.6 s after
    the stream started in 4 runs of 4, where a subscriber made before the node started waited for a
    DDS discovery round (about 3 s more) in 2 runs of 3."""

    def __init__(self) -> None:
        from rclpy.executors import SingleThreadedExecutor
        from rclpy.signals import SignalHandlerOptions

        rclpy.init(signal_handler_options=SignalHandlerOptions.NO)
        self.node = rclpy.create_node("cstomo_demo_view")
        self.executor = SingleThreadedExecutor()
        self.executor.add_node(self.node)
        self.latest: np.ndarray | None = None
        self.stamp: float | None = None  # the latest wrench's header.stamp, s (system clock)
        self.sigma_n = math.nan  # the latest ~/wrench_sigma's norm: the 1-sigma sigma_n of its wrench, N
        self.count = 0
        self.stamps: list[int] = []  # every wrench's stamp (ns), force and sigma by stamp: the picture
        self.forces: list[tuple[float, float, float]] = []
        self.sigmas: dict[int, tuple[float, float, float]] = {}
        self.first: float | None = None  # time.monotonic() of the first wrench
        self.wake = threading.Event()  # set by the first wrench with its sigma (and by the watch's signal handlers)
        self.node.create_subscription(WrenchStamped, "/cstomo_sensor/wrench", self._on_wrench, 10)
        self.node.create_subscription(Vector3Stamped, "/cstomo_sensor/wrench_sigma", self._on_sigma, 10)
        self._spinner = threading.Thread(target=self._spin, daemon=True)
        self._spinner.start()

    def _on_wrench(self, msg: WrenchStamped) -> None:
        f = msg.wrench.force
        self.stamp = msg.header.stamp.sec + 1e-9 * msg.header.stamp.nanosec
        self.latest = np.array([f.x, f.y, f.z])
        self.stamps.append(msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec)
        self.forces.append((f.x, f.y, f.z))
        self.count += 1
        if self.first is None:
            self.first = time.monotonic()
            self._first_line()

    def _first_line(self) -> None:
        """The first wrench's line is printed at once, not at the next half second, once its sigma has
        come too (published right after it; without it the line would show a noise's direction)."""
        if self.latest is not None and not math.isnan(self.sigma_n):
            self.wake.set()

    def _on_sigma(self, msg: Vector3Stamped) -> None:
        """The per-axis 1-sigma of a wrench (published with it, under its stamp): sigma_n = its norm,
        sqrt(trace(cov)); the sigma of the latest wrench or of one a frame away, which differ little."""
        v = msg.vector
        self.sigmas[msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec] = (v.x, v.y, v.z)
        first = math.isnan(self.sigma_n)
        self.sigma_n = math.sqrt(v.x * v.x + v.y * v.y + v.z * v.z)
        if first:
            self._first_line()

    def _spin(self) -> None:
        from rclpy.executors import ExternalShutdownException

        try:
            self.executor.spin()
        except ExternalShutdownException:
            pass  # rclpy shut down under the spin: the watch is over

    def close(self) -> None:
        self.executor.shutdown(timeout_sec=1.0)
        self.node.destroy_node()
        rclpy.try_shutdown()
        self._spinner.join(2.0)


def judge(times: np.ndarray, forces: np.ndarray, labels: list[str], t: float, est: np.ndarray,
          sigma_n: float = math.nan, settle: float = 0.6) -> tuple[str, tuple[float, float] | None]:
    """(the line's columns from ``t`` to the angle error, (angle error deg, relative magnitude error)
    if the line counts in the summary) of an estimate ``est`` (1-sigma ``sigma_n``, :func:`_fmt`) of
    the frame measured at script time ``t``: judged against the load in force at ``t``; it counts
    when that load is not zero and had been held over ``settle`` s."""
    i = load_index(times, t)
    true = force_at(times, forces, t)
    settled = i >= 0 and t - times[i] > settle
    err = np.degrees(angle_between(est, true)) if np.linalg.norm(true) > 0 else float("nan")
    shown = f"{err:15.1f}" if np.isfinite(err) else f"{'-':>15}"
    counted = None
    if settled and np.isfinite(err):
        counted = (float(err), float(abs(np.linalg.norm(est) - np.linalg.norm(true)) / np.linalg.norm(true)))
    return f"{t:6.1f}  {labels[max(i, 0)]:<22} {_fmt(true)}   {_fmt(est, sigma_n)}   {shown}", counted


def _watch(a, t0, duration, times, forces, labels, board, view: _View,
           script_t0: float | None = None) -> tuple[int, dict]:
    # Ctrl-C and SIGTERM end the watch quietly: the summary is printed, the node and the board are
    # stopped in order by NodeWithBoard (they run in sessions of their own, so a terminal's Ctrl-C
    # reaches only this process).
    stop = threading.Event()

    def on_signal(*_: object) -> None:
        stop.set()
        view.wake.set()

    previous = {sig: signal.signal(sig, on_signal) for sig in (signal.SIGINT, signal.SIGTERM)}
    print(LEGEND)
    width = len(FORCE_COLUMNS)
    estimated = "estimated (the node's ~/wrench)"
    print(f"\n{'':6}  {'':22} {'true force':^{width}}   {estimated:^{width}}")
    print(f"{'t [s]':>6}  {'load':<22} {FORCE_COLUMNS}   {FORCE_COLUMNS}   {'angle err [deg]':>15} "
          f"{'rate [1/s]':>10}")
    errors = []
    last_n, last_t = 0, time.monotonic()
    try:
        while time.monotonic() - t0 < duration and board.poll() is None:
            view.wake.wait(0.5)  # a line every half second, and one at the first wrench
            view.wake.clear()
            if stop.is_set():
                break
            now = time.monotonic()
            rate = (view.count - last_n) / (now - last_t)
            last_n, last_t = view.count, now
            est, stamp = view.latest, view.stamp
            if est is None:
                t = now - t0
                print(f"{t:6.1f}  {labels[max(load_index(times, t), 0)]:<22} waiting for the node's first wrench...",
                      flush=True)
                continue
            # the script time of the wrench's frame: its stamp on the script's clock (the demo's own
            # clock lags: at a load change it would judge the new load's estimate against the old load)
            t = stamp - script_t0 if script_t0 is not None and stamp else now - t0
            line, counted = judge(times, forces, labels, t, est, view.sigma_n)
            if counted is not None:
                errors.append(counted)
            print(f"{line} {rate:10.0f}", flush=True)
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
    if stop.is_set():
        print(f"\nstopped at t = {time.monotonic() - t0:.1f} s", flush=True)
    summary = {"first": view.first, "count": view.count, "errors": np.array(errors).reshape(-1, 2)}
    if errors:
        return 0, summary
    if view.count:
        print(f"\n{view.count} wrenches received; no load held long enough (0.6 s) to summarise")
        return 0, summary
    if stop.is_set():
        print("no wrench received yet")
        return 0, summary
    print("\nno wrench received from the node", file=sys.stderr)
    return 1, summary
