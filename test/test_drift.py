"""The zero that holds (force/slow_states/drift.py): a device whose resistivity changes uniformly after its tare
(it warmed or cooled; section "Device changes" of docs/physics.md), simulated honestly on the truth's
own mesh with its contacts unchanged (so the change is a scaling plus a contact change, not the
tracker's model), reads the same force as without the change.

Zero-load reading: the norm of the mean force over 2 s of unloaded frames after the change (what a
controller sees through the filter: the bias; the frames' own noise is not drift)."""
from __future__ import annotations

import numpy as np
import pytest
from conftest import PIPE

from cstomo_sensor.angles import angle_between, force_from_angles
from cstomo_sensor.model.simulate import Load, Truth, add_noise

ZERO_AIM = 0.2  # N, issue 20: up to +-10 % uniform resistivity change
RATE = 100.0    # frames per second


@pytest.fixture(scope="module")
def device(warm_model):
    """(reference, {change: unloaded frame}, loads (n, 3), {change: loaded frames (n, 208)}), noise-free."""
    truth = Truth(warm_model.geometry, seed=31)
    rng = np.random.default_rng(5)
    forces = np.array([force_from_angles(m, np.radians(e), np.radians(a)) for m, e, a in
                       zip(rng.uniform(5, 30, 6), rng.uniform(20, 85, 6), rng.uniform(-180, 180, 6))])
    sigma = [truth.conductivity(Load("socket", force=tuple(f))) for f in forces]
    s0 = truth.forward.sigma0
    changes = (-0.10, -0.01, 0.0, 0.01, 0.10)
    unloaded = {a: truth.forward.voltages(s0 / (1 + a)) for a in changes}
    loaded = {a: np.array([truth.forward.voltages(s / (1 + a)) for s in sigma]) for a in (-0.01, 0.0, 0.01)}
    return unloaded[0.0], unloaded, forces, loaded


def _stream(pipe, ref, tracking, rng):
    from cstomo_sensor.frame_path.config import StreamConfig
    from cstomo_sensor.frame_path.stream import FrameStream

    stream = FrameStream(pipe, StreamConfig.offline(drift_tracking=tracking))
    tare = add_noise(np.repeat(ref[None], 20, 0), ref, 60, rng)
    stream.set_reference(tare.mean(axis=0), tare.std(axis=0, ddof=1), 20, "tare")
    return stream


def _zero_reading(pipe, device, change, tracking, ramp_s=300.0, rate=20.0):
    """The bias at zero load over 10 s after the device changed by ``change`` over ``ramp_s`` (10 % in
    5 minutes: a joint warming by 2.5 K a minute at 0.8 %/K, faster than the fastest of a warm-up)."""
    ref, unloaded, *_ = device
    rng = np.random.default_rng(7)
    stream = _stream(pipe, ref, tracking, rng)
    forces = []
    for k in range(int((ramp_s + 10) * rate)):
        a = change * min(k / (ramp_s * rate), 1.0)  # linear in the change between the solved states
        v = ref + (unloaded[change] - ref) * (a / change if change else 0.0)
        out = stream.push(add_noise(v, ref, 60, rng), stamp_ns=int(1e9 * (1 + k / rate)))
        if k >= ramp_s * rate:
            forces.append(out.result.force if out is not None and out.result.valid else np.full(3, np.nan))
    return float(np.linalg.norm(np.mean(forces, axis=0))), stream


@pytest.mark.parametrize("change", [-0.01, 0.01])
@pytest.mark.slow
def test_a_one_percent_change_reads_no_force(warm_model, device, change):
    untracked, _ = _zero_reading(warm_model, device, change, tracking=False)
    tracked, stream = _zero_reading(warm_model, device, change, tracking=True)
    assert untracked > 10.0  # without tracking: 18 N per percent, as the issue found
    assert tracked <= ZERO_AIM, (change, tracked)
    assert stream.slow.drift.change == pytest.approx(change, abs=5e-4)
    assert stream.slow.drift.rest_frames > 0.9 * 7 * RATE  # unloaded frames are seen as rest


@pytest.mark.parametrize("change", [-0.10, 0.10])
@pytest.mark.slow
def test_a_ten_percent_change_reads_within_the_aim(warm_model, device, change):
    tracked, stream = _zero_reading(warm_model, device, change, tracking=True)
    assert stream.slow.drift.change == pytest.approx(change, abs=2e-3)
    assert tracked <= ZERO_AIM, (change, tracked)


