"""Issue 14, time and recovery: a step of the host's ROS clock does not blank the output (frames are
judged late on the monotonic clock), and the node publishes again within a second of a replugged or
restarted board. Real rclpy, a simulated board on a virtual link (conftest.start)."""
from __future__ import annotations

import re
import threading
import time

import numpy as np
import pytest
from conftest import diag, diag_records, start, wait_for

rclpy = pytest.importorskip("rclpy")


@pytest.mark.slow  # starts a node
def test_a_forward_step_of_the_host_clock_does_not_blank_the_output(ros, tmp_path, source, warm_model):
    """The node's ROS clock (use_sim_time, driven by /clock here as ntp or a user would step the wall
    clock) jumps 30 s forward, far beyond stale_timeout (1 s): wrenches go on within half a second,
    stamped on the new clock, and no frame is dropped as late. Before issue 14 every frame was "late"
    for clock_window (10 s) while the diagnostics said OK."""
    from geometry_msgs.msg import WrenchStamped
    from rosgraph_msgs.msg import Clock

    # stale_timeout 1 s (still 30 times below the step): a loaded host that starves the in-process
    # board for 0.3 s must not make this test about stalls
    h, board = start(ros, tmp_path, source, rate=100.0, tare_on_start=True, tare_frames=5, use_sim_time=True,
                     stale_timeout=1.0)
    pub = h.probe.create_publisher(Clock, "/clock", 10)
    step = {"at": None, "offset": 1000.0}
    published = []  # (monotonic s, ROS time s) of every /clock message
    stop = threading.Event()

    def tick():  # ROS time = 1000 s + monotonic time, plus 30 s from the step on
        while not stop.is_set():
            t = time.monotonic()
            if step["at"] is not None and t >= step["at"]:
                step["offset"] = 1030.0
            ns = int((step["offset"] + t) * 1e9)
            published.append((time.monotonic(), ns * 1e-9))  # before the node can have it
            pub.publish(Clock(clock=rclpy.time.Time(nanoseconds=ns).to_msg()))
            stop.wait(0.05)  # a 20 Hz /clock: enough for the stamps, light on the in-process board

    clock = threading.Thread(target=tick, daemon=True)
    clock.start()
    try:
        wr = h.record("/cstomo_sensor/wrench", WrenchStamped)
        dg = diag_records(h)
        board.start()
        assert wait_for(lambda: len(wr) > 50, 30.0), len(wr)
        step["at"] = t_step = time.monotonic() + 0.2
        assert wait_for(lambda: time.monotonic() > t_step, 5.0)
        frames_at_step = h.node.stream.counter.counts.frames
        assert wait_for(lambda: time.monotonic() > t_step + 2.5, 5.0)
        late = h.node.stream.counter.counts.late
        frames = h.node.stream.counter.counts.frames - frames_at_step
    finally:
        stop.set()
        clock.join()
        board.close()
        h.close()
    after = [(t, m) for t, m in wr if t > t_step]
    print(f"clock step: first wrench {(after[0][0] - t_step) * 1e3:.0f} ms after it, {late} late" if after else "")
    # (bounds loose for a loaded machine; before the fix: no wrench for 10 s, every frame late)
    assert after and after[0][0] - t_step < 1.0, (after[:1], t_step)
    times = np.array([t for t, _ in after])
    # no blackout: every frame the node received after the step gave a wrench (the in-process board,
    # sharing the GIL with the node, the probe and the clock thread, does not always keep its 100
    # frames/s on a loaded host: a CI run saw 1.75 s without a frame, none of them late)
    assert frames > 20 and len(times) >= frames - 5, (frames, len(times))
    stamps = np.array([m.header.stamp.sec + m.header.stamp.nanosec * 1e-9 for _, m in after[20:]])
    # each stamp is on the new clock: the last /clock published before the wrench arrived, minus the
    # frame's age (at most a few frames). Judged against the /clock actually sent, not against 1030 s +
    # the monotonic time: on a loaded host the /clock thread itself stalls (a CI run saw a stamp 0.5 s
    # behind the monotonic time with every /clock message on time relative to it), and the old clock
    # is 30 s away from either.
    at, ros_s = np.array(published).T
    last_clock = ros_s[np.searchsorted(at, times[20:], side="right") - 1]
    lag = last_clock - stamps
    assert np.all((lag > -1e-3) & (lag < 0.5)), (lag.min(), lag.max())
    assert late < 10, late
    assert not any("late" in diag(m)[1] for t, m in dg if t > t_step), [diag(m)[1] for _, m in dg]


