"""The fast pieces of the per-frame path against their plain versions: the scalar force angles
against the numpy ones, the thin-plate spline (value and analytic Jacobian) against scipy's
RBFInterpolator and its finite differences, and the ``model`` estimator's Gauss-Newton fit against
a plain least-squares fit through scipy's interpolant."""
from __future__ import annotations

import numpy as np
import pytest
from scipy.interpolate import RBFInterpolator
from scipy.optimize import least_squares

from cstomo_sensor.angles import force_angles, force_angles3
from cstomo_sensor.force.estimators.tps import ThinPlateSpline


def test_scalar_angles_equal_the_numpy_ones():
    rng = np.random.default_rng(0)
    fs = np.vstack([rng.normal(size=(200, 3)) * 20, [[0, 0, -5], [0, 0, 5], [0, 0, 0], [1e-12, 0, -3], [3, -4, 0]]])
    for f in fs:
        np.testing.assert_allclose(force_angles3(f), [float(v) for v in force_angles(f)], rtol=1e-12, atol=1e-12)
    assert force_angles3([0.0, 0.0, -5.0]) == (5.0, np.pi / 2, 0.0)
    assert all(np.isnan(force_angles3([np.nan, 0.0, 1.0])[:2]))


@pytest.fixture(scope="module")
def nodes():
    rng = np.random.default_rng(1)
    p = rng.uniform(-2, 2, size=(80, 3))
    v = np.column_stack([np.sin(p @ rng.normal(size=3)) for _ in range(6)]) + p[:, :1] ** 2
    return p, v


def test_thin_plate_spline_equals_scipy_and_its_jacobian_the_finite_differences(nodes):
    p, v = nodes
    ours = ThinPlateSpline(p, v)
    ref = RBFInterpolator(p, v, kernel="thin_plate_spline", degree=1)
    x = np.random.default_rng(2).uniform(-2.5, 2.5, size=(30, 3))
    np.testing.assert_allclose(ours(x), ref(x), atol=1e-9)
    np.testing.assert_allclose(ours(p), v, atol=1e-9)  # interpolates
    for xi in list(x[:10]) + [p[5]]:  # and at a node, where phi is only C^1
        val, jac = ours.value_and_jacobian(xi)
        np.testing.assert_allclose(val, ref(xi[None])[0], atol=1e-9)
        h = 1e-6
        fd = np.column_stack([(ref((xi + h * e)[None])[0] - ref((xi - h * e)[None])[0]) / (2 * h) for e in np.eye(3)])
        np.testing.assert_allclose(jac, fd, atol=1e-5)


def test_model_estimator_finds_the_least_squares_force_of_the_surrogate(warm_model_estimator):
    """The Gauss-Newton fit (reduced subspace, analytic Jacobian) lands where a plain trust-region
    least-squares fit of the noise-weighted residual through scipy's interpolant does."""
    est = warm_model_estimator
    keep = est.keep
    ref = RBFInterpolator(est.forces / est.scale, est.y[:, keep], kernel="thin_plate_spline", degree=1)
    rng = np.random.default_rng(3)
    for i in rng.choice(np.arange(1, len(est.y)), 8, replace=False):
        y = est.y[i] + rng.normal(size=est.y.shape[1]) * est.noise
        F = est.estimate(y)
        fit = least_squares(lambda f, y=y: (y[keep] - ref(f[None] / est.scale)[0]) * est.w,
                            est.linear.estimate(y), xtol=1e-12, ftol=1e-12)
        np.testing.assert_allclose(F, fit.x, atol=0.02)  # N, against forces of 5..40 N


@pytest.fixture(scope="module")
def warm_model_estimator(cuboid, cuboid_model):
    from cstomo_sensor.force.estimators.estimate import build_estimator

    return build_estimator("model", cuboid, cuboid_model)


