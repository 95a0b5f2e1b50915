"""``cstomo bench-node``: latency, CPU and memory of the real node on the real simulated board.

For each frame rate in ``--rates`` and with the stress field off (``stress_field_every:=0``) and
on (``:=1``), starts ``cstomo_sensor_node`` (tare on start) and ``cstomo board-sim`` (binary
protocol, a constant load script: unloaded for 2 s, then 20 N pushing straight down) on a pty
link, as ``cstomo demo`` does, subscribes to ``~/wrench`` and ``/diagnostics`` with rclpy and, over
a window of ``--seconds`` after a warm-up, measures what follows. With ``--sensors N`` it starts N
boards and N sensors together (namespaces ``/s0`` .. ``/s<N-1>``; with ``--hosted`` all N in one
``cstomo_sensor_host`` process instead of a process each) and measures them together: every
sensor's frames from its own /diagnostics counters, the wrenches and latency of ``/s0`` only (one
subscriber, so the measuring side stays small), the CPU of every node process and of the boards
(sums, and per process in ``node_bench_sensors.csv``):

* latency = receive time in this subscriber (``time.time_ns()``, the system clock: the node's host
  time is its ROS clock, which is the system clock without ``use_sim_time``) minus the wrench's
  ``header.stamp``. The stamp is the board's write time mapped onto host time by the lower envelope
  of ``host_time - board_time`` (board.clock.ClockMapper), so it is the board's write time *plus the
  smallest transport delay seen* (pty + serial driver thread + queue hand-over): that minimum is
  not included in the latency; what is measured is everything above it (processing, DDS,
  the subscriber's executor, scheduling);
* CPU of the node process (all threads): the sum of its threads' run times
  (``/proc/<pid>/task/<tid>/schedstat``, ns, exact) over the window, in % of one core and in
  microseconds per wrench received (and of the board simulator, which shares the 2 cores, and of this
  bench); the kernel's tick-sampled utime+stime (``/proc/<pid>/stat``) as a cross-check
  (``node_cpu_ticks_pct``: at 100 frames/s a workload at the tick's own rate aliases it);
* wrenches received per second, the node's frames per second and its dropped frames (queue
  overflow, late, sequence gaps: differences of the /diagnostics counters over the window);
* VmRSS and VmHWM of the node from /proc/<pid>/status at the end of the window (the largest node
  process with several);
* per sensor (``node_bench_sensors.csv``): the frames its board sent over the window (received +
  lost on the way: queue overflow, sequence gaps, corrupt), the frames it published (received minus
  late, rejected and implausible ones) and their ratio, from the differences of its /diagnostics
  counters; the configuration row carries the smallest ratio over the sensors (``published_min_pct``)
  and the smallest published rate against the nominal one (``published_of_nominal_min_pct``: a board
  that falls behind under load sends fewer frames than asked, which the first ratio cannot see);
* CPU per frame of the first node process (``/s0``'s, or the host's) by thread: the CPU time of each of
  its threads over the window (``/proc/<pid>/task/<tid>/schedstat``, ns; by OS thread name,
  ``/proc/<pid>/task/<tid>/comm``) grouped as the frame thread (``cstomo_frames``: it reads the port,
  decodes and processes), a driver's reader thread (``cstomo_reader``: none in the node since it reads on
  its frame thread, issue 27; kept for a threaded driver), the executor (the main thread and the
  threads named as it: the executor's pool) and the other threads (the middleware's), in microseconds
  per frame the process received (its sensors' diagnostics ``frames``), next to the process total
  (``node0_cpu_us_per_frame``) and every thread name's figure (``node0_threads``);
* with ``--cold``, the same configuration again at ``--cold-rate`` (10 frames/s: each frame comes after
  ~100 ms idle) and its per-frame CPU by thread in the ``cold_*`` columns: the cost of a frame after an
  idle period next to the warm one (it doubles the run time). The cold figures include what the node
  does per second whatever the rate (diagnostics, timers) spread over fewer frames;
* the outputs built: the topics the first sensor published on over the window and their rates
  (``outputs``, from the ``messages_published`` counters of its diagnostics).

With ``--lean`` the lean loop of :mod:`.lean` runs in place of each node (a process each, same boards,
ptys, rates, subscriber and accounting): the floor of any rclpy node under these conditions.

Prints markdown tables and writes ``node_bench.csv``, ``node_bench_sensors.csv`` and ``node_bench.md``
in ``--out``.
"""
from __future__ import annotations

import argparse
import csv
import math
import os
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import rclpy
import yaml
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import WrenchStamped

from ...errors import CstomoError
from ...frame_path.config import PipelineConfig
from ...frame_path.pipeline import Pipeline
from ...settings import default
from ..common import NodeWithBoard, ToolParser, add_setting_arg, executable, help_text, local_ros_env, positive