@pytest.mark.slow
def test_a_ten_percent_change_is_tracked_and_warned(warm_model, device):
    """What holds at 10 %: the scale is followed, the zero stays within 0.6 N (1/300 of what it was),
    the diagnostics say the change in % and kelvin and advise a re-tare."""
    for change in (-0.10, 0.10):
        tracked, stream = _zero_reading(warm_model, device, change, tracking=True)
        assert stream.slow.drift.change == pytest.approx(change, abs=2e-3) and tracked <= 0.6, (change, tracked)
        level, msgs, kv = stream.health(1e9)
        assert kv["drift_change"] == f"{stream.slow.drift.change:+.3%}" and "K at" in kv["drift_kelvin"]
        assert any("re-tare" in m for m in msgs), msgs


@pytest.mark.slow
def test_loads_read_the_same_through_a_change(warm_model, device):
    """Loads held 0.3 s with rests between them, the device 1 % changed: the angle and magnitude errors
    with tracking are those without any change (within 1.25x / 1.5x, the issue's aims for a warm-up)."""
    ref, unloaded, forces, loaded = device

    def errors(change, tracking):
        rng = np.random.default_rng(11)
        stream = _stream(warm_model, ref, tracking, rng)
        ang, mag, k = [], [], 0
        for _ in range(3):
            for i, f in enumerate(forces):
                for frame in [unloaded[change]] * 50 + [loaded[change][i]] * 30:
                    out = stream.push(add_noise(frame, ref, 60, rng), stamp_ns=int(1e9 * (1 + k / RATE)))
                    k += 1
                    if frame is not unloaded[change] and out is not None and out.result.valid:
                        ang.append(np.degrees(angle_between(out.result.force, f)))
                        mag.append(abs(np.linalg.norm(out.result.force) / np.linalg.norm(f) - 1))
        return np.median(ang), np.median(mag)

    base_ang, base_mag = errors(0.0, tracking=False)
    for change in (-0.01, 0.01):
        ang, mag = errors(change, tracking=True)
        assert ang <= 1.25 * base_ang and mag <= 1.5 * base_mag, (change, ang, mag, base_ang, base_mag)
    ang0, mag0 = errors(0.0, tracking=True)  # tracking costs nothing when nothing drifts
    assert ang0 <= 1.1 * base_ang and mag0 <= 1.25 * base_mag, (ang0, mag0, base_ang, base_mag)


@pytest.mark.slow
def test_an_all_zero_frame_does_not_move_the_scale(warm_model, device):
    """A failing board's frame is implausible and never taken for a change of the device."""
    ref, *_ = device
    rng = np.random.default_rng(3)
    stream = _stream(warm_model, ref, True, rng)
    for k in range(20):
        stream.push(add_noise(ref, ref, 60, rng), stamp_ns=int(1e9 * (1 + k / RATE)))
    stream.push(np.zeros(208), stamp_ns=int(1e9 * 1.3))
    stream.push(ref * 10, stamp_ns=int(1e9 * 1.31))
    assert abs(stream.slow.drift.change) < 1e-4 and stream.counter.counts.implausible == 2


def test_the_node_parameter_and_the_command_line_turn_it_off(warm_model):
    from cstomo_sensor.frame_path.config import StreamConfig
    from cstomo_sensor.ros.params import PARAMETERS, NodeConfig
    from cstomo_sensor.tools.common import add_pipeline_args  # noqa: F401 - the flags' module imports

    assert PARAMETERS["drift_tracking"][0] is StreamConfig.drift_tracking is True
    cfg = NodeConfig.from_parameters(lambda n: {**{k: v[0] for k, v in PARAMETERS.items()}, "drift_tracking": False,
                                                "grid": PIPE["grid"]}[n])
    assert cfg.stream.drift_tracking is False


