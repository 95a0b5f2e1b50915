"""Measure the fault table of docs/faults.md: each fault injected into the simulated board (a real pty)
while the node (real rclpy, the test harness of conftest.py) reads it under a 20 N load.

    PYTHONPATH=. OPENBLAS_NUM_THREADS=1 ROS_DOMAIN_ID=41 python test/fault_table.py [NAME ...]

Per fault it prints: survived (the frame thread alive and wrenches in the last second), frames lost
outside the fault (frames the board measured outside the fault window, after the tare, that gave no
wrench, less those the fault itself harmed), the recovery time (first wrench after the window ends,
or after the board is back), and the worst diagnostics status during the fault. Frames are matched
to wrenches by their board time (the wrench stamp minus the host clock offsets).
"""
from __future__ import annotations

import math
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from conftest import BagSource, diag, diag_records, start, wait_for  # noqa: E402

RATE = 100.0
T_FAULT = 2.0   # board seconds at which each fault starts
RUN = 7.0       # board seconds each scenario runs
LOADED = slice(30, 60)  # bag frames under a held 20 N load


class Recorded:
    """The bag's loaded frames, recording the board time of every frame measured; ``harm(v)`` is
    applied inside the window [a, b)."""

    def __init__(self, bag, window=(math.inf, math.inf), harm=None):
        self.frames, self.window, self.harm, self.times = bag.frames[LOADED], window, harm, []

    def frame(self, t, rng):
        self.times.append(time.monotonic())  # just before the board reads its clock for the frame
        v = self.frames[int(round(t * RATE)) % len(self.frames)]
        a, b = self.window
        return self.harm(v) if self.harm is not None and a <= t < b else v

    def truth(self, t):
        return np.zeros(3)


def scenarios():
    from cstomo_sensor.board.sim import FaultConfig

    w = (T_FAULT, T_FAULT + 0.5)
    return {
        "all contacts false 0.5 s": (dict(faults=FaultConfig(no_contact_at=w[0], no_contact_for=0.5)), w, None),
        "all channels saturated 0.5 s": (dict(faults=FaultConfig(saturate_all_at=w[0], saturate_all_for=0.5)), w, None),
        "all-zero frames 1 s": (dict(), (T_FAULT, T_FAULT + 1.0), lambda v: np.zeros_like(v)),
        "huge values (x1e6) 0.5 s": (dict(), w, lambda v: v * 1e6),
        "bit flips 5 %": (dict(faults=FaultConfig(bit_flip=0.05)), None, None),
        "truncated frames 5 %": (dict(faults=FaultConfig(truncate=0.05)), None, None),
        "garbage bursts 5 %": (dict(faults=FaultConfig(garbage=0.05)), None, None),
        "NaN values 5 %": (dict(faults=FaultConfig(nan=0.05)), None, None),
        "dropped frames 5 %": (dict(faults=FaultConfig(drop=0.05)), None, None),
        "stall 2 s": (dict(faults=FaultConfig(stall_at=T_FAULT, stall_for=2.0)), (T_FAULT, T_FAULT + 2.0), None),
        "unplug 3.3 s, replug": (dict(faults=FaultConfig(disconnect_at=T_FAULT, reappear_after=3.3)), "replug", None),
        "board killed, new board 3.3 s later": ({}, "restart", None),
    }


