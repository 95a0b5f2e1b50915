"""End to end over a real pseudo-terminal: SimulatedBoard (in a thread) -> BoardDriver."""
import logging
import signal
import time

import numpy as np
import pytest
from conftest import board_link

from cstomo_sensor.board.driver import BoardDriver
from cstomo_sensor.board.sim import FaultConfig, SimulatedBoard
from cstomo_sensor.board.wire import DataFrame, encode
from cstomo_sensor.errors import ConfigError
from cstomo_sensor.model.pattern import MeasurementPattern

RATE = 400.0


class CountingSource:
    """The k-th frame asked for is k + i / 1024 (exact in float32), and every frame is kept."""

    def __init__(self):
        self.frames = []

    def frame(self, t, rng):
        v = len(self.frames) + np.arange(208) / 1024
        self.frames.append(v.copy())
        return v

    def truth(self, t):
        return np.zeros(3)


def wait_for(pred, timeout=5.0):
    deadline = time.monotonic() + timeout
    while not pred():
        if time.monotonic() > deadline:
            return False
        time.sleep(0.01)
    return True


def drain(driver, quiet=0.3):
    """Every frame the driver delivers until none comes for ``quiet`` seconds."""
    out = []
    while (f := driver.get(quiet)) is not None:
        out.append(f)
    return out


def run(tmp_path, faults=FaultConfig(), protocol="binary", duration=1.0, queue_size=4096, rate=RATE, src=None,
        virtual=False, **driver_kw):
    """Connect a driver to a fresh board (on a pty, linked in tmp_path; ``virtual``: on a virtual link),
    stream for ``duration``, return everything that arrived."""
    src = src or CountingSource()
    board = SimulatedBoard(src, protocol=protocol, rate_hz=rate, duration=duration, link=board_link(tmp_path, pty=not virtual),
                           faults=faults, seed=1)
    driver = BoardDriver(board.device, protocol=protocol, queue_size=queue_size, **driver_kw)
    try:
        assert wait_for(lambda: driver.stats().connected)
        board.start()
        frames = []
        while not board.join(0.05):
            frames += drain(driver, quiet=0.0)
        frames += drain(driver)
        return src, board.stats(), driver.stats(), frames
    finally:
        driver.close()
        board.close()


def check_values(frames, src, skip=()):
    """Each frame carries exactly the values the source produced for its seq (float32 on the wire)."""
    keep = np.ones(208, bool)
    keep[list(skip)] = False
    for f in frames:
        want = np.float32(src.frames[f.seq])
        assert np.array_equal(f.values[keep], want[keep]), f"frame {f.seq} values differ"


def test_frames_arrive_in_order_with_the_values_sent(tmp_path):
    src, board, st, frames = run(tmp_path, duration=0.5)
    assert len(frames) > 50 and board.sent == len(frames) == st.frames == board.next_seq
    assert [f.seq for f in frames] == list(range(len(frames)))
    check_values(frames, src)
    assert np.all(np.diff([f.board_time_us for f in frames]) > 0)
    assert all(f.contact_ok.all() and not f.saturated.any() for f in frames)
    assert (st.corrupt, st.seq_gaps, st.dropped_overflow, st.reconnects, st.resyncs) == (0, 0, 0, 0, 0)
    assert 0 < st.period <= 1.2 / RATE, st.period
    # only an upper bound at 400 frames/s: the period is measured on the board's clock, and the
    # simulated board, a thread of this loaded host, measures late and catches up (frames 8 ms, then
    # 0.1 ms apart). The exact period is pinned at 1 frame/s (test_a_one_frame_per_second_board_is_not_reopened).


def trailing(frames, board) -> int:
    """Frames the board measured after the last one that arrived: the driver cannot see them lost (no
    later frame's seq shows the gap), so a fault that hit one of them is not counted."""
    return board.next_seq - 1 - frames[-1].seq