def test_a_drifting_device_over_time_is_followed(warm_model):
    """scenes/timeline_drift_short.yaml (honest truth over time: 3 K at +1 %/K with a 30 % gradient,
    contacts -1 %/K and each drifting up to 20 %, the drive +0.5 %; no load): the tracked scale follows
    the true uniform change (the rubber's mean resistivity and the drive) and the zero holds, where
    untracked it reads several newtons."""
    from pathlib import Path

    from cstomo_sensor.frame_path.config import StreamConfig
    from cstomo_sensor.frame_path.stream import FrameStream
    from cstomo_sensor.model.timeline import Timeline

    scene = Path(__file__).resolve().parents[1] / "scenes" / "timeline_drift_short.yaml"
    tl = Timeline.from_scene(scene).prepare()
    rng = np.random.default_rng(2)
    times, frames, _, state = tl.frames(RATE, rng=rng)
    tare = tl.tare(20, rng)
    zero = {}
    for tracking in (False, True):
        stream = FrameStream(warm_model, StreamConfig.offline(drift_tracking=tracking))
        stream.set_reference(tare.mean(axis=0), tare.std(axis=0, ddof=1), 20, "tare")
        scale, forces = [], []
        for t, v in zip(times, frames):
            out = stream.push(v, stamp_ns=int(1e9 * (1 + t)))
            forces.append(out.result.force if out is not None and out.result.valid else np.full(3, np.nan))
            scale.append(stream.slow.scale)
        late = times >= times[-1] - 2.0
        zero[tracking] = float(np.linalg.norm(np.nanmean(np.array(forces)[late], axis=0)))
    true = (1 + state.rho_change) * state.drive
    assert true[-1] - 1 > 0.03  # the device changed by more than 3 %
    assert np.max(np.abs(np.array(scale) - true)[times >= 1.0]) < 0.002, "the scale follows the true change"
    print(f"scale error max {np.max(np.abs(np.array(scale) - true)[times >= 1.0]):.2e}; zero {zero}")
    assert zero[False] > 5.0 and zero[True] < 0.5, zero


def _follow_run(follow: bool):
    """A tracker on random directions (a scale r and two other states G, 60 dB-like noise): 60 s at rest
    while the device warms (the scale +3e-4/s, the other states moving with it by fixed slopes), then 30 s
    of a load outside every direction, then 10 s at rest. Frames at 10/s, formed as the pipeline forms
    them, with the tracker's state; each frame's scale measured as the model estimator's joint fit
    measures it (JointScale: here the true ratio with a 1e-4 error). ``follow`` False: the slopes kept
    at 0 (what the tracker did before issue 26's fix)."""
    from cstomo_sensor.force.slow_states.coordinator import drift_status
    from cstomo_sensor.force.slow_states.drift import DriftTracker

    rng = np.random.default_rng(4)
    n = 208
    r, G, W, load = rng.normal(size=n), rng.normal(size=(2, n)), 100 * rng.normal(size=(3, n)), rng.normal(size=n)
    slope = np.array([0.3, -0.5])  # each state's change per unit of the scale's (section 9: a gradient, contacts)
    tr = DriftTracker(r, G, np.full(n, 1e-3), np.ones(n, bool), W)
    out = []
    for k in range(1000):
        t = k / 10.0
        s = 1.0 + 3e-4 * t
        y = (s / tr.scale - 1.0) * r + (slope * (s - 1.0) - tr.gradient) @ G + rng.normal(0.0, 1e-3, n)
        loaded = 60.0 <= t < 90.0
        if not follow:
            tr.follow[:] = 0.0
        joint = (s / tr.scale - 1.0 + rng.normal(0.0, 1e-4), 1e-8, np.zeros(3), np.zeros(3), np.zeros(3))
        rest = tr.observe(y + 0.05 * load * loaded, t, joint)
        out.append((t, rest, np.abs(tr.gradient - slope * (s - 1.0)).max(), tr.unmeasured_n, drift_status(tr)))
    return out


def test_under_load_the_states_a_rest_measures_follow_the_scale_and_their_sigma_says_so():
    """Issue 26: "the tracking never locks: when it loses the device, it says so and re-acquires". The
    other states follow the scale by their slope at rest (force/slow_states/drift.py FOLLOW_MEMORY); without it they
    stand still under load, the first rest after it no longer looks like rest, and none after it does."""
    for follow in (True, False):
        out = _follow_run(follow)
        t = np.array([o[0] for o in out])
        rest = np.array([o[1] for o in out])
        err = np.array([o[2] for o in out])
        unmeasured = np.array([o[3] for o in out])
        level, msg = out[899][4]  # the end of the load: the diagnostics say the states are unmeasured
        assert level == 1 and "unmeasured since the last rest frame (30.0 s ago" in msg, msg
        change = 0.5 * 3e-4 * 30.0  # the larger state's change during the load
        assert rest[(t >= 10) & (t < 60)].all() and not rest[(t >= 60) & (t < 90)].any()
        if follow:
            assert err[t < 90.0][-1] < 0.1 * change  # followed the scale under load
            assert rest[t >= 90.0].mean() > 0.95  # the rest after it is rest
            # the error bar of the unmeasured states grew during the load and shrank at the rest
            assert unmeasured[t < 90.0][-1] > 5 * unmeasured[t < 60.0][-1]
            assert unmeasured[-1] < 0.5 * unmeasured[t < 90.0][-1]
            assert out[-1][4] == (0, "")
        else:
            assert err[t < 90.0][-1] > 0.8 * change  # stood still
            assert not rest[t >= 90.0].any()  # locked: the rest is not taken for rest