def run(ros, tmp, bag, name, kwargs, window, harm):
    from geometry_msgs.msg import WrenchStamped

    from cstomo_sensor.board.sim import SimulatedBoard

    src = Recorded(bag, window if isinstance(window, tuple) else (math.inf, math.inf), harm)
    h, board = start(ros, tmp, src, rate=RATE, tare_on_start=True, tare_frames=5, pty=True, **kwargs)
    boards, sources = [board], [src]
    try:
        wr = h.record("/cstomo_sensor/wrench", WrenchStamped)
        dg = diag_records(h)
        board.start()
        assert wait_for(lambda: getattr(board, "_t0_ns", None) is not None, 5.0)
        t0 = board._t0_ns / 1e9  # the board's time origin on the monotonic clock
        wall_minus_mono = time.time() - time.monotonic()
        if window == "restart":
            time.sleep(T_FAULT)
            board.close()
            time.sleep(3.3)
            sources.append(Recorded(bag))
            boards.append(SimulatedBoard(sources[-1], rate_hz=RATE, link=board.device, seed=5).start())
            back = boards[-1].stats().generation_opened[0]
            time.sleep(RUN - T_FAULT - 3.3)
        else:
            time.sleep(RUN)
        alive = h.node._thread.is_alive()
    finally:
        for b in boards:
            b.close()
        h.close()
    recv = np.array([t for t, _ in wr])
    stamps = np.array([m.header.stamp.sec + m.header.stamp.nanosec * 1e-9 for _, m in wr])
    board_t = stamps - wall_minus_mono - t0  # the wrench's board time
    if window == "replug":
        back = board.stats().generation_opened[1]
        window = (T_FAULT, back - t0)
    elif window == "restart":
        window = (T_FAULT, back - t0)
    times = np.array(src.times[5:] + sum((s.times for s in sources[1:]), [])) - t0  # after the tare
    if window is None:
        outside = times
    else:
        outside = times[(times < window[0] - 0.02) | (times >= window[1] + 0.02)]
    # in order: each wrench takes the earliest unmatched frame within 0.9 periods (its board clock is
    # read a little after the frame is recorded here, never before)
    matched = np.zeros(len(outside), bool)
    j, tol = 0, 0.9 / RATE
    for bt in np.sort(board_t):
        while j < len(outside) and outside[j] < bt - tol:
            j += 1
        if j < len(outside) and abs(outside[j] - bt) < tol:
            matched[j] = True
            j += 1
    inj = board.stats().injected
    harmed = sum(inj.get(k, 0) for k in ("bit_flip", "truncate", "nan", "drop", "overrun")) if window is None else 0
    lost = int((~matched).sum()) - harmed
    end = window[1] if window is not None else None
    recovery = (recv[recv > t0 + end][0] - (t0 + end)) if end is not None and np.any(recv > t0 + end) else math.nan
    during = [diag(m) for t, m in dg if window is None or t0 + window[0] <= t <= t0 + window[1] + 1.0]
    worst = max(during, key=lambda d: d[0]) if during else (0, "", {})
    last_s = bool(np.any(recv > recv.max() - 1.0)) if len(recv) else False
    end_kv = diag(dg[-1][1])[2] if dg else {}
    keys = ("corrupt", "seq_gaps", "resyncs", "late_dropped", "frames_rejected", "implausible", "reconnects")
    counts = ", ".join(f"{k} {end_kv[k]}" for k in keys if end_kv.get(k, "0") != "0")
    return dict(name=name, survived=alive and last_s, lost=lost, unmatched=outside[~matched], counts=counts,
                harmed=harmed, recovery=recovery,
                level="OK WARN ERROR STALE".split()[worst[0]], message=worst[1], kv=worst[2])


def main(argv: list[str]) -> int:
    import rclpy
    from conftest import PIPE

    from cstomo_sensor.frame_path.config import PipelineConfig
    from cstomo_sensor.frame_path.pipeline import Pipeline

    Pipeline.build(PipelineConfig(**{k: (tuple(v) if k == "grid" else v) for k, v in PIPE.items()}))
    ctx = rclpy.Context()
    rclpy.init(context=ctx)
    bag = BagSource()
    rows = []
    try:
        for name, (kwargs, window, harm) in scenarios().items():
            if argv and not any(a in name for a in argv):
                continue
            with tempfile.TemporaryDirectory() as tmp:
                r = run(ctx, Path(tmp), bag, name, kwargs, window, harm)
            rows.append(r)
            if os.environ.get("FAULT_TABLE_DEBUG"):
                print(name, "unmatched board times:", np.round(r["unmatched"], 3).tolist())
            rec = "" if math.isnan(r["recovery"]) else f"{r['recovery'] * 1e3:.0f} ms"
            print(f"| {name} | {'yes' if r['survived'] else 'NO'} | {r['lost']} | {rec} | {r['level']}: {r['message']} "
                  f"| {r['counts']} |", flush=True)
    finally:
        rclpy.try_shutdown(context=ctx)
    return 0 if all(r["survived"] for r in rows) else 1


if __name__ == "__main__":
    os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
    sys.exit(main(sys.argv[1:]))
