"""``~/wrench_filtered``: the first-order low-pass (frame_path/filter.py) against the continuous filter it
states (step response, -3 dB at the cutoff, noise), its restarts, and the real node on a simulated board
(reset on tare and after a reconnect, noise reduction and step delay on a held load)."""
from __future__ import annotations

import math
import time

import numpy as np
import pytest

from cstomo_sensor.errors import ConfigError
from cstomo_sensor.frame_path.filter import LowPass


def _run(f: LowPass, xs, ts):
    return np.array([f(x, t) for x, t in zip(xs, ts)])


@pytest.mark.parametrize("jitter", [0.0, 0.3])
def test_step_response_is_the_continuous_first_order_one(jitter):
    """A unit step: y(t) = 1 - exp(-t / tau), tau = 1 / (2 pi fc), at every stamp, jittered or not
    (stated tolerance: 1e-9, the filter being exact for an input held between frames)."""
    fc, fs = 5.0, 1000.0
    rng = np.random.default_rng(0)
    ts = np.cumsum(np.full(400, 1 / fs) * (1 + jitter * rng.uniform(-1, 1, 400)))
    f = LowPass(fc)
    f((0.0, 0.0, 0.0), ts[0])
    y = _run(f, np.tile([1.0, -2.0, 0.5], (399, 1)), ts[1:])
    want = 1 - np.exp(-(ts[1:] - ts[0]) * 2 * math.pi * fc)
    np.testing.assert_allclose(y, want[:, None] * [1.0, -2.0, 0.5], atol=1e-9)
    tau = 1 / (2 * math.pi * fc)
    t63 = ts[1:][np.argmax(y[:, 0] >= 1 - math.exp(-1))] - ts[0]
    assert t63 == pytest.approx(tau, abs=1.5 / fs)


def test_gain_at_the_cutoff_is_minus_3_db_and_noise_falls_as_stated():
    fc, fs = 20.0, 1000.0
    ts = np.arange(20000) / fs
    f = LowPass(fc)
    y = _run(f, np.column_stack([np.sin(2 * math.pi * fc * ts)] * 3), ts)
    amp = np.abs(y[5000:, 0]).max()
    assert amp == pytest.approx(1 / math.sqrt(2), rel=0.01)
    rng = np.random.default_rng(1)
    noise = rng.normal(size=(20000, 3))
    out = _run(LowPass(fc), noise, ts)
    ratio = out[200:].std() / noise.std()
    assert ratio == pytest.approx(math.sqrt(math.pi * fc / fs), rel=0.05)  # white noise, bandwidth pi fc / 2


def test_restarts_on_reset_gap_and_stamps_going_back_and_off_is_identity():
    f = LowPass(2.0, max_gap=0.1)
    f((0, 0, 0), 0.0)
    assert f((1, 1, 1), 0.01)[0] < 0.2
    f.reset()
    assert f((5, 6, 7), 0.02) == (5.0, 6.0, 7.0)
    assert f((0, 0, 0), 0.03)[0] > 4.0
    assert f((9, 9, 9), 0.2) == (9.0, 9.0, 9.0)  # gap of 0.17 s > max_gap
    assert f((1, 2, 3), 0.1) == (1.0, 2.0, 3.0)  # stamps went back (a board clock restarted)
    off = LowPass(0.0)
    for t, x in enumerate(np.random.default_rng(2).normal(size=(5, 3))):
        assert off(x, t * 1e-3) == tuple(x)


@pytest.mark.parametrize("bad", [-1.0, float("nan"), float("inf")])
def test_a_bad_cutoff_is_named(bad):
    with pytest.raises(ConfigError, match="wrench_filter_hz"):
        LowPass(bad)


# --- the real node, a simulated board (virtual link) ------------------------------------------------

class HeldLoad:
    """The committed bag's unloaded frames for ``unloaded_for`` s, then its frames of the held 20 N
    load (0.44..1.36 s of the bag: honest simulation, 60 dB), looping."""

    def __init__(self, bag, unloaded_for: float = 1.0):
        from conftest import BAG_RATE

        self.rate, self.unloaded_for = BAG_RATE, unloaded_for
        self.unloaded, self.loaded = bag.frames[:20], bag.frames[22:68]

    def frame(self, t, rng):
        frames = self.unloaded if t < self.unloaded_for else self.loaded
        return frames[int(round(t * self.rate)) % len(frames)]

    def truth(self, t):
        return np.zeros(3) if t < self.unloaded_for else np.array([0.0, 0.0, -20.0])