@pytest.mark.parametrize("fault", ["bit_flip", "drop", "truncate", "garbage"])
def test_injected_fault_is_counted_and_stream_resumes(tmp_path, fault):
    src, board, st, frames = run(tmp_path, FaultConfig(**{fault: 0.1}), duration=0.6)
    n_faults = board.injected.get(fault, 0)
    # an overrun (the pty had no room: a starved host) loses a frame too; it is counted, not hidden
    overrun = board.injected.get("overrun", 0)
    assert n_faults > 0 and overrun <= 0.05 * board.next_seq
    seqs = [f.seq for f in frames]
    assert seqs == sorted(seqs) and seqs[0] == 0
    check_values(frames, src)
    lost = board.next_seq - len(frames)
    missing_inside = seqs[-1] + 1 - len(frames)
    assert st.corrupt + st.seq_gaps == missing_inside  # every lost frame counted once
    assert st.duplicates == st.reordered == 0
    if fault == "garbage":  # a burst is line noise, no lost frame: one resync each, the frame after it survives
        assert lost == overrun and st.corrupt <= overrun
        assert n_faults - overrun <= st.resyncs <= n_faults + overrun
    elif fault == "drop":  # measured, not sent: a gap with nothing corrupt in between
        assert n_faults <= lost <= n_faults + overrun and st.corrupt <= overrun
        assert n_faults - overrun - trailing(frames, board) <= st.seq_gaps <= n_faults
    else:  # a harmed frame is one corrupt frame (not one per piece), and no gap besides
        assert n_faults <= lost <= n_faults + overrun
        # (the last frames harmed: a timing-dependent end, as a loaded host sends fewer frames in 0.6 s)
        assert n_faults - trailing(frames, board) <= st.corrupt <= n_faults + overrun, (st, board)
        assert st.seq_gaps <= overrun, (st, board)
    assert seqs[-1] >= board.next_seq - 5 and len(frames) > 0.7 * board.next_seq  # it went on after faults


def test_stall_reopens_and_resumes(tmp_path):
    faults = FaultConfig(stall_at=0.3, stall_for=0.5)
    src, board, st, frames = run(tmp_path, faults, duration=1.2, stall_timeout=0.2)
    assert board.injected["stall"] == 1 and st.reconnects >= 1
    times = np.array([f.board_time_us for f in frames]) / 1e6
    assert times.max() > 0.9 and np.diff(times).max() > 0.4  # frames on both sides of the stall
    assert [f.seq for f in frames] == list(range(len(frames))) and st.seq_gaps == 0
    check_values(frames, src)


@pytest.mark.slow  # seconds of a real clock
def test_a_board_back_from_a_stall_is_identified_once_not_once_per_reopen(tmp_path, caplog):
    """While a board is silent the driver reopens the pty every stall, each time sending IDENTIFY; the
    pty keeps them, and the board answers them all at once when it is back: one identity line (it was
    logged once per queued IDENTIFY). Nor are the stall and the reopen logged at every reopen (two
    lines every 2.5 s while a board stays frozen): the stall once per change of its text, the
    reopens at debug, and one line when bytes come again."""
    faults = FaultConfig(stall_at=0.3, stall_for=1.2)
    with caplog.at_level(logging.DEBUG, logger="cstomo_sensor.board.driver"):
        src, board, st, frames = run(tmp_path, faults, duration=2.0, stall_timeout=0.2, rate_hz=RATE)
    records = [r for r in caplog.records if r.name == "cstomo_sensor.board.driver"]
    info = [r.getMessage() for r in records if r.levelno == logging.INFO]
    identities = [m for m in info if "Identity(" in m]
    answered = [r for r in records if "Identity(" in r.getMessage()]
    assert st.reconnects >= 3 and len(answered) >= 3, info  # the queued IDENTIFYs were answered together
    assert len(identities) == 2, info  # the first connection's, and once when the board was back
    assert sum("connected" in m for m in info) == 1, info  # the first open; the reopens at debug
    warnings = [r.getMessage() for r in records if r.levelno == logging.WARNING]
    assert len(warnings) <= 2 and all("stalled" in m for m in warnings), warnings  # 0.2 s, then 2.5 s
    back = [m for m in info if "receiving again after" in m]  # (the end of the run is a stall too)
    assert len(back) == 1 and int(back[0].split("after ")[1].split()[0]) >= 3, info
    assert max(f.board_time_us for f in frames) / 1e6 > 1.6  # the stream resumed after the stall


def test_saturated_channel_and_dead_electrode_are_flagged(tmp_path):
    faults = FaultConfig(saturate_channel=17, full_scale=2.5, dead_electrode=5)
    src, board, st, frames = run(tmp_path, faults, duration=0.3)
    dead = MeasurementPattern(16, 2).electrode_rows(5)
    assert len(frames) > 20 and st.corrupt == 0
    for f in frames:
        assert np.flatnonzero(f.saturated).tolist() == [17] and f.values[17] == 2.5
        assert np.flatnonzero(~f.contact_ok).tolist() == [5]
        assert not np.any(f.values[dead] == np.float32(src.frames[f.seq])[dead])
    check_values(frames, src, skip=[17, *np.flatnonzero(dead)])


