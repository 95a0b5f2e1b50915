"""``cstomo bench-node``: latency, CPU and memory of the real node on the real simulated board.

For each frame rate in ``--rates`` and with the stress field off (``stress_field_every:=0``) and
on (``:=1``), starts ``cstomo_sensor_node`` (tare on start) and ``cstomo board-sim`` (binary
protocol, a constant load script: unloaded for 2 s, then 20 N pushing straight down) on a pty
link, as ``cstomo demo`` does, subscribes to ``~/wrench`` and ``/diagnostics`` with rclpy and, over
a window of ``--seconds`` after a warm-up, measures:

* latency = receive time in this subscriber (``time.time_ns()``, the system clock: the node's host
  time is its ROS clock, which is the system clock without ``use_sim_time``) minus the wrench's
  ``header.stamp``. The stamp is the board's write time mapped onto host time by the lower envelope
  of ``host_time - board_time`` (board.clock.ClockMapper), so it is the board's write time *plus the
  smallest transport delay seen* (pty + serial driver thread + queue hand-over): that minimum is
  not included in the latency; what is measured is everything above it (processing, DDS,
  the subscriber's executor, scheduling);
* CPU of the node process (all threads): utime+stime from /proc/<pid>/stat over the window, in %
  of one core and in microseconds per wrench received (and of the board simulator, which shares the
  2 cores);
* wrenches received per second, the node's frames per second and its dropped frames (queue
  overflow, late, sequence gaps: differences of the /diagnostics counters over the window);
* VmRSS and VmHWM of the node from /proc/<pid>/status at the end of the window.

Prints a markdown table and writes ``node_bench.csv`` in ``--out``.
"""
from __future__ import annotations

import argparse
import csv
import math
import os
import tempfile
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import rclpy
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import WrenchStamped

from ...errors import CstomoError
from ...force.estimate import ESTIMATORS
from ...force.pipeline import Pipeline, PipelineConfig
from ..common import DEFAULTS, NodeWithBoard, local_ros_env

COLUMNS = ["rate_hz", "stress_field_every", "window_s", "wrenches", "wrench_rate_hz", "node_frame_rate_hz",
           "frames_dropped", "dropped_overflow", "seq_gaps", "late_dropped", "keeps_up",
           "latency_median_ms", "latency_p99_ms", "latency_max_ms",
           "node_cpu_pct", "node_cpu_us_per_wrench", "board_cpu_pct", "node_vmrss_mb", "node_vmhwm_mb",
           "processing_mean_ms", "host_loadavg_1m"]

METHOD = ("latency = subscriber receive time (time.time_ns, system clock = the node's ROS clock) - "
          "wrench header.stamp (board write time mapped to host time by the lower envelope of "
          "host_time - board_time); caveat: the minimum transport delay (pty + driver + queue hand-over) is "
          "absorbed into the clock offset and NOT included. CPU = utime+stime of the process (all threads) "
          "over the window, % of one core. dropped = diagnostics dropped_overflow + late_dropped + seq_gaps "
          "over the window. load 1m = the host's 1-minute load average at the window's end (2 cores here: "
          "above ~1.5 the figures include contention with other work).")

_TICK = os.sysconf("SC_CLK_TCK")


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


@dataclass
class _Recorder:
    """What the subscriber sees; ``recording`` gates the latency samples to the window."""
    lock: threading.Lock = field(default_factory=threading.Lock)
    wrenches: int = 0
    recording: bool = False
    latencies_ns: list = field(default_factory=list)
    diags: list = field(default_factory=list)  # (time.monotonic(), {key: value})

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
            if s.name.startswith("/cstomo_sensor:"):  # the node's full name (namespace included)
                with self.lock:
                    self.diags.append((now, {kv.key: kv.value for kv in s.values}))


def _num(d: dict, key: str) -> float:
    try:
        return float(d.get(key, "nan"))
    except ValueError:
        return math.nan