COLUMNS = ["rate_hz", "stress_field_every", "window_s", "wrenches", "wrench_rate_hz", "node_frame_rate_hz",
           "frames_dropped", "dropped_overflow", "seq_gaps", "late_dropped", "keeps_up",
           "latency_median_ms", "latency_p99_ms", "latency_max_ms",
           "node_cpu_pct", "node_cpu_us_per_wrench", "board_cpu_pct", "node_vmrss_mb", "node_vmhwm_mb",
           "processing_mean_ms", "host_loadavg_1m",
           "sensors", "hosted", "published_min_pct", "published_of_nominal_min_pct", "node_cpu_us_per_frame",
           "node_cpu_max_pct", "bench_cpu_pct", "host_loadavg_end", "lean", "node_cpu_ticks_pct"]
#: Thread groups of the first node process, by OS thread name (/proc/<pid>/task/<tid>/comm): the frame
#: thread, the driver's reader thread (both named by the node), the executor (the main thread and the
#: threads named as it: Python's, as the executor's pool) and the other threads (the middleware's,
#: which name themselves).
THREAD_GROUPS = ("frames", "reader", "executor", "other")
_NODE0 = ["node0_cpu_us_per_frame"] + [f"node0_{g}_us_per_frame" for g in THREAD_GROUPS]
COLUMNS += _NODE0 + ["node0_threads", "outputs", "cold_rate_hz"] + [f"cold_{c}" for c in _NODE0] + [
    "cold_node0_threads", "cold_host_loadavg_1m"]
#: One row per sensor and configuration (node_bench_sensors.csv).
SENSOR_COLUMNS = ["rate_hz", "stress_field_every", "sensors", "hosted", "sensor", "window_s", "board_frames",
                  "board_rate_hz", "frames", "published", "published_pct", "published_rate_hz", "dropped_overflow",
                  "seq_gaps", "corrupt", "late_dropped", "rejected", "implausible", "node_cpu_pct"]

METHOD = ("latency = subscriber receive time (time.time_ns, system clock = the node's ROS clock) - "
          "wrench header.stamp (board write time mapped to host time by the lower envelope of "
          "host_time - board_time); caveat: the minimum transport delay (pty + driver + queue hand-over) is "
          "absorbed into the clock offset and NOT included. CPU = the sum of the process's threads' run times "
          "(/proc/<pid>/task/<tid>/schedstat, ns; a thread that ends within the window is lost) over the "
          "window, % of one core (ticks % = utime+stime of /proc/<pid>/stat, 10 ms ticks, a sample: a "
          "cross-check); with several sensors the sum over the node processes (the one "
          "host process with --hosted), and the boards' sum. dropped = diagnostics dropped_overflow + "
          "late_dropped + seq_gaps over the window (every sensor). published = a sensor's frames minus its "
          "late, rejected and implausible ones, of the frames its board sent (frames + overflow + gaps + "
          "corrupt), from its /diagnostics counters; the smallest over the sensors. load 1m = the host's "
          "1-minute load average at the window's start and end (2 cores here: above ~1.5 the figures include "
          "contention with other work). Per thread (first node process): CPU time of each thread "
          "(/proc/<pid>/task/<tid>/schedstat, ns) over the window by OS thread name (comm), per frame the "
          "process received (its sensors' diagnostics 'frames'); frame thr = cstomo_frames, reader thr = "
          "cstomo_reader (the driver), executor = the main thread and the threads named as it (the "
          "executor's pool), other = the middleware's threads; us/frame = their sum. lean = the lean loop "
          "(tools/bench/lean.py) in place of the node. cold = the same configuration at a low "
          "rate (--cold-rate): every frame comes after an idle period (caches and branch predictors cold, "
          "CPU clock down). outputs = the topics the first sensor published on over the window "
          "(its diagnostics' messages_published).")

_TICK = os.sysconf("SC_CLK_TCK")


def thread_cpu(pid: int) -> dict[int, tuple[str, int]]:
    """tid -> (OS thread name, CPU time in ns) of every thread of a process: the run time of
    /proc/<pid>/task/<tid>/schedstat (ns), else utime+stime of its stat (clock ticks, 10 ms); a thread
    that ends while it is read is left out."""
    out = {}
    for tid in os.listdir(f"/proc/{pid}/task"):
        task = f"/proc/{pid}/task/{tid}"
        try:
            with open(f"{task}/comm") as f:
                comm = f.read().strip()
            try:
                with open(f"{task}/schedstat") as f:
                    ns = int(f.read().split()[0])
            except FileNotFoundError:  # a kernel without schedstats
                with open(f"{task}/stat") as f:
                    rest = f.read().rsplit(")", 1)[1].split()
                ns = (int(rest[11]) + int(rest[12])) * 1_000_000_000 // _TICK
        except (FileNotFoundError, ProcessLookupError, IndexError, ValueError):
            continue
        out[int(tid)] = (comm, ns)
    return out


