"""A held load through the board's reference firmware (host build) reads within the same error as
through `cstomo board-sim`'s simulated board, for the same frames: the committed bag's honest frames
(test/data/make_bag.py: 20 unloaded, then a held 20 N load, 60 dB) in a frames file, played by the
firmware's front-end and by a SimulatedBoard, each read by the real BoardDriver over a pty and
estimated by a FrameStream tared on the unloaded frames."""
from __future__ import annotations

import time

import numpy as np
import pytest
from conftest import board_link
from firmware_harness import Process, build_host, write_frames

from cstomo_sensor.board.driver import BoardDriver
from cstomo_sensor.board.sim import SimulatedBoard
from cstomo_sensor.frame_path.config import StreamConfig
from cstomo_sensor.frame_path.stream import FrameStream

RATE = 100.0
TRUE_FORCE = np.array([0.0, 0.0, -20.0])  # the bag's held load (raw_voltages_truth.csv)


class Rows:
    """board-sim's voltage source playing the rows in turn, one per measured frame (its seq)."""

    def __init__(self, rows):
        self.rows, self.k = rows, 0

    def frame(self, t, rng):
        self.k += 1
        return self.rows[(self.k - 1) % len(self.rows)]

    def truth(self, t):
        return TRUE_FORCE


def one_pass(device: str, n: int) -> list:
    """The frames of seq n .. 2n - 1 (row k of the file is the frame of seq k mod n), read by the driver."""
    driver = BoardDriver(device, rate_hz=RATE, queue_size=1 << 14)
    got, deadline = {}, time.monotonic() + 30
    try:
        while len(got) < n and time.monotonic() < deadline:
            f = driver.get(0.1)
            if f is not None and n <= f.seq < 2 * n:
                got[f.seq] = f
        st = driver.stats()
    finally:
        driver.close()
    assert len(got) == n and (st.seq_gaps, st.corrupt) == (0, 0), st
    return [got[s] for s in range(n, 2 * n)]


def forces(pipe, frames, n_tare: int) -> np.ndarray:
    stream = FrameStream(pipe, StreamConfig.offline(wrench_filter_hz=0.0))
    tare = np.array([f.values for f in frames[:n_tare]])
    stream.set_reference(tare.mean(axis=0), tare.std(axis=0, ddof=1), n_tare, "tare")
    return np.array([stream.push(f.values, f.saturated, f.contact_ok).result.force for f in frames[n_tare:]])


@pytest.mark.slow
def test_a_held_load_reads_within_board_sims_error(tmp_path, source, warm_model):
    path = write_frames(tmp_path / "held.csv", np.vstack([source.frames[:20], source.frames[22:68]]))
    rows = np.loadtxt(path, delimiter=",")
    n = len(rows)
    with Process([str(build_host(tmp_path)), "--frames", str(path), "--rate", str(RATE)]) as board:
        fw = one_pass(board.device, n)
    with SimulatedBoard(Rows(rows), rate_hz=RATE, link=board_link(tmp_path, pty=True), seed=1) as sim:
        sim.start()
        ref = one_pass(sim.device, n)
    for a, b in zip(fw, ref):  # the same frames on both wires (float32)
        np.testing.assert_array_equal(a.values, b.values)
    F_fw, F_sim = forces(warm_model, fw, 20), forces(warm_model, ref, 20)
    err_fw = np.linalg.norm(F_fw - TRUE_FORCE, axis=1)
    err_sim = np.linalg.norm(F_sim - TRUE_FORCE, axis=1)
    print(f"held 20 N: firmware mean error {err_fw.mean():.3f} N (rms {np.sqrt((err_fw ** 2).mean()):.3f}), "
          f"board-sim {err_sim.mean():.3f} N")
    assert err_fw.mean() == pytest.approx(err_sim.mean(), rel=0.01, abs=0.01)
    assert np.sqrt((err_fw ** 2).mean()) == pytest.approx(np.sqrt((err_sim ** 2).mean()), rel=0.01, abs=0.01)
    assert err_fw.mean() < 0.25 * 20.0  # and the load is read: the force, not noise


@pytest.mark.slow
def test_the_node_reads_the_firmware(ros, tmp_path, source, warm_model):
    """The node (its parameters pointing its port at the host firmware's pty) tares on the first 10
    frames (unloaded rows) and publishes the held load's 20 N for the loaded rows, with no frame lost."""
    from conftest import PIPE, Harness, wait_for
    from geometry_msgs.msg import WrenchStamped

    path = write_frames(tmp_path / "held.csv", np.vstack([source.frames[:20], source.frames[22:68]]))
    with Process([str(build_host(tmp_path)), "--frames", str(path), "--rate", str(RATE)]) as board:
        p = dict(PIPE, port=board.device, tare_file=str(tmp_path / "tare.csv"), tare_on_start=True, tare_frames=10,
                 creep_per_decade=0.0, rate_hz=RATE)
        h = Harness(ros, p, name="cstomo_fw")
        try:
            assert wait_for(lambda: h.state() == "active", 30.0), h.state()
            wrenches = h.record("/cstomo_fw/wrench", WrenchStamped)
            assert wait_for(lambda: len(wrenches) >= 300, 20.0), len(wrenches)
            st = h.node.driver.stats()
            identity = h.node.driver.identity
        finally:
            h.close()
    assert identity.firmware == "cstomo-fw 1.0 (host)"
    assert (st.seq_gaps, st.corrupt) == (0, 0), st
    f = np.array([(m.wrench.force.x, m.wrench.force.y, m.wrench.force.z) for _, m in wrenches])
    loaded = np.linalg.norm(f - TRUE_FORCE, axis=1) < 3.0
    unloaded = np.linalg.norm(f, axis=1) < 3.0
    assert (loaded | unloaded).mean() > 0.95
    assert loaded.mean() == pytest.approx(46 / 66, abs=0.08)  # the rows' share of the held load