def run_one(ros_node, a, rate: float, stress: int, work: Path, script: Path) -> dict:
    """One configuration: node + board, warm-up, measured window; a row of COLUMNS."""

    rec = _Recorder()
    subs = [ros_node.create_subscription(WrenchStamped, "/cstomo_sensor/wrench", rec.on_wrench, 100),
            ros_node.create_subscription(DiagnosticArray, "/diagnostics", rec.on_diag, 10)]
    tag = f"r{rate:g}_s{stress}"
    # startup (rclpy import, model load, tare, 2 s unloaded) + warm-up + window + margin
    duration = 30.0 + a.warmup + a.seconds
    params = {"sensor": a.sensor, "estimator": a.estimator, "rate_hz": rate, "protocol": "binary",
              "tare_on_start": "true", "tare_frames": 50, "tare_file": work / "tare.csv", "stress_field_every": stress}
    board_args = ["--sensor", a.sensor, "--load-script", str(script), "--rate", str(rate), "--duration", str(duration),
                  "--protocol", "binary"]
    logs = [open(work / f"node_{tag}.log", "w"), open(work / f"board_{tag}.log", "w")]
    run = NodeWithBoard(work / f"board_{tag}", params, board_args, node_out=logs[0], board_err=logs[1])
    try:
        try:
            run.start()
        except CstomoError as err:
            raise CstomoError(f"{err}; see {logs[1].name}") from None
        node, board = run.node, run.board
        deadline = time.monotonic() + 60.0
        while rec.wrenches == 0 or not rec.diags:  # the window's counters start from a diagnostics message
            if time.monotonic() > deadline or node.poll() is not None or board.poll() is not None:
                raise CstomoError(f"no wrench and diagnostics from the node within 60 s; see {logs[0].name}")
            time.sleep(0.05)
        time.sleep(a.warmup)  # past the tare and the step to 20 N; queues and caches settled

        with rec.lock:
            rec.recording, n0 = True, rec.wrenches
        t0, c0, b0 = time.monotonic(), cpu_seconds(node.pid), cpu_seconds(board.pid)
        time.sleep(a.seconds)
        t1, c1, b1 = time.monotonic(), cpu_seconds(node.pid), cpu_seconds(board.pid)
        with rec.lock:
            rec.recording, n1 = False, rec.wrenches
            lat = np.array(rec.latencies_ns, float) * 1e-6
        rss, hwm = memory_mb(node.pid)
        load = os.getloadavg()[0]  # other work on the host's cores skews every figure: say so
        with rec.lock:
            diags = list(rec.diags)
    finally:
        run.stop()
        for s in subs:
            ros_node.destroy_subscription(s)
        for f in logs:
            f.close()

    window = t1 - t0
    wrench_rate = (n1 - n0) / window
    # diagnostics (1 Hz, cumulative counters): from the last one at or before the window's start to
    # the last one in the window (at least seconds - 1 s of it)
    before = [(t, d) for t, d in diags if t <= t0]
    inside = [(t, d) for t, d in diags if t0 < t <= t1]
    node_rate, proc_ms = math.nan, math.nan
    parts = {k: math.nan for k in ("dropped_overflow", "seq_gaps", "late_dropped")}
    if before and inside:
        (tb, db), (ta, da) = before[-1], inside[-1]
        node_rate = (_num(da, "frames") - _num(db, "frames")) / (ta - tb)
        parts = {k: _num(da, k) - _num(db, k) for k in parts}
        proc = [x for x in (_num(d, "processing_time_mean_ms") for _, d in inside) if math.isfinite(x)]
        proc_ms = float(np.mean(proc)) if proc else math.nan
    dropped = sum(parts.values())
    if not math.isfinite(dropped):  # no diagnostics: count the missing wrenches instead
        dropped = max(0.0, rate * window - (n1 - n0))
        parts = {k: -1 for k in parts}  # unknown
    keeps_up = int(wrench_rate >= 0.98 * rate and dropped == 0)
    pct = lambda q: float(np.percentile(lat, q)) if lat.size else math.nan  # noqa: E731
    return {"rate_hz": rate, "stress_field_every": stress, "window_s": round(window, 3), "wrenches": n1 - n0,
            "wrench_rate_hz": round(wrench_rate, 1), "node_frame_rate_hz": round(node_rate, 1),
            "frames_dropped": int(dropped), **{k: int(v) for k, v in parts.items()}, "keeps_up": keeps_up,
            "latency_median_ms": round(pct(50), 3),
            "latency_p99_ms": round(pct(99), 3), "latency_max_ms": round(float(lat.max()) if lat.size else math.nan, 3),
            "node_cpu_pct": round(100 * (c1 - c0) / window, 1),
            "node_cpu_us_per_wrench": round(1e6 * (c1 - c0) / max(n1 - n0, 1), 1), "board_cpu_pct": round(100 * (b1 - b0) / window, 1),
            "node_vmrss_mb": round(rss, 1), "node_vmhwm_mb": round(hwm, 1), "processing_mean_ms": round(proc_ms, 3),
            "host_loadavg_1m": round(load, 2)}