def test_text_mode_nan_lines_are_dropped_and_counted(tmp_path):
    src, board, st, frames = run(tmp_path, FaultConfig(nan=0.1), protocol="text", duration=0.8, rate=200.0)
    overrun = board.injected.get("overrun", 0)  # a starved host's partial line: corrupt as well
    assert board.injected["nan"] > 0 and overrun <= 0.05 * board.next_seq
    assert board.injected["nan"] <= st.corrupt <= board.injected["nan"] + overrun
    assert len(frames) + st.corrupt <= board.next_seq <= len(frames) + st.corrupt + overrun
    ks = [int(f.values[0]) for f in frames]
    assert ks == sorted(ks) and ks[-1] >= board.next_seq - 3
    for k, f in zip(ks, frames):
        assert f.seq is None and np.array_equal(f.values, src.frames[k])


def test_disconnect_reconnects_through_the_link_without_losing_frames(tmp_path):
    faults = FaultConfig(disconnect_at=0.3, reappear_after=0.3)
    src, board, st, frames = run(tmp_path, faults, duration=1.2, stall_timeout=0.5, reconnect_backoff=(0.02, 0.1))
    assert board.injected["disconnect"] == 1 and st.reconnects >= 1
    first_after = board.generation_first_seq[1]
    assert first_after > 0
    seqs = [f.seq for f in frames]
    assert [s for s in seqs if s >= first_after] == list(range(first_after, board.next_seq))
    assert st.seq_gaps == seqs[-1] + 1 - len(frames)
    check_values(frames, src)


def test_queue_overflow_drops_the_oldest_and_counts(tmp_path):
    src = CountingSource()
    with SimulatedBoard(src, rate_hz=RATE, duration=0.3, seed=1) as board, \
            BoardDriver(board.device, queue_size=8) as driver:
        assert wait_for(lambda: driver.stats().connected)
        board.start().join()
        assert wait_for(lambda: driver.stats().frames == board.stats().sent)
        frames = drain(driver, quiet=0.1)
        st, b = driver.stats(), board.stats()
    # every frame the board sent was received; all but the newest 8 were dropped and counted. A frame the
    # pty had no room for (the board's overrun: a loaded host's reader stalled; a run at load 6 lost 1 of
    # 120) never arrived: it is not the queue's
    n, overrun = b.next_seq, b.injected.get("overrun", 0)
    assert n > 50 and b.sent == n - overrun and st.dropped_overflow == b.sent - 8, (st, b)
    seqs = [f.seq for f in frames]
    if overrun:
        assert len(seqs) == 8 and seqs == sorted(seqs) and seqs[0] >= n - 8 - overrun and seqs[-1] < n, seqs
    else:
        assert seqs == list(range(n - 8, n)) and st.seq_gaps == 0


def test_close_is_idempotent(tmp_path):
    board = SimulatedBoard(CountingSource(), rate_hz=RATE, seed=1).start()
    driver = BoardDriver(board.device)
    assert driver.get(2.0) is not None
    driver.close()
    driver.close()
    n = driver.stats().frames
    drain(driver, quiet=0.01)  # frames received before close() stay readable
    assert not driver.stats().connected and driver.get(0.1) is None and driver.stats().frames == n
    board.close()
    board.close()


def test_loop_url(tmp_path):
    with BoardDriver("loop://", read_timeout=0.01) as driver:
        assert wait_for(lambda: driver.stats().connected)
        sent = [DataFrame(s, 10 * s, np.full(208, s / 4)) for s in (3, 4, 6)]
        assert driver.send(b"\x13\x37garbage" + b"".join(encode(f) for f in sent))
        got = [driver.get(2.0) for _ in sent]
        st = driver.stats()
    assert [g.seq for g in got] == [3, 4, 6] and [g.values[0] for g in got] == [0.75, 1.0, 1.5]
    assert (st.corrupt, st.resyncs, st.seq_gaps, st.frames) == (0, 1, 1, 3)  # garbage before a frame loses none