def cpu_ns(before: dict, after: dict) -> int:
    """CPU time (ns) of a process between two :func:`thread_cpu` readings: the sum over its threads
    (a thread started in between counts from zero, one that ended is lost)."""
    return sum(ns - before.get(tid, (comm, 0))[1] for tid, (comm, ns) in after.items())


def thread_group(tid: int, pid: int, comm: str, main_comm: str) -> str:
    """The group of THREAD_GROUPS a thread of process ``pid`` belongs to."""
    from ...board.driver import READER_THREAD
    from ...ros.node import FRAME_THREAD

    if comm == FRAME_THREAD:
        return "frames"
    if comm == READER_THREAD:
        return "reader"
    if tid == pid or comm == main_comm:
        return "executor"
    return "other"


def thread_figures(pid: int, before: dict, after: dict, frames: float) -> dict:
    """CPU microseconds per frame of a process's thread groups between two :func:`thread_cpu`
    readings (a thread started in between counts from zero, one that ended is lost), and every thread
    name's, as 'name=us ...' (largest first)."""
    main_comm = after.get(pid, before.get(pid, ("", 0)))[0]
    groups = dict.fromkeys(THREAD_GROUPS, 0)
    names: dict[str, int] = {}
    for tid, (comm, ns) in after.items():
        d = ns - before.get(tid, (comm, 0))[1]
        groups[thread_group(tid, pid, comm, main_comm)] += d
        names[comm] = names.get(comm, 0) + d
    per = lambda ns: round(ns * 1e-3 / frames, 1) if frames > 0 else math.nan  # noqa: E731
    return {**{f"node0_{g}_us_per_frame": per(ns) for g, ns in groups.items()},
            "node0_threads": " ".join(f"{c}={per(ns):g}" for c, ns in sorted(names.items(), key=lambda x: -x[1])
                                      if ns > 0)}


def published_topics(diags: list, t0: float, t1: float) -> str:
    """The topics a sensor published messages on over the window, with their rates ('wrench=100/s ...'),
    from the ``messages_published`` counters of its diagnostics; '' when it does not report them."""
    before = [(t, d) for t, d in diags if t <= t0 and "messages_published" in d]
    inside = [(t, d) for t, d in diags if t0 < t <= t1 and "messages_published" in d]
    if not (before and inside):
        return ""
    (tb, db), (ta, da) = before[-1], inside[-1]
    parse = lambda d: dict((k, int(v)) for k, _, v in (x.partition("=") for x in d["messages_published"].split()))  # noqa: E731
    b, a = parse(db), parse(da)
    return " ".join(f"{t}={(n - b.get(t, 0)) / (ta - tb):.0f}/s" for t, n in sorted(a.items()) if n > b.get(t, 0))


def cpu_seconds(pid: int) -> float:
    """utime + stime of a process (all its threads), seconds."""
    with open(f"/proc/{pid}/stat") as f:
        rest = f.read().rsplit(")", 1)[1].split()  # fields after the command name; rest[0] is field 3
    return (int(rest[11]) + int(rest[12])) / _TICK


def memory_mb(pid: int) -> tuple[float, float]:
    """(VmRSS, VmHWM) of a process in MiB."""
    vals = {}
    with open(f"/proc/{pid}/status") as f:
        for line in f:
            key, _, v = line.partition(":")
            if key in ("VmRSS", "VmHWM"):
                vals[key] = int(v.split()[0]) / 1024.0
    return vals.get("VmRSS", math.nan), vals.get("VmHWM", math.nan)


def diagnostics_name(namespace: str) -> str:
    """The /diagnostics status name of the sensor in ``namespace`` ('' for the root namespace)."""
    return f"{namespace}/cstomo_sensor: sensor"


@dataclass
class _Recorder:
    """What the subscriber sees; ``recording`` gates the latency samples to the window."""
    names: tuple[str, ...] = (diagnostics_name(""),)  # the sensors' diagnostics names
    lock: threading.Lock = field(default_factory=threading.Lock)
    wrenches: int = 0
    recording: bool = False
    latencies_ns: list = field(default_factory=list)
    diags: dict = field(default_factory=dict)  # name -> [(time.monotonic(), {key: value})]

    def on_wrench(self, msg) -> None:
        now = time.time_ns()
        st = msg.header.stamp
        with self.lock:
            self.wrenches += 1
            if self.recording:
                self.latencies_ns.append(now - (st.sec * 1_000_000_000 + st.nanosec))

    def on_diag(self, msg) -> None:
        now = time.monotonic()
        for s in msg.status:
            if s.name in self.names:
                with self.lock:
                    self.diags.setdefault(s.name, []).append((now, {kv.key: kv.value for kv in s.values}))