def markdown(rows: list[dict]) -> str:
    head = ["fps", "stress", "wrench/s", "node fr/s", "dropped", "overflow", "seq gaps", "late", "keeps up",
            "lat med ms", "lat p99 ms", "node CPU %", "CPU us/wrench", "board CPU %", "VmRSS MB", "VmHWM MB", "proc ms", "load 1m"]
    keys = ["rate_hz", "stress_field_every", "wrench_rate_hz", "node_frame_rate_hz", "frames_dropped",
            "dropped_overflow", "seq_gaps", "late_dropped", "keeps_up",
            "latency_median_ms", "latency_p99_ms", "node_cpu_pct", "node_cpu_us_per_wrench", "board_cpu_pct", "node_vmrss_mb",
            "node_vmhwm_mb", "processing_mean_ms", "host_loadavg_1m"]
    assert len(head) == len(keys)
    out = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for r in rows:
        cells = [("yes" if r[k] else "no") if k == "keeps_up" else f"{r[k]:g}" for k in keys]
        out.append("| " + " | ".join(cells) + " |")
    return "\n".join(out)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="cstomo bench-node", description=__doc__.splitlines()[0])
    p.add_argument("--rates", type=float, nargs="+", default=[100.0, 1000.0], help="board frame rates, Hz")
    p.add_argument("--stress", type=int, nargs="+", default=[0, 1], help="stress_field_every values (0 = off)")
    p.add_argument("--seconds", type=float, default=10.0, help="measured window per configuration, s")
    p.add_argument("--warmup", type=float, default=2.0, help="s after the first wrench before measuring")
    p.add_argument("--out", default=".", help="directory for node_bench.csv and the processes' logs")
    p.add_argument("--sensor", default=DEFAULTS.sensor)
    p.add_argument("--estimator", default=DEFAULTS.estimator, choices=ESTIMATORS)
    a = p.parse_args(argv)

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
    rows = []
    try:
        for rate in a.rates:
            for stress in a.stress:
                print(f"run: {rate:g} fps, stress_field_every {stress}, {a.seconds:g} s window ...", flush=True)
                t = time.monotonic()
                rows.append(run_one(ros_node, a, rate, stress, work, script))
                print(f"     done in {time.monotonic() - t:.1f} s", flush=True)
    finally:
        ros_node.destroy_node()
        rclpy.try_shutdown()
        spin.join(2.0)

    path = out / "node_bench.csv"
    with open(path, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=COLUMNS)
        w.writeheader()
        w.writerows(rows)
    print()
    print(markdown(rows))
    print(f"\nMethod: {METHOD}")
    print(f"wrote {path}; logs in {work}")
    return 0
