"""The in-process virtual board (board/links.py, board/protocol_virtual.py): the simulated board on a
socket pair registered as ``virtual://NAME``, read by the real BoardDriver through pyserial's URL
handlers; and the same recording decoded alike over the virtual link and over a real pty."""
import numpy as np
import pytest
from conftest import board_link
from test_board_pty import CountingSource, check_values, drain, run, trailing, wait_for

from cstomo_sensor.board.driver import BoardDriver
from cstomo_sensor.board.sim import FaultConfig, SimulatedBoard


def test_frames_arrive_in_order_with_the_values_sent(tmp_path):
    src, board, st, frames = run(tmp_path, duration=0.5, virtual=True)
    assert len(frames) > 50 and board.sent == len(frames) == st.frames == board.next_seq
    assert [f.seq for f in frames] == list(range(len(frames)))
    check_values(frames, src)
    assert (st.corrupt, st.seq_gaps, st.dropped_overflow, st.reconnects, st.resyncs) == (0, 0, 0, 0, 0)
    assert 0 < st.period <= 1.2 / 400.0, st.period  # an upper bound only: see test_board_pty's twin


@pytest.mark.parametrize("fault", ["bit_flip", "drop"])
def test_an_injected_fault_is_counted_once_per_frame(tmp_path, fault):
    src, board, st, frames = run(tmp_path, FaultConfig(**{fault: 0.1}), duration=0.5, virtual=True)
    n, overrun = board.injected[fault], board.injected.get("overrun", 0)
    seqs = [f.seq for f in frames]
    assert n > 0 and seqs == sorted(seqs) and board.next_seq - len(frames) in range(n, n + overrun + 1)
    assert st.corrupt + st.seq_gaps == seqs[-1] + 1 - len(frames)
    # every fault counted once, but for those among the frames after the last that arrived (no later
    # seq shows them; a loaded host sends fewer frames in 0.5 s, so which frame is last varies: a run at
    # load 5 ended on a flipped one, 25 corrupt of 26 flipped)
    assert (st.corrupt if fault == "bit_flip" else st.seq_gaps) >= n - overrun - trailing(frames, board)
    check_values(frames, src)


def test_text_mode_streams_over_the_virtual_link(tmp_path):
    src, board, st, frames = run(tmp_path, protocol="text", duration=0.4, rate=200.0, virtual=True)
    ks = [int(f.values[0]) for f in frames]
    assert len(frames) > 40 and ks == list(range(len(ks))) and st.corrupt == 0
    assert all(np.array_equal(f.values, src.frames[k]) for k, f in zip(ks, frames))


def test_stall_reopens_and_resumes(tmp_path):
    src, board, st, frames = run(tmp_path, FaultConfig(stall_at=0.3, stall_for=0.5), duration=1.2, stall_timeout=0.2,
                                 virtual=True)
    assert board.injected["stall"] == 1 and st.reconnects >= 1
    assert [f.seq for f in frames] == list(range(len(frames))) and st.seq_gaps == 0
    times = np.array([f.board_time_us for f in frames]) / 1e6
    assert times.max() > 0.9 and np.diff(times).max() > 0.4


def test_a_disconnect_fails_the_open_like_an_absent_device_until_the_board_is_back(tmp_path):
    """The fault closes the socket pair: the driver's read fails (end of file), its opens fail as for
    a missing device ("open failed ... no virtual board") and it reads the new pair once it appears,
    every frame measured on it in order."""
    src = CountingSource()
    board = SimulatedBoard(src, rate_hz=200.0, duration=1.5, link=board_link(tmp_path),
                           faults=FaultConfig(disconnect_at=0.3, reappear_after=0.5), seed=1)
    with BoardDriver(board.device, queue_size=4096, stall_timeout=0.5, reconnect_backoff=(0.02, 0.05)) as driver:
        assert wait_for(lambda: driver.stats().connected)
        board.start()
        assert wait_for(lambda: not driver.stats().connected, 2.0)
        assert wait_for(lambda: "open failed" in driver.stats().last_error, 1.0)
        assert "no virtual board" in driver.stats().last_error and board.device in driver.stats().last_error
        board.join(5.0)
        frames = drain(driver, quiet=0.3)
        st = driver.stats()
    board.close()
    first_after = board.stats().generation_first_seq[1]
    seqs = [f.seq for f in frames]
    assert board.stats().injected["disconnect"] == 1 and st.reconnects == 1 and first_after > 0
    assert [s for s in seqs if s >= first_after] == list(range(first_after, board.stats().next_seq))
    check_values(frames, src)


