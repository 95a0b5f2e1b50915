"""Every force with its error bar (force/sigma.py, issue 26 item 3): the stream's sigma, its
diagnostics, and its honesty on an honest simulation (a device off the model, calibrated)."""
from __future__ import annotations

import numpy as np
import pytest

from cstomo_sensor.force.config import StreamConfig
from cstomo_sensor.force.health import WARN
from cstomo_sensor.force.sigma import UNDESCRIBED, ForceSigma, relative_error
from cstomo_sensor.force.stream import FrameStream


def test_sigma_is_the_covariance_diagonal_and_its_trace():
    """The per-axis sigma and sigma_n equal the full covariance the module docstring writes, computed
    plainly (noise, the tracker's states with the load's own scale change, calibration, creep)."""
    rng = np.random.default_rng(2)
    n, m = 208, 8
    W, D, noise = rng.normal(size=(3, n)), rng.normal(size=(m, n)) * 1e-2, np.full(n, 1e-3)
    keep = rng.random(n) > 0.1
    L = rng.normal(size=(m + 1, m + 1)) * 1e-3
    P = L @ L.T
    f, o = np.array([3.0, -4.0, -12.0]), rng.normal(size=n) * 1e-3
    s = ForceSigma(W, noise, keep, D, 0.05, 0.29)
    sigma, sigma_n = s(f, P, s.creep_force(o), 0.03)
    Wk = W * keep
    WD = Wk @ (D * keep).T
    wr = np.linalg.norm(WD[:, 0])  # the force of a unit uniform change: its undescribed share (UNDESCRIBED)
    WD[:, 0] += f
    c = 0.29 * Wk @ o
    cov = (Wk * noise) @ (Wk * noise).T + WD @ P[:m, :m] @ WD.T + 0.05**2 * (f @ f) / 3 * np.eye(3) + np.outer(c, c) \
        + (UNDESCRIBED * wr * 0.03) ** 2 / 3 * np.eye(3)
    np.testing.assert_allclose(sigma, np.sqrt(np.diag(cov)), rtol=1e-9)
    assert sigma_n == pytest.approx(np.sqrt(np.trace(cov)), rel=1e-9)


def test_uncalibrated_residual_is_the_nominal_accuracy():
    k_model, where = relative_error(None, "model")
    assert "nominal" in where and 0.01 < k_model < 0.03 < relative_error(None, "linear")[0]


def test_the_stream_gives_every_force_a_sigma_and_says_when_it_exceeds_the_bound(warm_model):
    pipe = warm_model
    ref = pipe.model_reference
    rng = np.random.default_rng(5)
    noise = 1e-3 * np.sqrt(np.mean(ref**2)) * np.ones_like(ref)
    for bound, warned in ((100.0, False), (1e-3, True)):
        stream = FrameStream(pipe, StreamConfig(stress_field_every=0, max_sigma_n=bound))
        stream.set_reference(ref, noise, 50, "test")
        outs = [stream.push(ref + rng.normal(size=ref.shape) * noise, stamp_ns=(k + 1) * 10_000_000) for k in range(20)]
        sig = np.array([o.result.sigma for o in outs])
        sn = np.array([o.result.sigma_n for o in outs])
        assert np.isfinite(sig).all() and (sig > 0).all()
        np.testing.assert_allclose(sn, np.linalg.norm(sig, axis=1))
        level, msgs, kv = stream.health(1e9)
        assert (level >= WARN and any("max_sigma_n" in m for m in msgs)) == warned, msgs
        assert kv["sigma_over_frames"] == (20 if warned else 0) and float(kv["sigma_n"]) == pytest.approx(sn[-1], rel=1e-3)


@pytest.mark.slow
def test_sigma_is_honest_and_informative_on_the_no_drift_baseline(monkeypatch):
    """The robot bench's device a (off the model, calibrated on 20 loads), back-to-back loads for 30 s
    without warming, drift tracking off (the no-drift baseline): at most 1 % of the published frames
    err beyond 3 sigma_n, and the median sigma_n is within 2x the median error."""
    from cstomo_sensor.model.timeline import Timeline, TimelineSpec
    from cstomo_sensor.tools.bench import robot

    monkeypatch.setattr(robot, "ESTIMATORS", ("linear",))
    sc, truth = robot.device_truth()
    pipe = robot.calibrated_pipes(truth, sc.snr_db, say=lambda m: None)["linear"]
    tare = Timeline(TimelineSpec(duration=1.0), snr_db=sc.snr_db, seed=robot.SEED, truth=truth).tare(
        20, np.random.default_rng([robot.SEED, 22]))
    spec = robot.loaded_warmup(False)
    spec = type(spec)(**{**spec.__dict__, "duration": 30.0})
    tl = Timeline(spec, snr_db=sc.snr_db, seed=robot.SEED, truth=truth).prepare()
    times, est, forces, _, sigma = robot.run_stream(pipe, tl, tare, False, robot.LOADED_RATE, 0.0)
    ok = np.isfinite(sigma)
    assert ok.mean() > 0.99
    fig = robot.sigma_figures(np.linalg.norm(est[ok] - forces[ok], axis=1), sigma[ok])
    assert fig["over3sigma_pct"] <= 1.0 and 0.5 <= fig["sigma_ratio"] <= 2.0, fig


@pytest.fixture(scope="module")
def model_pipe():
    from conftest import PIPE

    from cstomo_sensor.force.config import PipelineConfig
    from cstomo_sensor.force.pipeline import Pipeline

    return Pipeline.build(PipelineConfig(**{**PIPE, "grid": tuple(PIPE["grid"]), "estimator": "model"}))


def test_the_model_estimators_noise_term_is_its_own_scatter(model_pipe, cuboid_truth):
    """Issue 26, informative: the ``model`` estimator's sigma takes the noise through its own fit near the
    load, not through its linear part (the ridge map it starts from, 2x as sensitive: on main the noise
    term read 0.76 N on the robot bench's device_b, whose forces scatter by 0.37 N). A load held on the
    honest device (its own finer mesh), 60 dB, tracking off: the sigma's part beyond the calibration
    residual (nominal, isotropic: k |F|) is the forces' own scatter around their mean, within 25 %."""
    from cstomo_sensor.model.simulate import Load, add_noise

    pipe = model_pipe
    rng = np.random.default_rng(11)
    ref, loaded = cuboid_truth.frames([Load("socket", force=(6.0, -4.0, -12.0))])
    tare = add_noise(np.repeat(ref[None], 50, 0), ref, 60.0, rng)
    stream = FrameStream(pipe, StreamConfig(stress_field_every=0, drift_tracking=False, creep_per_decade=0.0))
    stream.set_reference(tare.mean(axis=0), tare.std(axis=0, ddof=1), len(tare), "test")
    frames = add_noise(np.repeat(loaded, 400, 0), ref, 60.0, rng)
    outs = [stream.push(v, stamp_ns=(k + 1) * 10_000_000) for k, v in enumerate(frames)]
    F = np.array([o.result.force for o in outs])
    sn = np.array([o.result.sigma_n for o in outs])
    scatter = np.sqrt(np.sum(np.var(F, axis=0)))
    k, _ = relative_error(None, "model")
    noise_part = np.sqrt(np.median(sn) ** 2 - (k * np.linalg.norm(F.mean(axis=0))) ** 2)
    print(f"scatter {scatter:.3f} N, sigma_n {np.median(sn):.3f} N, its noise part {noise_part:.3f} N")
    assert noise_part == pytest.approx(scatter, rel=0.25)