def _num(d: dict, key: str) -> float:
    try:
        return float(d.get(key, "nan"))
    except ValueError:
        return math.nan


def _sensor_figures(diags: list, t0: float, t1: float, rate: float) -> dict:
    """One sensor's figures over the window from its diagnostics (1 Hz, cumulative counters): from the
    last one at or before the window's start to the last one in the window (at least seconds - 1 s)."""
    keys = ("frames", "dropped_overflow", "seq_gaps", "corrupt", "late_dropped", "frames_rejected", "implausible")
    before = [(t, d) for t, d in diags if t <= t0]
    inside = [(t, d) for t, d in diags if t0 < t <= t1]
    if not (before and inside):
        return {}
    (tb, db), (ta, da) = before[-1], inside[-1]
    d = {k: _num(da, k) - _num(db, k) for k in keys}
    span = ta - tb
    published = d["frames"] - d["late_dropped"] - d["frames_rejected"] - d["implausible"]
    board = d["frames"] + d["dropped_overflow"] + d["seq_gaps"] + d["corrupt"]
    proc = [x for x in (_num(x, "processing_time_mean_ms") for _, x in inside) if math.isfinite(x)]
    return {"window_s": round(span, 3), "board_frames": board, "board_rate_hz": round(board / span, 1),
            "frames": d["frames"], "published": published,
            "published_pct": round(100 * published / board, 3) if board > 0 else math.nan,
            "published_rate_hz": round(published / span, 1), "published_of_nominal": 100 * published / (rate * span),
            "dropped_overflow": d["dropped_overflow"], "seq_gaps": d["seq_gaps"], "corrupt": d["corrupt"],
            "late_dropped": d["late_dropped"], "rejected": d["frames_rejected"], "implausible": d["implausible"],
            "frame_rate_hz": d["frames"] / span, "processing_mean_ms": float(np.mean(proc)) if proc else math.nan}


