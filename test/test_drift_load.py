"""A load is never taken for the device (issue 26, items 2 and 4; force/estimators/scale_fit.py JointScale): held
socket loads straight down, the direction closest to a uniform change, read what they are through a
fresh tare with the drift tracking on, and a controller's expected load (``expect_load``) helps the
tracker find the device's change under load.

Honest simulation: the nominal sensor's truth on its own finer mesh (not the model's), 60 dB; the
voltages between solved loads are interpolated linearly in the load (2 N/s: 0.02 N per frame)."""
from __future__ import annotations

import numpy as np
import pytest
from conftest import PIPE

from cstomo_sensor.model.simulate import Load, Truth, add_noise

pytestmark = pytest.mark.slow  # the honest device's frames (~27 s set-up on a fresh clone) and the model estimator

RATE = 100.0  # frames per second


@pytest.fixture(scope="module")
def model_pipe(warm_model):
    """The test's pipeline with the default estimator (``model``: the one with the joint fit)."""
    from cstomo_sensor.frame_path.config import PipelineConfig
    from cstomo_sensor.frame_path.pipeline import Pipeline

    return Pipeline.build(PipelineConfig(**{**PIPE, "grid": tuple(PIPE["grid"]), "estimator": "model"}))


@pytest.fixture(scope="module")
def down(warm_model):
    """(reference, {magnitude N: voltages}) for loads straight down of 0..10 N, noise-free."""
    truth = Truth(warm_model.geometry, seed=31)
    mags = np.arange(0.0, 10.5, 1.0)
    volts = {float(m): truth.forward.voltages(truth.conductivity(Load("socket", force=(0.0, 0.0, -m))))
             if m else truth.forward.voltages(truth.forward.sigma0) for m in mags}
    return volts[0.0], volts


def _voltages(volts, m):
    lo = min(int(m), 9)
    return volts[float(lo)] + (volts[float(lo + 1)] - volts[float(lo)]) * (m - lo)


def _run(pipe, down_, profile, seconds, tracking=True, expected=None):
    """The forces read (n, 3) for the magnitude ``profile(t)`` straight down, from a fresh tare."""
    from cstomo_sensor.frame_path.config import StreamConfig
    from cstomo_sensor.frame_path.stream import FrameStream

    ref, volts = down_
    rng = np.random.default_rng(11)
    stream = FrameStream(pipe, StreamConfig.offline(drift_tracking=tracking, creep_per_decade=0.0))
    tare = add_noise(np.repeat(ref[None], 20, 0), ref, 60, rng)
    stream.set_reference(tare.mean(axis=0), tare.std(axis=0, ddof=1), 20, "tare")
    t = np.arange(int(seconds * RATE)) / RATE
    out = np.full((len(t), 3), np.nan)
    for k, tk in enumerate(t):
        m = profile(tk)
        stamp = int(1e9 * (1 + tk))
        if expected is not None:
            stream.expect_load((0.0, 0.0, -m), expected, stamp)
        o = stream.push(add_noise(_voltages(volts, m), ref, 60, rng), stamp_ns=stamp)
        if o is not None and o.result.valid:
            out[k] = o.result.force
    return t, out, stream


def _held(pipe, down_, held, tracking):
    t, f, stream = _run(pipe, down_, lambda tk: held if tk >= 1.0 else 0.0, 11.0, tracking=tracking)
    return np.array([-np.nanmean(f[(t >= s) & (t < s + 1), 2]) for s in range(2, 11)]), stream