#: s: the board's outage. The old backoff (0.05 s doubling to 2 s) retried 1.55 s and 3.15 s after the loss: back
#: after 1.8 s, it read again 1.35 s later (> the 1 s judged), and a loss noticed up to 0.25 s late still shows it
OUTAGE_S = 1.8


@pytest.mark.parametrize("how", ["replug", "restart"])
@pytest.mark.slow
def test_the_node_publishes_within_a_second_of_the_board_coming_back(ros, tmp_path, source, warm_model, how):
    """replug: the board's link disappears for 1.8 s and comes back (its clock and counter go on);
    restart: the board is killed and a new one (clock and counter from zero) appears on the same link
    1.8 s later. The time from the board being back (its link open) to the first new wrench's frame is
    under 1 s (before issue 14 the doubling reconnect backoff retried at 1.55 s, then 3.15 s: 1.35 s; an
    outage of 3.3 s showed the same, 1.85 s, in 1.5 s more per run). The diagnostics' last error clears and
    the status returns to OK."""
    from geometry_msgs.msg import WrenchStamped

    from cstomo_sensor.board.sim import FaultConfig, SimulatedBoard

    faults = FaultConfig(disconnect_at=1.5, reappear_after=OUTAGE_S) if how == "replug" else None
    h, board = start(ros, tmp_path, source, faults=faults, rate=100.0, tare_on_start=True, tare_frames=5)
    boards = [board]
    try:
        wr = h.record("/cstomo_sensor/wrench", WrenchStamped)
        dg = diag_records(h)
        board.start()
        assert wait_for(lambda: len(wr) > 50, 30.0)
        if how == "replug":
            assert wait_for(lambda: len(board.stats().generation_opened) == 2, 10.0)
            back = board.stats().generation_opened[1]
        else:
            board.close()
            time.sleep(OUTAGE_S)
            boards.append(SimulatedBoard(source, rate_hz=100.0, link=board.device, seed=5))
            back = boards[-1].stats().generation_opened[0]
            boards[-1].start()
        assert wait_for(lambda: any(t > back for t, _ in wr), 5.0), "no wrench after the board came back"
        received = next(t for t, _ in wr if t > back) - back
        assert wait_for(lambda: len(dg) and diag(dg[-1][1])[0] == 0 and dg[-1][0] > back + 1.0, 10.0), \
            [diag(m)[1] for _, m in dg[-3:]]
    finally:
        for b in boards:
            b.close()
        h.close()
    # judged on the first new wrench's stamp (when the board measured its frame, on the monotonic clock):
    # the reconnect's delay alone. Its arrival here adds the node's and the probe's scheduling, which
    # a loaded host stretches (a CI run saw 1.75 s without a frame in this harness): printed, not judged.
    ros_to_mono = time.monotonic() - time.time()  # the node's ROS clock is the system clock
    stamps = np.array([m.header.stamp.sec + m.header.stamp.nanosec * 1e-9 for _, m in wr]) + ros_to_mono
    recovery = stamps[stamps > back].min() - back
    print(f"{how}: first new frame measured {recovery * 1e3:.0f} ms after the board was back, its wrench "
          f"received after {received * 1e3:.0f} ms")
    assert recovery < 1.0, recovery
    level, message, v = diag(dg[-1][1])
    assert v["last_error"] == "" and v["connected"] == "True" and v["stale_reason"] == "", v
    assert int(v["reconnects"]) >= 1


