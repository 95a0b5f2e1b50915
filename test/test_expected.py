"""The rules of a controller's expected load (force/checks/expected.py, issue 34 item 5) on the frame stream: the
committed bag's honest frames (its own simulator's mesh, 60 dB), tared on its unloaded frames, then its
(10, 0, -10) N load held; the ``model`` estimator (the joint fit that uses an expected load). Each run is
compared with the same frames without any message. Through a real node: test_node_expected.py."""
from __future__ import annotations

import math

import numpy as np
import pytest
from conftest import PIPE

TRUE = np.array([10.0, 0.0, -10.0])
RATE = 50.0


@pytest.fixture(scope="module")
def model_pipe(warm_model):
    from cstomo_sensor.frame_path.config import PipelineConfig
    from cstomo_sensor.frame_path.pipeline import Pipeline

    return Pipeline.build(PipelineConfig(**{**PIPE, "grid": tuple(PIPE["grid"]), "estimator": "model"}))


def _run(pipe, bag, n, message=None):
    """(forces (n, 3), scales (n,), scale 1-sigmas (n,), stream) of ``n`` frames of the held load from a
    tare on the bag's unloaded frames; ``message(k, stamp_ns, stream)`` is called before frame k."""
    from cstomo_sensor.frame_path.config import StreamConfig
    from cstomo_sensor.frame_path.stream import FrameStream

    stream = FrameStream(pipe, StreamConfig.offline(creep_per_decade=0.0))
    rest = bag.frames[:20]
    stream.set_reference(rest.mean(axis=0), rest.std(axis=0, ddof=1), len(rest), "tare")
    load = bag.frames[70:120]
    out, scale, sd = np.full((n, 3), np.nan), np.zeros(n), np.zeros(n)
    for k in range(n):
        stamp = int(1e9 * (1000.0 + k / RATE))
        if message is not None:
            message(k, stamp, stream)
        o = stream.push(load[k % 50], stamp_ns=stamp)
        out[k] = o.result.force
        scale[k], sd[k] = stream.slow.drift.scale, math.sqrt(stream.slow.drift.P[0, 0])
    return out, scale, sd, stream


def test_each_bad_kind_is_refused_and_counted_and_none_moves_anything(model_pipe, source, caplog):
    n = 150
    base, s0, sd0, _ = _run(model_pipe, source, n)
    bad = [((0, 0, math.nan), 0.0, None), ((math.inf, 0, 0), 0.0, None), ((0, 0, -1e9), 0.0, None),
           ((0, 0, -100.0), 0.0, None), ((0, 0, -40.0), 0.0, None), (TRUE, -1e6, None), (TRUE, 1e6, None),
           (TRUE, 0.0, "world")]
    expect = ["not_finite", "not_finite", "beyond_range", "beyond_range", "", "stale", "future", "other_frame"]

    def message(k, stamp, stream):
        force, rel, frame = bad[k % len(bad)]
        said = stream.expect_load(force, 2.0, stamp + int(rel * 1e9), frame or "cstomo_socket")
        if k >= 1:  # the first frame: no time to check a stamp against yet
            assert said == expect[k % len(bad)], (k, said)

    with caplog.at_level("WARNING", logger="cstomo_sensor.force.checks.expected"):
        out, s1, _, stream = _run(model_pipe, source, n, message)
    refused = stream.slow.expected.refused
    print(refused)
    assert all(refused[k] > 0 for k in ("not_finite", "beyond_range", "far", "stale", "future", "other_frame"))
    said = [r.getMessage() for r in caplog.records if "refused" in r.getMessage()]
    assert len(said) == 6, said  # once per kind
    # nothing was used: the same forces and states as without any message
    np.testing.assert_allclose(out, base, atol=1e-9)
    np.testing.assert_allclose(s1, s0, atol=1e-12)


@pytest.mark.parametrize("chi2", [20.0])
def test_an_accepted_message_moves_the_states_by_no_more_than_their_sigma(model_pipe, source, chi2):
    """A controller that says, every frame for 5 s, a load as far from the frames as the consistency
    test accepts (chi-square ``chi2`` of 3 degrees against the frame's estimate and sigma): the device's
    scale stays within its own 1-sigma of the same frames' without it, and every force within its sigma_n."""
    n = 250
    base, s0, sd0, _ = _run(model_pipe, source, n)

    def message(k, stamp, stream):
        # offset along -z (a heavier load than the frames say) by chi2 with the frame's sigma and the message's
        sig = stream.slow._frame_sigma
        if sig is not None:
            var = sig[2] ** 2 + 4.0
            stream.expect_load(base[k] + (0, 0, -math.sqrt(chi2 * var) * 0.99), 2.0, stamp)

    out, s1, _, stream = _run(model_pipe, source, n, message)
    moved = np.abs(s1 - s0)
    print(f"scale moved by up to {moved.max():.2e} (its 1-sigma {sd0.min():.2e}..{sd0.max():.2e}); force by up to "
          f"{np.linalg.norm(out - base, axis=1).max():.3f} N; used {stream.slow.expected.used_frames} frames, refused "
          f"{stream.slow.expected.refused}")
    assert stream.slow.expected.used_frames > 0.8 * n
    assert np.all(moved <= sd0)
    assert np.linalg.norm(out - base, axis=1).max() < 0.25  # the frames' 1-sigma here: 0.25 N