@pytest.mark.slow
@pytest.mark.alone  # the filter runs on the frames' arrival stamps: beside a busy neighbour they come in bursts and
# the smoothing judged below reads less (a fresh-clone CI: filtered x sd 0.13 N against 0.077 alone, bound 0.10)
def test_node_filtered_wrench_resets_on_tare_and_reconnect_and_smooths_a_held_load(ros, tmp_path, source,
                                                                                     warm_model):
    """Board at 100 frames/s: unloaded (tare at start), a step to a held 20 N, an unplug of 0.3 s,
    then ~/tare_forced under the load. The filtered wrench (2 Hz) equals the raw one exactly on the first
    frame, the first after the reconnect and the first after the tare, and nowhere else; on the held
    load its spread is under half the raw one's, its mean the same; the step reaches 63 % at tau."""
    from conftest import start, wait_for
    from geometry_msgs.msg import WrenchStamped

    from cstomo_sensor.board.sim import FaultConfig

    fc = 2.0
    faults = FaultConfig(disconnect_at=3.0, reappear_after=0.3)
    h, board = start(ros, tmp_path, HeldLoad(source), faults=faults, rate=100.0, name="cstomo_filter",
                     tare_on_start=True, tare_frames=10, wrench_filter_hz=fc, stale_timeout=2.0,
                     creep_per_decade=0.0)  # the simulated rubber does not creep: its held load is held
    try:
        raw = h.record("/cstomo_filter/wrench", WrenchStamped)
        filt = h.record("/cstomo_filter/wrench_filtered", WrenchStamped)
        board.start()
        assert wait_for(lambda: h.node.driver is not None and h.node.driver.stats().reconnects >= 1, 10.0)
        n = len(raw)
        assert wait_for(lambda: len(raw) > n + 100, 10.0)
        r = h.call_tare(service="tare_forced")  # under the held load: ~/tare refuses it (issue 20)
        assert r.success and "forced tare, overrode: it carries a load" in r.message, r.message
        n = len(raw)
        assert wait_for(lambda: len(raw) > n + 50 and len(filt) >= len(raw) - 2, 10.0)
        back = board.stats().generation_opened[1]  # time.monotonic() at which the replugged board was back
    finally:
        board.close()
        h.close()
    ros_to_mono = time.monotonic() - time.time()  # the node's ROS clock is the system clock

    def table(rec):
        return {m.header.stamp.sec * 10**9 + m.header.stamp.nanosec:
                (m.wrench.force.x, m.wrench.force.y, m.wrench.force.z) for _, m in rec}

    R, F = table(raw), table(filt)
    stamps = np.array(sorted(set(R) & set(F)))
    assert len(stamps) >= len(R) - 2
    fr = np.array([R[s] for s in stamps])
    ff = np.array([F[s] for s in stamps])
    t = (stamps - stamps[0]) * 1e-9
    # a restarted filter outputs its input; the source repeats each bag frame for two frames (100 on
    # 50 frames/s), so a frame equal to the previous one is not a restart
    new = np.r_[True, np.any(fr[1:] != fr[:-1], axis=1)]
    same = np.flatnonzero(np.all(fr == ff, axis=1) & new)
    gaps = np.diff(t)
    # the reconnect and the tare found by what the board and the node did, not as the longest silences
    # (a loaded host's stall of the in-process board is a silence too: a run at load 5 saw one longer
    # than the unplug's): the first wrench of a frame measured after the board was back (its stamp, on
    # the monotonic clock), and the first after it without the held load (the forced tare zeroed it)
    reconnect = int(np.argmax(stamps * 1e-9 + ros_to_mono > back))
    assert reconnect > 0 and 0.25 < gaps[reconnect - 1] < 2.0  # the 0.3 s unplugged
    tare = reconnect + int(np.argmax(np.linalg.norm(fr[reconnect:], axis=1) < 10.0))
    assert t[tare] > t[reconnect] and 0.09 < gaps[tare - 1] < 1.0  # the tare's 10 frames gave no output
    # the filter restarts there and after any silence longer than stale_timeout (2 s: a stalled host's)
    stalls = [i for i in np.flatnonzero(gaps > 2.0) + 1 if new[i]]  # (a repeated frame shows no restart)
    assert same.tolist() == sorted({0, reconnect, tare, *stalls}), (same, reconnect, tare, stalls)

    # the step to 20 N (first raw frame above 10 N), then the held load before the unplug
    step = int(np.argmax(np.linalg.norm(fr, axis=1) > 10))
    tau = 1 / (2 * math.pi * fc)
    plateau = fr[step:reconnect, 2].mean()
    t63 = t[step + int(np.argmax(ff[step:, 2] <= 0.632 * plateau))] - t[step - 1]
    assert t63 == pytest.approx(tau, abs=0.02)  # two frames
    held = (t > t[step] + 5 * tau) & (np.arange(len(t)) < reconnect)
    assert held.sum() > 50
    sd_raw, sd_f = fr[held].std(axis=0), ff[held].std(axis=0)
    print(f"held load: raw sd {sd_raw} N, filtered sd {sd_f} N; step 63 % after {t63 * 1e3:.0f} ms (tau "
          f"{tau * 1e3:.0f} ms)")
    assert np.all(sd_f < 0.5 * sd_raw)
    np.testing.assert_allclose(ff[held].mean(axis=0), fr[held].mean(axis=0), atol=0.2)