@pytest.mark.slow  # starts a node
@pytest.mark.parametrize("drop, level", [pytest.param(0.0, 0, marks=pytest.mark.slow), (0.05, 1),
                                         pytest.param(0.4, 2, marks=pytest.mark.slow)])
def test_lost_frames_raise_the_level_above_the_stated_fractions(ros, tmp_path, source, warm_model, drop, level):
    """A board that loses a fraction of its frames (measured, never sent: sequence gaps): none is OK,
    5 % is WARN (above LOSS_WARN = 1 % over the last 5 s), 40 % is ERROR (above LOSS_ERROR = 20 %);
    the message says how many and of what kind. Before issue 14 gaps never raised the level."""
    from cstomo_sensor.board.sim import FaultConfig
    from cstomo_sensor.frame_path.health import LOSS_ERROR, LOSS_WARN

    assert LOSS_WARN < 0.05 < LOSS_ERROR < 0.4
    h, board = start(ros, tmp_path, source, faults=FaultConfig(drop=drop), rate=100.0, tare_on_start=True,
                     tare_frames=5)
    try:
        dg = diag_records(h)
        t0 = time.monotonic()
        board.start()
        assert wait_for(lambda: sum(t > t0 + 2.5 for t, _ in dg) >= 2, 10.0)
    finally:
        board.close()
        h.close()
    # the frames a loaded host lost itself count as well: its frame queue overflowed, frames went late,
    # or its reader left the link full (the board's overrun: a partial frame, corrupt). A run at load 5
    # saw "4 of 299 frames lost or dropped in the last 3 s (overflow 4)" with drop 0: WARN, rightly.
    overrun = board.stats().injected.get("overrun", 0)
    host = {"overflow", "late"} | ({"corrupt", "gaps"} if overrun else set())

    def kinds(msg):
        m = re.search(r"frames lost or dropped in the last \d+ s \(([^)]*)\)", msg)
        return {part.split()[0] for part in m.group(1).split(", ")} if m else set()

    late = [diag(m) for t, m in dg if t > t0 + 2.5]
    if level:
        assert all(lv == level for lv, _, _ in late), [(lv, msg) for lv, msg, _ in late]
        assert all("frames lost or dropped in the last" in msg and "gaps" in msg for _, msg, _ in late), late
        assert all(int(v["seq_gaps"]) > 0 and int(v["corrupt"]) <= overrun for _, _, v in late), (late, overrun)
    else:  # OK, or WARN for the host's own losses only: never for losses of the board's
        assert all(lv == 0 or (lv == 1 and kinds(msg) and kinds(msg) <= host) for lv, msg, _ in late), \
            ([(lv, msg) for lv, msg, _ in late], overrun)


@pytest.mark.slow
def test_a_one_frame_per_second_board_streams_without_reconnecting(ros, tmp_path, source, warm_model):
    """The node with a 1 frame/s board and stale_timeout 0.3 s: one connection and a wrench per frame
    (the data is stale between frames, and the diagnostics say so: stale_timeout is below the
    board's period). Before issue 14 the stall timeout followed stale_timeout: the node reopened the
    port every 0.3 s for ever, each time re-reading the first frame after START."""
    from geometry_msgs.msg import WrenchStamped

    h, board = start(ros, tmp_path, source, rate=1.0, tare_on_start=True, tare_frames=1)
    try:
        wr = h.record("/cstomo_sensor/wrench", WrenchStamped)
        dg = diag_records(h)
        board.start()
        time.sleep(4.5)  # 4 periods: the old rule had reopened the port every 0.3 s, 15 times by then
        st = h.node.driver.stats()
    finally:
        board.close()
        h.close()
    assert st.reconnects == 0 and st.period == pytest.approx(1.0, rel=0.05), st
    assert 3 <= len(wr) <= 4, len(wr)  # frames 1..4 (frame 0 is the tare)
    _, _, v = diag(dg[-1][1])
    assert v["frame_period_ms"].startswith(("99", "100")) and v["reconnects"] == "0", v