def test_a_name_is_one_boards_until_it_closes(tmp_path):
    link = board_link(tmp_path)
    with SimulatedBoard(CountingSource(), link=link):
        with pytest.raises(FileExistsError, match="already holds"):
            SimulatedBoard(CountingSource(), link=link)
    with SimulatedBoard(CountingSource(), rate_hz=100.0, link=link, seed=1) as board, BoardDriver(link) as driver:
        board.start()
        assert driver.get(2.0).seq == 0  # the name is free again once its board closed


def test_an_unknown_name_is_retried_not_raised():
    with BoardDriver("virtual://nobody-here", reconnect_backoff=(0.01, 0.02)) as driver:
        assert wait_for(lambda: "open failed" in driver.stats().last_error)
        assert driver.get(0.05) is None and not driver.stats().connected


class Recording:
    """A recording of 120 frames (seeded), played in order: the k-th frame measured is frame k plus
    the board's own noise (its seeded generator, also in order)."""

    frames = np.random.default_rng(11).normal(0.5, 0.2, (120, 208))

    def __init__(self):
        self.k = 0

    def frame(self, t, rng):
        v = self.frames[self.k % len(self.frames)] + rng.normal(0.0, 1e-4, 208)
        self.k += 1
        return v

    def truth(self, t):
        return np.zeros(3)


def test_one_recording_decodes_alike_over_the_virtual_link_and_a_pty(tmp_path):
    """The same board (recording, seed, faults: dropped frames, a saturated channel, a dead
    electrode) through the real BoardDriver, once over a virtual link and once over a pty: the
    frames decoded carry the same seq, values and flags (the board times are each run's own)."""
    faults = FaultConfig(drop=0.05, saturate_channel=17, dead_electrode=5)
    got = {}
    for virtual in (True, False):
        (tmp_path / f"{virtual}").mkdir()
        _, board, st, frames = run(tmp_path / f"{virtual}", faults, duration=0.5, rate=200.0, src=Recording(),
                                   virtual=virtual)
        assert frames and board.injected["drop"] > 0, board
        got[virtual] = (board, st, {f.seq: f for f in frames})
    (vb, vst, v), (pb, pst, p) = got[True], got[False]
    both = sorted(v.keys() & p.keys())
    assert len(both) > 80 and both[0] == 0
    # a frame one run has and the other lacks: measured after the other's end, or lost to its overrun
    for mine, theirs, their_board in ((v, p, pb), (p, v, vb)):
        extra = [s for s in mine.keys() - theirs.keys() if s < max(theirs)]
        assert len(extra) <= their_board.injected.get("overrun", 0), (extra, their_board)
    for s in both:
        a, b = v[s], p[s]
        assert np.array_equal(a.values, b.values) and np.array_equal(a.saturated, b.saturated)
        assert np.array_equal(a.contact_ok, b.contact_ok)
    assert np.flatnonzero(~v[0].contact_ok).tolist() == [5] and np.flatnonzero(v[0].saturated).tolist() == [17]
    assert vst.seq_gaps > 0 and vst.corrupt == pst.corrupt == 0


def test_the_board_sim_command_refuses_a_virtual_link(capsys):
    """``cstomo board-sim`` runs in its own process: a virtual link there no host could open."""
    from cstomo_sensor.tools import board_sim

    with pytest.raises(SystemExit) as err:
        board_sim.main(["--sensor", "cuboid_joint", "--load-script", "x.csv", "--rate", "10", "--link", "virtual://b"])
    assert err.value.code == 2 and "a virtual link lives in one process" in capsys.readouterr().err