def _flipped(data: bytes) -> bytes:
    buf = bytearray(data)
    buf[len(buf) // 2] ^= 0x10  # inside the frame: its CRC fails
    return bytes(buf)


def test_duplicates_late_frames_and_corruption_are_counted_per_frame():
    """Sequence numbers 1 2 2 4 3 5, then 6, a bit-flipped 7, 8, a garbage burst, 9: the duplicate
    and the late 3 are dropped and counted (3 was not lost: no gap), the flipped frame is one
    corrupt frame, the burst one resync that loses nothing."""
    def frame(s):
        return encode(DataFrame(s, 1000 * s, np.full(208, float(s))))

    wire = b"".join(frame(s) for s in (1, 2, 2, 4, 3, 5, 6)) + _flipped(frame(7)) + frame(8) \
        + b"\x01\x02\x00\x07\x00\x00\xff\x13" + frame(9)
    with BoardDriver("loop://", read_timeout=0.01) as driver:
        assert wait_for(lambda: driver.stats().connected)
        assert driver.send(wire)
        assert wait_for(lambda: driver.stats().frames == 7)
        got = drain(driver, quiet=0.1)
        st = driver.stats()
    assert [g.seq for g in got] == [1, 2, 4, 5, 6, 8, 9]
    assert (st.duplicates, st.reordered, st.corrupt, st.seq_gaps, st.resyncs) == (1, 1, 1, 0, 1), st


@pytest.mark.slow
def test_a_one_frame_per_second_board_is_not_reopened(tmp_path):
    """The stall timeout follows the board's frame period: a 1 Hz board with a 0.3 s stall floor
    streams for 4.5 s on one connection, every frame in order (before: reopened every 0.3 s, START
    again, the same first frame over and over)."""
    src, board, st, frames = run(tmp_path, duration=4.5, rate=1.0, stall_timeout=0.3)
    assert st.reconnects == 0 and [f.seq for f in frames] == [0, 1, 2, 3, 4], (st, [f.seq for f in frames])
    assert st.period == pytest.approx(1.0, rel=0.05) and st.last_error == ""


@pytest.mark.slow  # seconds of a real clock
def test_replugged_board_is_read_again_within_a_quarter_second(tmp_path):
    """Unplugged for 2.5 s (the old doubling backoff reached 2 s by then): the driver retries the
    port every 0.25 s at most, so the first frame after the board is back comes within 0.3 s; the
    driver's last_error ("read failed"/"open failed") clears with it."""
    src = CountingSource()
    faults = FaultConfig(disconnect_at=0.3, reappear_after=2.5)
    board = SimulatedBoard(src, rate_hz=100.0, duration=3.5, link=tmp_path / "board", faults=faults, seed=1)
    with BoardDriver(board.device, stall_timeout=0.3) as driver:
        assert wait_for(lambda: driver.stats().connected)
        board.start()
        assert wait_for(lambda: not driver.stats().connected, 2.0)
        assert wait_for(lambda: "failed" in driver.stats().last_error, 1.0)
        drain(driver, quiet=0.0)
        f = driver.get(5.0)
        back_after = time.monotonic() - board.stats().generation_opened[1]
        st = driver.stats()
        board.close()
    assert f is not None and f.seq >= board.stats().generation_first_seq[1]
    assert back_after < 0.3, back_after
    assert st.last_error == "" and st.reconnects == 1


def test_missing_device_is_retried_not_raised(tmp_path, caplog):
    """A missing port: retried, and warned once in one sentence (not pyserial's '[Errno 2] could not
    open port X: [Errno 2] No such file or directory: X') that says what to check."""
    url = str(tmp_path / "nothing")
    with caplog.at_level(logging.WARNING, logger="cstomo_sensor.board.driver"):
        with BoardDriver(url, reconnect_backoff=(0.01, 0.02)) as driver:
            assert wait_for(lambda: "open failed" in driver.stats().last_error)
            assert driver.get(0.05) is None and not driver.stats().connected
            time.sleep(0.1)  # several more failed opens: logged once
    warnings = [r.getMessage() for r in caplog.records if "open failed" in r.getMessage()]
    assert len(warnings) == 1, warnings
    w = warnings[0]
    assert w.count(url) == 1 and "Errno" not in w, w
    for what in ("cable", "power", "'port' parameter", "config/99-cstomo.rules", "retrying (logged again when it changes)"):
        assert what in w, (what, w)


@pytest.mark.parametrize("kw", [{"protocol": "ascii"}, {"rate_hz": 0.0}, {"rate_hz": -5}])
def test_bad_arguments_raise_config_error(kw):
    with pytest.raises(ConfigError, match="protocol|rate_hz") as err:
        BoardDriver("loop://", **kw)
    if "protocol" in kw:
        assert "'ascii'" in str(err.value) and "binary" in str(err.value) and "text" in str(err.value)
    with pytest.raises(ConfigError):
        SimulatedBoard(CountingSource(), **{"rate_hz": 100.0, **kw})


def test_cli_prints_device_first_and_streams(tmp_path, monkeypatch, capsys):
    """``cstomo board-sim`` end to end; the real VoltageSource is another module's job, so a
    stand-in module provides ``VoltageSource.from_args`` here (a rubber that does not creep,
    ``--creep 0``: a creeping one is a Timeline, test_creep_defaults.py)."""
    from cstomo_sensor.tools import board_sim

    seen = {}

    class StandIn:
        @staticmethod
        def from_args(**kw):
            seen.update(kw)
            return CountingSource()

    monkeypatch.setattr(board_sim, "VoltageSource", StandIn)
    link = tmp_path / "board"
    script = tmp_path / "x.csv"  # read by board-sim itself before its loads are computed (the stand-in's job)
    script.write_text("time,fx,fy,fz\n0,0,0,0\n")
    before = {sig: signal.getsignal(sig) for sig in (signal.SIGINT, signal.SIGTERM)}
    with BoardDriver(str(link), reconnect_backoff=(0.01, 0.02)) as driver:
        argv = ["--sensor", "cuboid_joint", "--load-script", str(script), "--rate", "300", "--duration", "0.6",
                "--link", str(link), "--snr", "40", "--saturate-channel", "3", "--creep", "0"]
        assert board_sim.main(argv) == 0
        frames = drain(driver, quiet=0.2)
    # called in-process, it gives its caller's handlers back (the `cstomo` process keeps SIGINT ignored instead)
    assert {sig: signal.getsignal(sig) for sig in before} == before
    captured = capsys.readouterr()
    assert captured.out.splitlines()[0] == f"device: {link}"
    assert captured.err.splitlines()[-1].startswith("sent ") and "frames whole and unharmed" in captured.err
    assert seen == {"sensor": "cuboid_joint", "scene": None, "load_script": str(script), "snr_db": 40.0, "seed": 0}
    assert len(frames) > 10 and all(f.saturated[3] for f in frames)
    assert not link.exists()


@pytest.mark.slow
def test_a_board_restarted_at_a_slower_rate_is_followed(tmp_path):
    """A 400 Hz board is replaced on the same link by a 1 Hz one: after at most one stall (the old
    period no longer holds; it is measured again) the driver stays connected and reads every frame."""
    link = tmp_path / "board"
    fast = SimulatedBoard(CountingSource(), rate_hz=RATE, link=link, seed=1)
    with BoardDriver(str(link), stall_timeout=0.3) as driver:
        assert wait_for(lambda: driver.stats().connected)
        fast.start()
        assert wait_for(lambda: driver.stats().frames > 50)
        fast.close()
        slow = SimulatedBoard(CountingSource(), rate_hz=1.0, link=link, seed=2).start()
        try:
            time.sleep(4.5)  # 4 periods of the slow board: a driver still on the old period reopens every 0.3 s
            st = driver.stats()
        finally:
            slow.close()
        seqs = [f.seq for f in drain(driver, quiet=0.0)]
    slow_seqs = seqs[seqs.index(0, 1):]  # after the fast board's frames 0..n
    assert 1 <= st.reconnects <= 2 and st.period == pytest.approx(1.0, rel=0.05), st
    assert slow_seqs == list(range(len(slow_seqs))) and len(slow_seqs) >= 4, seqs


def test_the_boards_counts_are_said_in_words():
    """``cstomo board-sim``'s last lines (and ``cstomo demo``'s summary): every count with what it is."""
    from cstomo_sensor.board.sim import INJECTED_MEANING, SimStats

    st = SimStats(sent=98, next_seq=100, generation_first_seq=(0,), injected={"overrun": 1, "drop": 1})
    lines = st.describe()
    assert lines[0] == "sent 98 frames whole and unharmed"
    assert lines[1].startswith("1 drop: frames measured but not sent") and "injected" in lines[1]
    assert lines[2].startswith("1 overrun: ") and "nothing read it" in lines[2] and "not an injected fault" in lines[2]
    import re

    import cstomo_sensor.board.sim as sim

    counted = set(re.findall(r'_injected\["(\w+)"\]', open(sim.__file__, encoding="utf-8").read()))
    assert counted == set(INJECTED_MEANING), counted ^ set(INJECTED_MEANING)  # every count the board keeps


@pytest.mark.slow
# a SIGINT every 10 ms through the exit: before board-sim ignored SIGINT from its first stop to the process's exit
# (tools/board_sim.py _stopping, common.restore_signals), one landed once, beside a neighbour, between its
# handlers being restored and the `cstomo` process ignoring SIGINT (cli.main): a KeyboardInterrupt traceback
def test_board_sim_stopped_by_sigint_exits_cleanly_through_repeated_sigints(tmp_path):
    """``cstomo board-sim`` as ros2 launch stops it when not run from a terminal: the group's SIGINT,
    then launch's own SIGINT while the board is exiting (it takes ~0.1 s). A late SIGINT must not turn
    the clean exit into a death by SIGINT (launch: "process has died [exit code -2]") or a traceback."""
    import os
    import signal
    import subprocess
    import sys
    from pathlib import Path

    from conftest import prepare_board

    from cstomo_sensor.tools.launching import SIM_LOAD

    script = tmp_path / "load.csv"
    script.write_text(SIM_LOAD)  # a launch's own (its frames are cached by the launch tests)
    exe = Path(sys.executable).parent / "cstomo"
    cmd = [str(exe), "board-sim", "--load-script", str(script), "--rate", "200", "--protocol", "text",
           "--link", str(tmp_path / "board")]
    prepare_board(cmd)  # its frames in this process (read from the cache after the launch tests), not the board's
    err = tmp_path / "err.txt"
    with open(err, "w") as fe:
        p = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=fe, text=True,
                             env=dict(os.environ, OPENBLAS_NUM_THREADS="1"))
        try:
            for line in p.stdout:  # text protocol: streams without a reader
                if line.startswith("streaming"):
                    break
            time.sleep(0.3)
            p.send_signal(signal.SIGINT)
            while p.poll() is None:  # launch's SIGINT, at any moment of the exit
                time.sleep(0.01)
                p.send_signal(signal.SIGINT)
            code = p.wait(30)
        finally:
            if p.poll() is None:
                p.kill()
                p.wait()
    text = err.read_text()
    assert code == 0, (code, text)
    assert "Traceback" not in text and "frames whole and unharmed" in text, text