def _noisy_changes(est, rng, n):
    """Calibration changes at 0.3..1.2 of their load, noisy (loaded frames), and noise alone."""
    i = rng.integers(1, len(est.y), n)
    loaded = est.y[i] * rng.uniform(0.3, 1.2, (n, 1)) + rng.normal(size=(n, est.y.shape[1])) * est.noise
    return np.vstack([loaded, rng.normal(size=(n // 4, est.y.shape[1])) * est.noise])


@pytest.mark.parametrize("masked", [False, True])
def test_model_estimator_equals_its_previous_formulation(warm_model_estimator, masked):
    """The Gauss-Newton fit with the normal equations in one product and Cramer's rule on floats
    lands where the plain formulation (value, Jacobian, J^T J and J^T r apart) does, to rounding."""
    from reference_frame_path import model_estimate

    est = warm_model_estimator
    if masked:
        keep = np.ones(est.y.shape[1], bool)
        keep[[3, 50, 51, 120]] = False
        est = est.masked(keep)
    for y in _noisy_changes(est, np.random.default_rng(4), 40):
        y = np.where(est.keep, y, 0.0)
        est.forget()  # from the linear estimate, as the plain formulation starts (a warm start moves it within 1e-4 N)
        np.testing.assert_allclose(est.estimate(y), model_estimate(est, y), rtol=1e-10, atol=1e-10)


def tared_stream(pipe, seed: int, creep: float, age_s: float | None = None):
    """A stream of ``pipe`` (no field; creep compensated at ``creep`` per decade) tared on 20 frames of its
    model's reference at 60 dB (``age_s``: a saved tare this old); with the reference, the noise's std
    and the generator for the frames to come."""
    from cstomo_sensor.frame_path.config import StreamConfig
    from cstomo_sensor.frame_path.stream import FrameStream

    rng = np.random.default_rng(seed)
    ref = pipe.model_reference
    noise = np.sqrt(np.mean(ref**2)) * 1e-3  # 60 dB
    stream = FrameStream(pipe, StreamConfig.offline(creep_per_decade=creep))
    tare = ref + noise * rng.normal(size=(20, len(ref)))
    stream.set_reference(tare.mean(axis=0), tare.std(axis=0, ddof=1), 20, "tare", age_s=age_s)
    return stream, ref, noise, rng


@pytest.mark.slow  # seconds of computation
@pytest.mark.parametrize("masked", [False, True])
def test_drift_tracker_equals_its_previous_formulation(warm_model, masked):
    """The tracker's update (the prediction's diagonal as a strided view, LAPACK's solve at rest, its
    factors kept per period) follows the state the plain formulation does (row and column operations,
    a matrix inverse), frame for frame, to rounding: a stream through a 2 % warming with rests and
    loads, the twin fed each frame's change as the stream formed it."""
    import copy

    from reference_frame_path import drift_observe


    pipe = warm_model
    stream, ref, noise, rng = tared_stream(pipe, 6, creep=0.0)
    flags = None
    if masked:  # three saturated channels on every frame
        flags = np.zeros(pipe.n_meas, bool)
        flags[[7, 8, 100]] = True
        stream.update_mask(flags, None)
    ours = stream.slow.drift
    twin = copy.deepcopy(ours)
    observe = ours.observe
    rests = []

    def both(y, t=None, joint=None, now=False):
        assert joint is None  # linear: no joint fit (issue 26), the formulation the twin has (every frame updates)
        rest = observe(y, t, joint, now)
        assert drift_observe(twin, y.copy(), t) == rest
        np.testing.assert_allclose(ours.scale, twin.scale, rtol=1e-12)
        np.testing.assert_allclose(ours.rate, twin.rate, rtol=1e-6, atol=1e-15)
        np.testing.assert_allclose(ours.gradient, twin.gradient, rtol=1e-6, atol=1e-12)
        np.testing.assert_allclose(ours.P, twin.P, rtol=1e-6, atol=1e-9 * np.abs(twin.P).max())
        rests.append(rest)
        return rest

    ours.observe = both
    Y = np.asarray(pipe.estimator.y)
    for k in range(1500):
        v = (1 + 0.02 * min(k / 1000, 1)) * (ref + (Y[1 + k % (len(Y) - 1)] * pipe.model.v_scale
                                                   if (k // 100) % 2 else 0.0))
        stream.push(v + noise * rng.normal(size=len(ref)), flags, stamp_ns=int(1e9 * (1 + k / 100)))
    assert stream.slow.drift is ours and 0.3 < np.mean(rests) < 0.7  # both kinds of frame
    assert np.abs(ours.follow).max() > 0  # the loaded frames moved the other states (issue 26's follow)
    assert ours.change == pytest.approx(0.02, abs=2e-3)


@pytest.fixture
def model_pipe(warm_model):
    """The test's pipeline with the ``model`` estimator (its own: a mask stays with it)."""
    from conftest import PIPE

    from cstomo_sensor.frame_path.config import PipelineConfig
    from cstomo_sensor.frame_path.pipeline import Pipeline

    return Pipeline.build(PipelineConfig(**{**PIPE, "grid": tuple(PIPE["grid"]), "estimator": "model"}))


@pytest.mark.parametrize("masked", [False, True])
def test_model_sigma_equals_its_plain_formulation(model_pipe, masked):
    """The force's sigma through the ``model`` estimator's own map (``k (J^T J)^-1`` on Python floats,
    one product for every state's direction) equals the plain covariance (np.linalg.solve, the full 3 x 3
    matrix), frame for frame, to rounding: a stream with drift tracking and creep through a 2 % warming
    with rests and loads, after a restart (the states' covariance wide)."""
    from reference_frame_path import model_sigma


    pipe = model_pipe
    stream, ref, noise, rng = tared_stream(pipe, 7, creep=0.04, age_s=3600.0)
    flags = None
    if masked:
        flags = np.zeros(pipe.n_meas, bool)
        flags[[7, 8, 100]] = True
    checked, misfits = [], []

    class Checked:
        """The stream's sigma of one frame, checked against the plain form."""

        def __init__(self, sig):
            self.sig, self.offset = sig, None

        def creep_force(self, offset):
            self.offset = offset.copy()  # the offset the frame was corrected by
            return self.sig.creep_force(offset)

        def __call__(self, force, P, creep_f=None, change=0.0, misfit=1.0):
            out = self.sig(force, P, creep_f, change, misfit)
            plain = model_sigma(self.sig, stream.slow.drift._D, force, P, self.offset, change, misfit)
            misfits.append(misfit)
            np.testing.assert_allclose(out[0], plain[0], rtol=1e-9)
            assert out[1] == pytest.approx(plain[1], rel=1e-9)
            checked.append(out[1])
            return out

    sigma_model = stream.slow._sigma_model
    stream.slow._sigma_model = lambda p: Checked(sigma_model(p))
    Y = np.asarray(pipe.estimator.y)
    for k in range(400):
        v = (1 + 0.02 * k / 400) * (ref + (Y[1 + k % (len(Y) - 1)] * pipe.model.v_scale if (k // 50) % 2 else 0.0))
        stream.push(v + noise * rng.normal(size=len(ref)), flags, stamp_ns=int(1e9 * (1 + k / 100)))
    assert len(checked) == 400 and stream.slow.drift.rest_frames > 0 and stream.slow._sigma.est is pipe.estimator
    assert max(misfits) > 1.0  # frames whose misfit widened their sigma were checked too


def test_joint_fit_equals_its_numpy_formulation(model_pipe):
    """The joint fit of force and scale (``JointScale.measure``: its 3 x 3 normal matrix inverted on Python
    floats) gives what ``np.linalg.solve`` of the same normal equations gave, frame for frame, to rounding: a
    stream with drift tracking and creep through a 2 % warming with rests and loads after a restart (the other
    states measured under load too), each frame's measurement also taken with a controller's expected load."""
    from reference_frame_path import joint_measure

    from cstomo_sensor.force.estimators.scale_fit import JointScale

    pipe = model_pipe
    stream, ref, noise, rng = tared_stream(pipe, 5, creep=0.04, age_s=3600.0)
    measure = JointScale.measure
    kinds = []

    def checked(joint, expected=None, others=False):
        out = measure(joint, expected, others)
        plain = joint_measure(joint, expected, others)
        assert (out is None) == (plain is None)
        if out is not None:
            for a, b in zip(out[:5], plain[:5]):
                np.testing.assert_allclose(a, b, rtol=1e-9, atol=1e-12 * max(np.max(np.abs(b)), 1e-300))
            assert (out[5] is None) == (plain[5] is None)
            if out[5] is not None:
                for a, b in zip(out[5], plain[5]):
                    np.testing.assert_allclose(a, b, rtol=1e-7, atol=1e-9 * np.max(np.abs(b)))
            kinds.append(out[5] is not None)
        if expected is None and out is not None:  # the same frame with a load a controller expects
            e = (out[4] + 0.5, 0.5)
            a, b = measure(joint, e), joint_measure(joint, e)
            for x, y in zip(a[:5], b[:5]):
                np.testing.assert_allclose(x, y, rtol=1e-9, atol=1e-12 * max(np.max(np.abs(y)), 1e-300))
        return out

    JointScale.measure = checked
    try:
        Y = np.asarray(pipe.estimator.y)
        for k in range(300):
            v = (1 + 0.02 * k / 300) * (ref + (Y[1 + k % (len(Y) - 1)] * pipe.model.v_scale if (k // 50) % 2 else 0.0))
            stream.push(v + noise * rng.normal(size=len(ref)), stamp_ns=int(1e9 * (1 + k / 100)))
    finally:
        JointScale.measure = measure
    assert len(kinds) > 250 and any(kinds) and not all(kinds)  # with and without the others' part


@pytest.mark.parametrize("rate", [100.0, 30.0])
def test_creep_compensator_equals_its_previous_formulation(rate):
    """The creep's low-passes stepped by one product (``[diag(1 - a) | a]`` times the state and the change
    held) give the offsets the row operations did, frame for frame, to rounding: loads on and off, stamps
    that jitter, a gap, and channels frozen for a while; at 30 frames/s a period that does not divide the
    0.1 s delay (the part of a step)."""
    from reference_frame_path import PlainCreep

    from cstomo_sensor.force.slow_states.creep import CreepCompensator

    rng = np.random.default_rng(8)
    n = 208
    ours, plain = CreepCompensator(0.04, n), PlainCreep(0.04, n)
    load = rng.normal(size=n)
    t = 1.0
    frozen = np.zeros(n, bool)
    frozen[[5, 6, 77]] = True
    for k in range(1500):
        t += (1.0 + 1e-3 * rng.normal()) / rate + (0.5 if k == 700 else 0.0)
        y = load * ((k // 150) % 2) * (1 + 0.01 * rng.normal()) + 1e-3 * rng.normal(size=n)
        f = frozen if 400 <= k < 500 else None
        ours.observe(y, t, f)
        plain.observe(y, t, f)
        np.testing.assert_allclose(ours.offset, plain.offset, rtol=0, atol=1e-12 * np.abs(plain.offset).max() + 1e-300)
    assert np.abs(plain.offset).max() > 1e-3  # the loads crept


def test_slow_states_small_tests_equal_their_numpy_formulations():
    """The quiet test, the learner's unloaded test and the follow slope's sums on Python floats give the
    verdicts and means their numpy forms did, frame for frame, to rounding: forces at rest, loads put on and
    taken off (a step the tests see, then its post time), a NaN force, a known load, two frame rates."""
    from reference_frame_path import PlainQuietTest, PlainUnloaded, follow_add

    from cstomo_sensor.force.slow_states.drift_parts import FollowSlope, QuietTest
    from cstomo_sensor.force.slow_states.learned import Unloaded

    rng = np.random.default_rng(11)
    for dt in (0.01, 1 / 30):
        quiet, plain_q = QuietTest(0.05, 0.5), PlainQuietTest(0.05, 0.5)
        unl, plain_u = Unloaded(), PlainUnloaded()
        follow, fit, slope = FollowSlope(8), np.zeros((3, 8)), np.zeros(7)
        verdicts, clears, fitted = [], [], []
        for k in range(3000):
            load = np.array([3.0, -1.0, -8.0]) * ((k // 400) % 2) + (0.3 if 1500 <= k < 1700 else 0.0)
            f = load + 0.05 * rng.normal(size=3)
            rest = not load.any() and rng.random() < 0.9
            v = quiet.step(f, rest, dt)
            assert v == plain_q.step(f, rest, dt)
            np.testing.assert_allclose(quiet.fast, plain_q.fast, rtol=1e-12, atol=1e-15)
            np.testing.assert_allclose(quiet.slow, plain_q.slow, rtol=1e-12, atol=1e-15)
            assert quiet.quiet == plain_q.quiet and quiet.post == plain_q.post
            force = None if k == 2100 else np.array([np.nan, 0.0, 1.0]) if k == 2101 else f
            known = 2500 <= k < 2510
            c = unl.step(force, rest, 0.05, dt, known)
            assert c == plain_u.step(force, rest, 0.05, dt, known)
            assert (unl.clear, unl.broke) == (plain_u.clear, plain_u.broke)
            np.testing.assert_allclose(unl.fast, plain_u.fast, rtol=1e-12, atol=1e-15)
            if rest:  # the scale's change drifting, the other states along it
                s = 0.02 * k / 3000 + 1e-4 * rng.normal()
                g = s * np.arange(1, 8) * 0.1 + 1e-5 * rng.normal(size=7)
                follow.add(dt, s, g)
                fitted.append(follow_add(fit, slope, dt, s, g))
                assert follow.fitted == any(fitted)
                np.testing.assert_allclose(follow._fit, fit, rtol=1e-12)
                np.testing.assert_allclose(follow.slope, slope, rtol=1e-9, atol=1e-15)
            verdicts.append(v)
            clears.append(c)
        assert 0 < np.mean(verdicts) < 1 and 0 < np.mean(clears) < 1 and follow.fitted  # both kinds, a fitted slope


def test_a_noise_change_gives_the_frames_record_the_new_estimator_and_no_fit_of_the_old(model_pipe):
    """A noise estimate taken mid-stream (frame_path/stream.py, ``Pipeline.set_noise``): the frame's record the slow
    states then read (``Pipeline.after_noise``) is made with the new noise's estimator and consistency, and carries
    no fit (the old estimator's whitens the change by the old noise); its result and change stay."""
    pipe = model_pipe
    pipe.set_reference(pipe.model_reference)
    before = pipe.step(pipe.model_reference * (1 + 1e-3 * np.linspace(-1, 1, pipe.n_meas)))
    assert before.fit is not None and before.in_use.estimator is pipe.estimator  # the model estimator fitted it
    level = 1e-3 * float(np.sqrt(np.mean(pipe.model_reference**2)))  # 60 dB
    pipe.set_noise(np.full(pipe.n_meas, level), "test")
    after = pipe.after_noise(before)
    assert after.in_use is pipe.in_use and after.in_use is not before.in_use
    assert after.in_use.estimator is pipe.estimator and after.in_use.estimator is not before.in_use.estimator
    assert after.in_use.consistency is pipe.consistency and after.fit is None
    assert after.result is before.result and after.change is before.change and after.plausible == before.plausible


# ---- helper est (issue 34's frame cost: the estimator, the joint fit, the sigma) ----------------------------------

def test_spline_basis_rows_without_the_zero_terms_equal_the_full_rows(nodes, warm_model_estimator):
    """``basis_rows`` leaves out the gradient's ``1 (x - p_i)`` terms, which the coefficients of the spline (and
    of any values at its nodes) take to zero: its products with them equal the full rows' to rounding, at points
    among the nodes, near one (1e-9 away) and at one; on the test spline and on the model estimator's own."""
    from reference_frame_path import spline_rows

    p, v = nodes
    rng = np.random.default_rng(5)
    for spline in (ThinPlateSpline(p, v), warm_model_estimator.surrogate):
        pts = spline.points
        scale = np.abs(pts).max()
        xs = list(rng.uniform(-1, 1, (20, 3)) * scale) + [pts[3] + 1e-9, pts[7]]
        other = spline.coefficients_of(rng.normal(size=(len(pts), 2)))  # another spline's coefficients, same nodes
        for coef in (spline.coefficients, other):
            for x in xs:
                want = spline_rows(spline, x) @ coef
                got = spline.basis_rows(tuple(x)) @ coef
                np.testing.assert_allclose(got, want, rtol=1e-9, atol=1e-9 * np.abs(want).max())