@pytest.mark.parametrize("held", [1.0, 2.0])
def test_a_small_load_held_straight_down_is_not_taken_for_the_device(model_pipe, down, held):
    """A held 1-2 N load straight down (the load most like a uniform change) with the tracking on reads
    what it reads without tracking, to what the design separates: measured 0.95-0.99 x (1 N) and
    0.97-1.0 x (2 N) over 2-11 s, where the tracking before issue 26 read 0.16 N for 1 N after 2 s (it took
    the load for the device) and before the quiet test (force/slow_states/drift.py QUIET_N) 0.78 x and 0.85 x after
    10 s: 97 % of a 1 N load's frames pass the frame's own rest tests, and the contacts' and the gradient's
    states took the load's part along their directions from them, the scale following; at 2 N the frames
    that passed were those whose noise hid the load, their scale measurements biased (-1.3e-4 against
    +5e-5 on the others) and weighed as rest frames. What remains: the joint fit's scale under the
    load (the model's misfit of the load along the uniform change, -3e-5 noise-free at 1 N)."""
    on, stream = _held(model_pipe, down, held, True)
    off, _ = _held(model_pipe, down, held, False)
    print(f"{held} N held, 1 s means from 2 s: tracking on {on.round(3)}, off {off.round(3)}; tracked change "
          f"{stream.slow.drift.change:+.5f}")
    assert np.all(on >= 0.9 * off) and np.all(on <= 1.1 * off)
    assert abs(stream.slow.drift.change) < 0.0001  # 1 N straight down looks like a 0.08 % uniform change


@pytest.mark.parametrize("held", [1.0, 2.0])
def test_a_small_load_held_straight_down_reads_within_10_pct(model_pipe, down, held):
    """Issue 26's aim with the tracking on: 1-2 N held straight down read within 10 % for 10 s (1 s means
    from 1 to 10 s after the load; measured 0.90-0.97 N and 1.90-1.95 N; before the quiet test 1 N read
    0.75 N after 10 s, 2 N 1.66 N)."""
    on, _ = _held(model_pipe, down, held, True)
    assert np.all(np.abs(on - held) < 0.1 * held), on


@pytest.mark.parametrize("held", [1.0, 2.0])
def test_a_small_load_held_straight_down_reads_within_10_pct_untracked(model_pipe, down, held):
    """The estimator itself: 1 and 2 N held straight down read within 10 % without the tracking (1 s
    means from 1 to 10 s after the load; measured 0.94-0.97 N and 1.93-1.95 N). Before the calibration's
    1 N loads 0.82-0.84 N and 1.78-1.80 N: its spline between the unloaded state and 5 N read 1 N as
    0.85 N on this device, noise-free, and 0.86 N on the model's own mesh."""
    off, _ = _held(model_pipe, down, held, False)
    assert np.all(np.abs(off - held) < 0.1 * held), off


@pytest.mark.slow
def test_a_ramp_to_10_n_then_held_30_s_reads_within_10_pct(model_pipe, down):
    profile = lambda tk: float(np.clip(2.0 * (tk - 1.0), 0.0, 10.0))  # noqa: E731 - 2 N/s from 1 s, 10 N at 6 s
    t, f, stream = _run(model_pipe, down, profile, 36.0)
    mags = np.array([profile(x) for x in t])
    ramp = (mags >= 2.0) & (mags < 10.0)
    rel = np.abs(-f[:, 2] - mags) / np.maximum(mags, 1e-9)
    held = t >= 6.5
    print(f"ramp: median rel err {np.nanmedian(rel[ramp]):.3f}, held: mean {-np.nanmean(f[held, 2]):.3f} N, "
          f"last 5 s {-np.nanmean(f[t >= 31, 2]):.3f} N, tracked {stream.slow.drift.change:+.5f}")
    assert np.nanmedian(rel[ramp]) < 0.10
    for s in range(7, 36):
        assert abs(-np.nanmean(f[(t >= s) & (t < s + 1), 2]) - 10.0) < 1.0, s
    assert abs(stream.slow.drift.change) < 0.002