class _Sensors:
    """N boards and N sensors: a node process each (``hosted`` False) or one ``cstomo_sensor_host``."""

    def __init__(self, a, n: int, hosted: bool, rate: float, stress: int, work: Path, script: Path, tag: str) -> None:
        self.n, self.hosted = n, hosted
        self.namespaces = [""] if n == 1 and not hosted else [f"/s{i}" for i in range(n)]
        # startup (rclpy import, model load, tare, 2 s unloaded; N boards and nodes share the cores) +
        # warm-up + window + margin
        duration = 30.0 + 8.0 * n + a.warmup + a.seconds
        if a.lean and hosted:
            raise CstomoError("--lean runs a lean loop in place of each node process: not with --hosted")
        self.params = {"sensor": a.sensor, "estimator": a.estimator, "rate_hz": float(rate), "protocol": "binary",
                       "tare_on_start": True,
                       # the tare within the load script's unloaded 2 s at a low (cold) rate too
                       "tare_frames": int(min(default("tare_frames"), max(5, rate // 2))), "stress_field_every": stress}
        board_args = ["--sensor", a.sensor, "--load-script", str(script), "--rate", str(rate), "--duration",
                      str(duration), "--protocol", "binary"]
        self.logs = []
        self.runs = []
        for i, ns in enumerate(self.namespaces):
            node_log, board_log = (open(work / f"{what}_{tag}_{i}.log", "w") for what in ("node", "board"))
            self.logs += [node_log, board_log]
            params = {k: str(v).lower() if isinstance(v, bool) else v for k, v in self.params.items()}
            params["tare_file"] = work / f"tare_{tag}_{i}.csv"
            run = NodeWithBoard(work / f"board_{tag}_{i}", params, board_args, node_out=node_log,
                                board_err=board_log, namespace=ns)
            if a.lean:  # the floor: the lean loop in place of the node (tools/bench/lean.py)
                run.node_cmd = [sys.executable, "-m", "cstomo_sensor.tools.bench.lean", run.link, "--rate", str(rate),
                                "--ros-args", "--log-level", "warn"] + (["-r", f"__ns:={ns}"] if ns else [])
            self.runs.append(run)
        self.host: subprocess.Popen | None = None
        self.host_cmd: list[str] = []
        if hosted:
            self.host_log = open(work / f"host_{tag}.log", "w")
            self.logs.append(self.host_log)
            sections = {"/**": {"ros__parameters": self.params}}
            for ns, run in zip(self.namespaces, self.runs):
                sections[f"{ns}/cstomo_sensor"] = {"ros__parameters": {
                    "port": run.link, "tare_file": str(work / f"tare_{tag}_{ns.strip('/')}.csv")}}
            params_file = work / f"host_{tag}.yaml"
            params_file.write_text(yaml.safe_dump(sections))
            try:
                cmd = [executable("cstomo_sensor_host")]
            except CstomoError:  # not installed as a console script (a source checkout): the module
                cmd = [sys.executable, "-m", "cstomo_sensor.ros.host"]
            self.host_cmd = cmd + self.namespaces + ["--ros-args", "--params-file", str(params_file),
                                                     "--log-level", "warn"]

    def start(self) -> None:
        for run in self.runs:  # the boards compute their loads in parallel
            run.start_board()
        for run in self.runs:
            if self.hosted:
                run.wait_device()
            else:
                run.start()
        if self.hosted:
            self.host = subprocess.Popen(self.host_cmd, stdout=self.host_log, stderr=subprocess.STDOUT,
                                         start_new_session=True)

    @property
    def node_pids(self) -> list[int]:
        return [self.host.pid] if self.hosted else [run.node.pid for run in self.runs]

    @property
    def board_pids(self) -> list[int]:
        return [run.board.pid for run in self.runs]

    def failed(self) -> str:
        """'' while every process runs, else which one ended."""
        procs = [("host", self.host)] if self.hosted else [(f"node {i}", r.node) for i, r in enumerate(self.runs)]
        procs += [(f"board {i}", r.board) for i, r in enumerate(self.runs)]
        return ", ".join(f"{name} ended ({p.returncode})" for name, p in procs if p is not None and p.poll() is not None)

    def stop(self) -> None:
        if self.host is not None and self.host.poll() is None:  # the nodes end before their boards
            self.host.send_signal(2)
            try:
                self.host.wait(10)
            except subprocess.TimeoutExpired:
                self.host.kill()
                self.host.wait()
        for run in self.runs:
            run.stop()
        for f in self.logs:
            f.close()


def run_one(ros_node, a, rate: float, stress: int, work: Path, script: Path, n: int = 1,
            hosted: bool = False) -> tuple[dict, list[dict]]:
    """One configuration: N boards and sensors, warm-up, measured window; a row of COLUMNS and a row
    of SENSOR_COLUMNS per sensor."""
    tag = f"r{rate:g}_s{stress}_n{n}{'h' if hosted else ''}"
    sensors = _Sensors(a, n, hosted, rate, stress, work, script, tag)
    rec = _Recorder(names=tuple(diagnostics_name(ns) for ns in sensors.namespaces))
    subs = [ros_node.create_subscription(WrenchStamped, f"{sensors.namespaces[0]}/cstomo_sensor/wrench",
                                         rec.on_wrench, 100),
            ros_node.create_subscription(DiagnosticArray, "/diagnostics", rec.on_diag, 10 * n)]
    me = os.getpid()
    try:
        try:
            sensors.start()
        except CstomoError as err:
            raise CstomoError(f"{err}; see the logs in {work}") from None
        deadline = time.monotonic() + 60.0 + 15.0 * n
        # the window's counters start from a diagnostics message of every sensor
        while rec.wrenches == 0 or len(rec.diags) < n:
            if time.monotonic() > deadline or sensors.failed():
                raise CstomoError(f"no wrench and diagnostics from the sensors within {deadline:.0f} s "
                                  f"({sensors.failed() or f'{len(rec.diags)} of {n} sensors seen'}); see the logs in {work}")
            time.sleep(0.05)
        time.sleep(a.warmup)  # past the tare and the step to 20 N; queues and caches settled

        load0 = os.getloadavg()[0]
        with rec.lock:
            rec.recording, n0 = True, rec.wrenches
        pids = sensors.node_pids + sensors.board_pids + [me]
        th0, k0 = [thread_cpu(p) for p in pids], [cpu_seconds(p) for p in pids]
        t0 = time.monotonic()
        time.sleep(a.seconds)
        t1 = time.monotonic()
        th1, k1 = [thread_cpu(p) for p in pids], [cpu_seconds(p) for p in pids]
        with rec.lock:
            rec.recording, n1 = False, rec.wrenches
            lat = np.array(rec.latencies_ns, float) * 1e-6
        mem = [memory_mb(p) for p in sensors.node_pids]
        load = os.getloadavg()[0]  # other work on the host's cores skews every figure: say so
        ended = sensors.failed()
        if ended:
            raise CstomoError(f"{ended} during the window; see the logs in {work}")
        time.sleep(1.2)  # the diagnostics of the window's end
        with rec.lock:
            diags = {k: list(v) for k, v in rec.diags.items()}
    finally:
        sensors.stop()
        for s in subs:
            ros_node.destroy_subscription(s)

    window = t1 - t0
    cpu = [1e-7 * cpu_ns(b, a_) / window for b, a_ in zip(th0, th1)]  # exact: the threads' run times
    ticks = [100 * (b - a_) / window for a_, b in zip(k0, k1)]  # a sample: the cross-check
    k = len(sensors.node_pids)
    node_cpu, board_cpu, bench_cpu = cpu[:k], cpu[k:k + n], cpu[-1]
    figs = [_sensor_figures(diags.get(name, []), t0, t1, rate) for name in rec.names]
    sensor_rows = []
    for i, (ns, f) in enumerate(zip(sensors.namespaces, figs)):
        row = {"rate_hz": rate, "stress_field_every": stress, "sensors": n, "hosted": int(hosted), "sensor": ns or "/",
               **{c: f.get(c, math.nan) for c in SENSOR_COLUMNS[5:-1]},
               "node_cpu_pct": round(node_cpu[i], 1) if not hosted else math.nan}
        sensor_rows.append(row)
    wrench_rate = (n1 - n0) / window
    total = lambda key: sum(f.get(key, math.nan) for f in figs) if all(figs) else math.nan  # noqa: E731
    parts = {key: total(key) for key in ("dropped_overflow", "seq_gaps", "late_dropped")}
    dropped = sum(parts.values())
    if not math.isfinite(dropped):  # a sensor without diagnostics: count the missing wrenches instead
        dropped = max(0.0, rate * window - (n1 - n0))
        parts = {key: -1 for key in parts}  # unknown
    f0 = figs[0] or {}
    published_min = min((f.get("published_pct", math.nan) for f in figs), default=math.nan) if all(figs) else math.nan
    nominal_min = min((f.get("published_of_nominal", math.nan) for f in figs), default=math.nan) if all(figs) else math.nan
    frames_all = total("frames")
    frames0 = frames_all if hosted else f0.get("frames", math.nan)  # the frames of the first node process
    node0 = thread_figures(sensors.node_pids[0], th0[0], th1[0], frames0)
    keeps_up = int(wrench_rate >= 0.98 * rate and dropped == 0 and published_min >= 99.9)
    pct = lambda q: float(np.percentile(lat, q)) if lat.size else math.nan  # noqa: E731
    row = {"rate_hz": rate, "stress_field_every": stress, "window_s": round(window, 3), "wrenches": n1 - n0,
           "wrench_rate_hz": round(wrench_rate, 1), "node_frame_rate_hz": round(f0.get("frame_rate_hz", math.nan), 1),
           "frames_dropped": int(dropped), **{key: int(v) for key, v in parts.items()}, "keeps_up": keeps_up,
           "latency_median_ms": round(pct(50), 3),
           "latency_p99_ms": round(pct(99), 3), "latency_max_ms": round(float(lat.max()) if lat.size else math.nan, 3),
           "node_cpu_pct": round(sum(node_cpu), 1),
           "node_cpu_us_per_wrench": round(1e4 * node_cpu[0] * window / max(n1 - n0, 1), 1),  # s0's process
           "board_cpu_pct": round(sum(board_cpu), 1),
           "node_vmrss_mb": round(max(m[0] for m in mem), 1), "node_vmhwm_mb": round(max(m[1] for m in mem), 1),
           "processing_mean_ms": round(f0.get("processing_mean_ms", math.nan), 3),
           "host_loadavg_1m": round(load0, 2),
           "sensors": n, "hosted": int(hosted), "published_min_pct": round(published_min, 3),
           "published_of_nominal_min_pct": round(nominal_min, 3),
           "node_cpu_us_per_frame": round(1e4 * sum(node_cpu) * window / frames_all, 1)
           if math.isfinite(frames_all) and frames_all > 0 else math.nan,
           "node_cpu_max_pct": round(max(node_cpu), 1), "bench_cpu_pct": round(bench_cpu, 1),
           "host_loadavg_end": round(load, 2), "lean": int(bool(a.lean)),
           "node_cpu_ticks_pct": round(sum(ticks[:k]), 1),
           "node0_cpu_us_per_frame": round(1e4 * node_cpu[0] * window / frames0, 1) if frames0 > 0 else math.nan,
           **node0, "outputs": published_topics(diags.get(rec.names[0], []), t0, t1),
           **{c: math.nan for c in COLUMNS if c.startswith("cold_")}}
    return row, sensor_rows


def with_cold(row: dict, cold: dict) -> dict:
    """``row`` with the first node process's per-frame CPU of ``cold`` (the same configuration at a low
    rate) in its ``cold_*`` columns."""
    return dict(row, cold_rate_hz=cold["rate_hz"], cold_host_loadavg_1m=cold["host_loadavg_1m"],
                **{f"cold_{c}": cold[c] for c in _NODE0 + ["node0_threads"]})


def _table(head: list[str], keys: list[str], rows: list[dict]) -> str:
    assert len(head) == len(keys)
    out = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for r in rows:
        cells = [("yes" if r[k] else "no") if k in ("keeps_up", "hosted", "lean") else
                 (r[k] if isinstance(r[k], str) else f"{r[k]:g}") for k in keys]
        out.append("| " + " | ".join(cells) + " |")
    return "\n".join(out)


def markdown(rows: list[dict]) -> str:
    head = ["fps", "stress", "lean", "wrench/s", "node fr/s", "dropped", "overflow", "seq gaps", "late", "keeps up",
            "lat med ms", "lat p99 ms", "node CPU %", "ticks %", "CPU us/wrench", "board CPU %", "VmRSS MB", "VmHWM MB",
            "proc ms", "load 1m"]
    keys = ["rate_hz", "stress_field_every", "lean", "wrench_rate_hz", "node_frame_rate_hz", "frames_dropped",
            "dropped_overflow", "seq_gaps", "late_dropped", "keeps_up",
            "latency_median_ms", "latency_p99_ms", "node_cpu_pct", "node_cpu_ticks_pct", "node_cpu_us_per_wrench",
            "board_cpu_pct", "node_vmrss_mb",
            "node_vmhwm_mb", "processing_mean_ms", "host_loadavg_1m"]
    if any(r.get("sensors", 1) > 1 or r.get("hosted") for r in rows):  # several sensors: the figures of the issue
        head = ["fps", "stress", "lean", "sensors", "hosted", "published min %", "of nominal min %", "dropped", "s0 wrench/s",
                "lat med ms", "lat p99 ms", "nodes CPU %", "max node CPU %", "CPU us/frame", "boards CPU %",
                "bench CPU %", "VmRSS MB", "load 1m start/end"]
        keys = ["rate_hz", "stress_field_every", "lean", "sensors", "hosted", "published_min_pct", "published_of_nominal_min_pct",
                "frames_dropped", "wrench_rate_hz", "latency_median_ms", "latency_p99_ms", "node_cpu_pct",
                "node_cpu_max_pct", "node_cpu_us_per_frame", "board_cpu_pct", "bench_cpu_pct", "node_vmrss_mb", "load"]
        rows = [dict(r, load=f"{r['host_loadavg_1m']:g}/{r['host_loadavg_end']:g}") for r in rows]
    return _table(head, keys, rows)


def threads_markdown(rows: list[dict]) -> str:
    """CPU per frame of the first node process by thread group, warm and (with --cold) cold, and the
    topics it published."""
    head = ["fps", "stress", "lean", "sensors", "hosted", "us/frame", "frame thr", "reader thr", "executor", "other",
            "cold fps", "cold us/frame", "cold frame thr", "cold reader thr", "cold executor", "cold other",
            "load 1m warm/cold", "outputs (msgs/s)"]
    keys = ["rate_hz", "stress_field_every", "lean", "sensors", "hosted", *_NODE0, "cold_rate_hz",
            *[f"cold_{c}" for c in _NODE0], "load", "outputs"]
    rows = [dict(r, load=f"{r['host_loadavg_1m']:g}/{r['cold_host_loadavg_1m']:g}") for r in rows]
    return _table(head, keys, rows)


def sensors_markdown(rows: list[dict]) -> str:
    head = ["fps", "stress", "sensors", "hosted", "sensor", "board fr/s", "published", "published %", "published/s",
            "overflow", "seq gaps", "corrupt", "late", "rejected", "implausible", "node CPU %"]
    keys = ["rate_hz", "stress_field_every", "sensors", "hosted", "sensor", "board_rate_hz", "published", "published_pct",
            "published_rate_hz", "dropped_overflow", "seq_gaps", "corrupt", "late_dropped", "rejected", "implausible",
            "node_cpu_pct"]
    return _table(head, keys, rows)


def parser() -> argparse.ArgumentParser:
    """This command's argument parser (cli.subcommand_parser)."""
    p = ToolParser(prog="cstomo bench-node", description=help_text(__doc__.splitlines()[0]))
    p.add_argument("--rates", type=positive("frames per second > 0"), nargs="+", default=[100.0, 1000.0], metavar="HZ",
                   help="board frame rates")
    p.add_argument("--stress", type=positive("a whole number >= 0", zero=True, kind=int), nargs="+", default=[0, 1],
                   metavar="N", help="stress_field_every values (0 = off)")
    p.add_argument("--sensors", type=positive("a whole number >= 1", kind=int), nargs="+", default=[1], metavar="N",
                   help="numbers of boards and sensors run together (default 1)")
    p.add_argument("--hosted", action="store_true",
                   help="the sensors in one cstomo_sensor_host process (default: a cstomo_sensor_node each)")
    p.add_argument("--lean", action="store_true",
                   help="a minimal rclpy loop (read, estimate, publish) in place of each node: the floor of an rclpy node")
    p.add_argument("--both", action="store_true", help="every configuration with a process each and hosted")
    p.add_argument("--seconds", type=positive("seconds > 0"), default=10.0, metavar="S",
                   help="measured window per configuration")
    p.add_argument("--warmup", type=positive("seconds >= 0", zero=True), default=2.0, metavar="S",
                   help="seconds after the first wrench before measuring")
    p.add_argument("--cold", action="store_true",
                   help="every configuration also at --cold-rate (frames after an idle period; doubles the run time)")
    p.add_argument("--cold-rate", type=positive("frames per second > 0"), default=10.0, metavar="HZ",
                   help="the cold run's frame rate")
    p.add_argument("--out", default=".", metavar="DIR", help="directory for the tables and the processes' logs")
    add_setting_arg(p, "sensor")
    add_setting_arg(p, "estimator")
    return p


def main(argv: list[str] | None = None) -> int:
    p = parser()
    a = p.parse_args(argv)
    if min(a.sensors) < 1:
        p.error("--sensors: at least 1")
    if a.lean and (a.hosted or a.both):
        p.error("--lean runs the lean loop in place of each node process: not with --hosted or --both")

    local_ros_env(30)
    os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)

    print("model and force estimator (built once, then loaded from the cache)", flush=True)
    t = time.monotonic()
    Pipeline.build(PipelineConfig(sensor=a.sensor, estimator=a.estimator))
    print(f"     ready in {time.monotonic() - t:.1f} s", flush=True)

    work = Path(tempfile.mkdtemp(prefix="cstomo_bench_node_", dir=out))
    script = work / "load.csv"  # constant load: unloaded 2 s (tare), then 20 N pushing straight down
    np.savetxt(script, [[0.0, 0, 0, 0], [2.0, 0, 0, -20.0]], delimiter=",", header="time,fx,fy,fz", comments="")

    rclpy.init()
    ros_node = rclpy.create_node("cstomo_bench_node")
    spin = threading.Thread(target=rclpy.spin, args=(ros_node,), daemon=True)
    spin.start()
    rows, sensor_rows = [], []
    modes = [False, True] if a.both else [a.hosted]
    try:
        for rate in a.rates:
            for stress in a.stress:
                for n in a.sensors:
                    for hosted in modes:
                        what = f"{n} sensors" + (" hosted" if hosted else " (a process each)" if n > 1 else "")
                        what += ", lean loop" if a.lean else ""
                        print(f"run: {rate:g} fps, stress_field_every {stress}, {what}, {a.seconds:g} s window ...",
                              flush=True)
                        t = time.monotonic()
                        row, per_sensor = run_one(ros_node, a, rate, stress, work, script, n, hosted)
                        if a.cold:
                            print(f"     cold: the same at {a.cold_rate:g} fps ...", flush=True)
                            row = with_cold(row, run_one(ros_node, a, a.cold_rate, stress, work, script, n, hosted)[0])
                        rows.append(row)
                        sensor_rows += per_sensor
                        print(f"     done in {time.monotonic() - t:.1f} s: published min {row['published_min_pct']:g} %, "
                              f"p99 {row['latency_p99_ms']:g} ms, nodes {row['node_cpu_pct']:g} % of a core, "
                              f"load {row['host_loadavg_end']:g}", flush=True)
    finally:
        ros_node.destroy_node()
        rclpy.try_shutdown()
        spin.join(2.0)

    path = out / "node_bench.csv"
    with open(path, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=COLUMNS)
        w.writeheader()
        w.writerows(rows)
    with open(out / "node_bench_sensors.csv", "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=SENSOR_COLUMNS)
        w.writeheader()
        w.writerows(sensor_rows)
    text = (f"{markdown(rows)}\n\nCPU per frame of the first node process by thread, us (cold: "
            f"{'at ' + format(a.cold_rate, 'g') + ' fps' if a.cold else 'not measured, see --cold'}):\n\n"
            f"{threads_markdown(rows)}\n\nPer sensor:\n\n{sensors_markdown(sensor_rows)}\n\nMethod: {METHOD}\n")
    (out / "node_bench.md").write_text(text)
    print()
    print(text)
    print(f"wrote {path}, node_bench_sensors.csv and node_bench.md in {out}; logs in {work}")
    return 0