def test_the_nodes_queue_keeps_the_frames_reads_bring_together_at_1000_frames_per_second():
    """The node's queue (ros/node.py frame_queue: 40 ms of frames, at least 4): one read of a pty brings
    up to 4 KB, 4-5 frames of 880 bytes, whenever they arrive together (a late board, a USB link). At
    1000 frames/s a burst of 37 frames (the largest seen from the simulated board on a loaded host)
    all reach the frame thread, none dropped; the old queue of 4 frames dropped some of them although
    the frame thread was waiting for them."""
    import os
    import threading
    import tty

    from cstomo_sensor.ros.node import FRAME_QUEUE, frame_queue

    n = 37
    wire = b"".join(encode(DataFrame(s, 1000 * s, np.full(208, float(s)))) for s in range(1, n + 1))

    def read_burst(queue_size: int):
        master, slave = os.openpty()
        tty.setraw(slave)
        try:
            with BoardDriver(os.ttyname(slave), read_timeout=0.01, thread=False, queue_size=queue_size) as driver:
                assert driver.get(0.05) is None and driver.stats().connected  # the reading thread opens the port
                writer = threading.Thread(target=os.write, args=(master, wire))  # blocks while the pty is full
                writer.start()
                got = []
                while len(got) + driver.stats().dropped_overflow < n:
                    frame = driver.get(2.0)
                    assert frame is not None, (len(got), driver.stats())
                    got.append(frame.seq)
                writer.join()
                return got, driver.stats().dropped_overflow
        finally:
            os.close(master)
            os.close(slave)

    got, dropped = read_burst(frame_queue(1000.0))
    assert got == list(range(1, n + 1)) and dropped == 0, (got, dropped)
    got, dropped = read_burst(FRAME_QUEUE)  # 4 frames: the reads' extra frames are dropped
    assert dropped > 0 and len(got) == n - dropped and got[-1] == n, (got, dropped)
