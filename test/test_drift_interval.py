"""The drift tracker's states updated once per interval of frames (force/slow_states/drift.py UPDATE_S) with every
frame's measurements summed, against the same tracker updated on every frame (UPDATE_S 0, the formulation before).

For states that do not move between the frames of an interval, K sequential Kalman updates of a linear-Gaussian
measurement (a held load's bias shared by its frames) are one update with the summed information: the two trackers
then hold the same states. So the test freezes the device's motion in the model (the random walks and the rate's
variance 0: nothing moves between frames but what the frames measure) and feeds both the same device, frame by
frame, each frame formed with each tracker's own state, as the pipeline forms them: a restart 1 % off its tare with
the other states off too, a held load from the first frame (its frames measure the other states, wanted: each
updates at once, drift.py UPDATE_S), rest, a held load (the scale's joint measurements with the load's own bias,
summed; every 8th frame checks the other states), rest. A tracker that counted one
frame's measurement for the interval's frames (the earlier attempt, branch decimate) is off by that frame's noise
(the bounds and what that reads: the test's docstring)."""
from __future__ import annotations

import numpy as np

N = 208
RATE = 100.0  # frames per second: 4 frames an interval


def _device_run(update_s: float, monkeypatch, seconds: float = 20.0):
    """The tracker's (scale, other states, P, bias) after each phase, with UPDATE_S ``update_s``."""
    from cstomo_sensor.force.slow_states import drift as dr

    monkeypatch.setattr(dr, "UPDATE_S", update_s)
    monkeypatch.setattr(dr, "LOADED_EVERY_FRAME", False)  # the loaded frames summed too (the mechanism under test)
    rng = np.random.default_rng(12)
    r, G, W, load = rng.normal(size=N), rng.normal(size=(2, N)), 100 * rng.normal(size=(3, N)), rng.normal(size=N)
    tr = dr.DriftTracker(r, G, np.full(N, 1e-3), np.ones(N, bool), W)
    tr._q[:] = 0.0  # nothing moves between frames but what the frames measure (module docstring)
    tr.widen(3600.0)
    m = tr.m
    P = tr.P.copy()
    P[m, :] = P[:, m] = 0.0  # the rate known to be 0: it stays 0
    tr.P = P
    s_true, x_true = 1.01, np.array([0.004, -0.002])
    Ho = np.array([[4e6, 1e6], [1e6, 2e6]])  # the loaded frames' information of the other states
    L = np.linalg.cholesky(np.linalg.inv(Ho))
    V = rng.normal(size=(3, 2))
    noise = np.random.default_rng(3)  # the frames' noise: the same draws for both trackers
    out, phases = [], ((5.0, True), (10.0, False), (15.0, True), (seconds, False))
    wanted = 0
    k = 0
    for end, loaded in phases:
        while k / RATE < end:
            t = 1.0 + k / RATE
            y = (s_true / tr.scale - 1.0) * r + (x_true - tr.gradient) @ G + noise.normal(0.0, 1e-3, N)
            z = s_true / tr.scale - 1.0 + noise.normal(0.0, 1e-4) + (5e-5 if loaded else 0.0)  # the load's own bias
            e = L @ noise.normal(size=2)
            part = None
            if tr.others_wanted():
                wanted += k / RATE > 3.0 and loaded  # after the restart's first seconds (every frame there)
                part = (Ho, Ho @ (x_true - tr.gradient + e), V)
            joint = (z, 1e-8, np.zeros(3), np.full(3, 100.0), np.array([0.0, 0.0, -10.0] if loaded else [0.0] * 3), part)
            tr.observe(y + 0.05 * load * loaded, t, joint)
            k += 1
        tr.flush()
        out.append((tr.scale, tr.gradient.copy(), tr.P.copy(), tr.rest_frames, tr._bias.b))
    assert wanted > 100  # the loaded frames measured the other states
    return out


def test_the_interval_update_equals_the_frame_by_frame_update_for_static_states(monkeypatch):
    """Bounds in each state's own 1-sigma (its posterior). Loaded from the restart: the same to rounding, 1e-6 of
    it; the held load's bias after the rests to 1e-6 of its prior's (1e-7 here). At rest the
    other states' measurement takes the scale as known at its estimate (the information of the other states
    only, drift.py ``_N_others``): frame by frame each frame's estimate, per interval the interval's; the states
    then differ by 5e-3 of their 1-sigma at most (4e-4 here, the same for offsets 10 x smaller: not the
    linearisation). One frame's measurement of the scale counted for the interval's four instead of their sum
    reads 0.07 (loaded) to 0.8 (rest) of the scale's 1-sigma off, 0.1 of the other states', 0.1 of the held load's
    bias's."""
    from cstomo_sensor.force.slow_states.drift_parts import LOAD_BIAS_SIGMA

    every = _device_run(0.0, monkeypatch)
    interval = _device_run(0.04, monkeypatch)
    for phase, ((s0, g0, P0, n0, b0), (s1, g1, P1, n1, b1)) in enumerate(zip(every, interval)):
        sd = np.sqrt(np.diag(P0))
        bound = 1e-6 if phase == 0 else 5e-3  # loaded since the restart (no rest yet); then after rests
        assert n1 == n0  # the same frames taken as at rest
        assert abs(s1 - s0) < bound * sd[0], (phase, s0, s1, sd[0])
        assert np.all(np.abs(g1 - g0) < bound * sd[1:3]), (phase, g0, g1, sd[1:3])
        np.testing.assert_allclose(P1, P0, rtol=1e-9, atol=1e-9 * np.abs(P0).max())
        assert abs(b1 - b0) < 1e-6 * LOAD_BIAS_SIGMA, (phase, b0, b1)
    s, g, *_ = interval[-1]
    assert abs(s - 1.01) < 1e-4 and np.abs(g - [0.004, -0.002]).max() < 1e-4  # and both found the device


def test_an_interval_is_update_s_of_frame_time(monkeypatch):
    """The states move at every 4th frame at 100 frames/s, every 2nd at 50, every frame at 25 (the frames' stamps)."""
    from cstomo_sensor.force.slow_states import drift as dr

    rng = np.random.default_rng(1)
    r, G, W = rng.normal(size=N), rng.normal(size=(2, N)), 100 * rng.normal(size=(3, N))
    for rate, every in ((100.0, 4), (50.0, 2), (25.0, 1)):
        tr = dr.DriftTracker(r, G, np.full(N, 1e-3), np.ones(N, bool), W)
        updates = []
        for k in range(40):
            Pa = tr._Pa
            tr.others_wanted()
            tr.observe(np.zeros(N), 1.0 + k / rate, (1e-5, 1e-8, np.zeros(3), np.zeros(3), np.zeros(3)))
            updates.append(tr._Pa is not Pa)
        assert updates[1:] == [(k + 1) % every == 0 for k in range(1, 40)], (rate, updates)