def _restart_under_load(pipe, ref, loaded, expected, rng):
    """A stream started from a tare 2 hours old while the drive is 2 % up (every voltage x 1.02) and the
    joint carries ``loaded`` (its noise-free voltages) from the first frame; ``expected``: a controller's
    1-sigma (its expected load drawn around the truth per frame), None: none. The forces read over 3 s."""
    from cstomo_sensor.frame_path.config import StreamConfig
    from cstomo_sensor.frame_path.stream import FrameStream

    stream = FrameStream(pipe, StreamConfig.offline(creep_per_decade=0.0))
    tare = add_noise(np.repeat(ref[None], 20, 0), ref, 60, rng)
    stream.set_reference(tare.mean(axis=0), tare.std(axis=0, ddof=1), 20, "saved tare", age_s=7200.0)
    force, v = loaded
    out = np.full((300, 3), np.nan)
    for k in range(300):
        stamp = int(1e9 * (1 + k / RATE))
        if expected is not None:
            stream.expect_load(np.add(force, rng.normal(0.0, expected, 3)), expected, stamp)
        o = stream.push(add_noise(1.02 * v, 1.02 * ref, 60, rng), stamp_ns=stamp)
        if o is not None and o.result.valid:
            out[k] = o.result.force
    return out, stream


def test_a_restart_under_load_finds_the_change_and_an_expected_load_helps(model_pipe, down):
    ref, volts = down
    force = (0.0, 0.0, -2.0)
    err = {}
    for expected in (None, 0.5):
        out, stream = _restart_under_load(model_pipe, ref, (force, volts[2.0]), expected, np.random.default_rng(3))
        e = np.linalg.norm(out - force, axis=1)
        err[expected] = float(np.nanmedian(e[10:100]))
        print(f"expected {expected}: error 0.1-1 s {err[expected]:.3f} N, 1-3 s {np.nanmedian(e[100:]):.3f} N, "
              f"tracked {stream.slow.drift.change:+.5f}")
        assert stream.slow.drift.change == pytest.approx(0.02, abs=0.001)  # found under load from the first frame
        assert np.nanmedian(e[100:]) < 0.5  # measured 0.45 N, 0.16 N with the expected load; untracked 36 N (18 N per %)
    # measured at 0.1-1 s: 0.17 N with an expected load of 0.5 N per axis against 0.42 N without (the slopes as
    # states: the expected load measures the other states too); it must at least not hurt
    assert err[0.5] < 1.2 * err[None]


def test_an_expected_load_is_checked(model_pipe):
    from cstomo_sensor.errors import ConfigError
    from cstomo_sensor.frame_path.stream import FrameStream

    stream = FrameStream(model_pipe)
    with pytest.raises(ConfigError, match="sigma"):
        stream.expect_load((0.0, 0.0, -2.0), 0.0)
    with pytest.raises(ConfigError, match="3 force components"):
        stream.expect_load((0.0, -2.0), 1.0)


def test_the_node_takes_a_controllers_expected_wrench(ros, tmp_path, source, warm_model):
    """``~/expected_wrench`` (geometry_msgs/WrenchStamped) reaches the stream as an expected load with
    the node's ``expected_wrench_sigma`` and the message's stamp (docs/node.md); its checks: test_expected.py."""
    from conftest import start, wait_for
    from geometry_msgs.msg import WrenchStamped

    h, board = start(ros, tmp_path, source, expected_wrench_sigma=1.5)
    try:
        pub = h.probe.create_publisher(WrenchStamped, "/cstomo_sensor/expected_wrench", 10)
        assert wait_for(lambda: pub.get_subscription_count() == 1, 5.0)
        msg = WrenchStamped()
        msg.header.stamp.sec, msg.header.stamp.nanosec = 12, 500
        msg.header.frame_id = "cstomo_socket"
        msg.wrench.force.x, msg.wrench.force.y, msg.wrench.force.z = 1.0, -2.0, -9.5
        pub.publish(msg)  # before any frame: its stamp is checked against the first frames'
        assert wait_for(lambda: h.node.stream.slow.expected.pending is not None, 5.0)
        force, sigma, t, checked = h.node.stream.slow.expected.pending
        np.testing.assert_allclose(force, [1.0, -2.0, -9.5])
        assert sigma == 1.5 and t == pytest.approx(12.0000005) and not checked
    finally:
        board.close()
        h.close()
