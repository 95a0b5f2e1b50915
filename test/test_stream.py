"""The frame stream's one list of outputs (frame_path/outputs.py OUTPUTS) against what the node publishes,
what replay writes and what ``cstomo_sensor_node --help`` says; and two sensors in two namespaces
with distinct diagnostics names."""
from __future__ import annotations

import re
import threading
from pathlib import Path

import numpy as np
import pytest
from conftest import PIPE, diagnostics_seen, wait_for

rclpy = pytest.importorskip("rclpy")

BAG = Path(__file__).resolve().parent / "data" / "raw_voltages_bag"
#: Settings that change the output set: the defaults, no stress field, no filter, neither.
CASES = [dict(), dict(stress_field_every=0), dict(wrench_filter_hz=0.0), dict(stress_field_every=0, wrench_filter_hz=0.0)]


def _nodes(namespaces_params: list[tuple[str, dict]]):
    """Start CstomoSensorNodes (topic input) in their namespaces on one executor; returns
    (context, nodes, stop)."""
    from rclpy.executors import MultiThreadedExecutor
    from rclpy.parameter import Parameter

    from cstomo_sensor.ros.node import CstomoSensorNode

    ctx = rclpy.Context()
    rclpy.init(context=ctx)
    nodes = [CstomoSensorNode("cstomo_sensor", namespace=ns, context=ctx,
                              parameter_overrides=[Parameter(k, value=v) for k, v in p.items()])
             for ns, p in namespaces_params]
    ex = MultiThreadedExecutor(num_threads=2, context=ctx)
    for n in nodes:
        ex.add_node(n)
    t = threading.Thread(target=ex.spin, daemon=True)
    t.start()

    def stop():
        ex.shutdown(timeout_sec=2.0)
        t.join(5.0)
        for n in nodes:
            n._release()
            n.destroy_node()
        rclpy.try_shutdown(context=ctx)

    return ctx, nodes, stop


@pytest.mark.slow  # starts a node
def test_the_node_publishes_exactly_the_stream_outputs(tmp_path, warm_model):
    from cstomo_sensor.frame_path.config import StreamConfig
    from cstomo_sensor.frame_path.outputs import OUTPUTS, output_set
    from cstomo_sensor.ros.messages import RAW_TOPIC, TOPIC_TYPES

    assert set(TOPIC_TYPES) == set(OUTPUTS) | {RAW_TOPIC}  # every output has its message type, nothing else
    specs = [(f"/case{i}", dict(PIPE, input="topic", tare_file=str(tmp_path / f"tare{i}.csv"), **c))
             for i, c in enumerate(CASES)]
    _, nodes, stop = _nodes(specs)
    try:
        assert wait_for(lambda: all(n._state_machine.current_state[1] == "active" for n in nodes), 20.0)
        for (ns, c), node in zip(specs, nodes):
            pubs = {name for name, _ in node.get_publisher_names_and_types_by_node("cstomo_sensor", ns)}
            own = {p for p in pubs if p.startswith(f"{ns}/cstomo_sensor/") and not p.endswith("/transition_event")}
            want = output_set(StreamConfig(**{k: v for k, v in c.items() if k in ("stress_field_every", "wrench_filter_hz")}),
                              scene_field=True)
            assert own == {f"{ns}/cstomo_sensor/{t}" for t in want}, (ns, sorted(own))
            assert node.stream.outputs == want
    finally:
        stop()
    assert output_set(StreamConfig(), scene_field=True) == tuple(OUTPUTS)  # the defaults publish every output


@pytest.mark.parametrize("case", CASES)
def test_replay_writes_exactly_the_stream_outputs(tmp_path, case, warm_model):
    pytest.importorskip("rosbags")
    from cstomo_sensor.frame_path.config import PipelineConfig, StreamConfig
    from cstomo_sensor.frame_path.outputs import output_set
    from cstomo_sensor.tools.replay import replay

    cfg = PipelineConfig(**{k: (tuple(v) if k == "grid" else v) for k, v in PIPE.items()})
    every = case.get("stress_field_every", StreamConfig.stress_field_every)
    hz = case.get("wrench_filter_hz", StreamConfig.wrench_filter_hz)
    s = replay(BAG, tmp_path / "out", cfg, tare_frames=10, stress_field_every=every, wrench_filter_hz=hz,
               pipeline=warm_model)
    want = output_set(StreamConfig(stress_field_every=every, wrench_filter_hz=hz), scene_field=True)
    assert s.output_topics == tuple(f"/cstomo_sensor/{t}" for t in want)
    from rosbags.rosbag2 import Reader

    with Reader(tmp_path / "out") as r:
        assert {c.topic for c in r.connections} == set(s.output_topics)
        assert sorted(p.name for p in (tmp_path / "out").iterdir()) == ["metadata.yaml", "out.db3"]  # its own name
    assert not [p for p in tmp_path.iterdir() if p.name != "out"]  # no partial left beside it


def test_help_lists_exactly_the_stream_outputs():
    from cstomo_sensor.frame_path.outputs import OUTPUTS
    from cstomo_sensor.ros.startup import usage

    text = usage()
    listed = set(re.findall(r"^\s+~/(\w+)\s", text, flags=re.M))
    assert listed == set(OUTPUTS) | {"raw_voltages", "tare", "tare_forced", "raw_voltages_in", "joint_free",
                                     "expected_wrench"}, listed


@pytest.mark.slow  # starts a node
def test_two_sensors_in_two_namespaces_have_distinct_diagnostics_names(tmp_path, warm_model):
    specs = [(ns, dict(PIPE, input="topic", tare_file=str(tmp_path / f"{ns.strip('/')}.csv")))
             for ns in ("/left_knee", "/right_knee")]
    ctx, nodes, stop = _nodes(specs)
    try:
        with diagnostics_seen(ctx) as seen:
            assert wait_for(lambda: len(seen) >= 2 and min(map(len, list(seen.values()))) >= 2, 20.0), seen
    finally:
        stop()
    assert set(seen) == {"/left_knee/cstomo_sensor: sensor", "/right_knee/cstomo_sensor: sensor"}, seen


def test_a_dropped_frame_never_raises_and_repeats_are_logged_once(warm_model, caplog):
    """The stream's boundary: frames of the wrong length and an unexpected error are counted and
    logged at most once per LOG_EVERY s, never raised to the caller."""
    from cstomo_sensor.frame_path.stream import FrameStream

    stream = FrameStream(warm_model)
    stream.set_reference(warm_model.model_reference, None, 1, "test")
    with caplog.at_level("WARNING", logger="cstomo_sensor.frame_path.stream"):
        for _ in range(20):
            assert stream.push(np.ones(207)) is None
        assert stream.push(np.array(["x"] * 208, dtype=object)) is None  # not numbers: an unexpected error
    assert stream.counter.counts.rejected == 21 and stream.counter.counts.errors <= 1
    assert len([r for r in caplog.records if "dropped frame" in r.getMessage()]) == 1
    out = stream.push(warm_model.model_reference * 1.0001)
    assert out is not None and out.result.valid and stream.counter.counts.reject_reason == ""


def test_health_is_a_snapshot_and_a_period_ends_only_when_asked(warm_model):
    """Issue 27 item 3: reading the health changes nothing (twice the same problems and figures);
    end_period returns the period's health and the next period starts without its rejected and
    implausible frames (the all-time counts stay)."""
    from cstomo_sensor.frame_path.config import StreamConfig
    from cstomo_sensor.frame_path.health import WARN
    from cstomo_sensor.frame_path.stream import FrameStream

    stream = FrameStream(warm_model, StreamConfig.offline())
    ref = warm_model.model_reference
    stream.set_reference(ref, None, 1, "test")
    for k in range(5):
        stream.push(ref * 1.0001, stamp_ns=(k + 1) * 10_000_000)
    stream.push(np.ones(207))  # rejected
    stream.push(ref * 10, stamp_ns=60_000_000)  # implausible
    first = stream.health(1.0)
    assert first == stream.health(1.0)
    level, msgs, kv = first
    assert level == WARN and any("1 frames rejected" in m for m in msgs), msgs
    assert any("1 implausible frames" in m for m in msgs) and kv["implausible"] == 1, msgs
    assert stream.end_period(1.0) == first
    level, msgs, kv = stream.health(2.0)
    assert not any("rejected" in m or "implausible" in m for m in msgs), msgs
    assert kv["frames_rejected"] == 1 and kv["implausible"] == 1 and kv["frames"] == 7


def test_the_pipeline_offers_what_the_force_layers_protocols_read(warm_model):
    """The force layer reads the pipeline through Protocols (it does not import the frame path): the tare's rules
    (force/reference/tare_rules.py ``Pipe``), the calibration (force/reference/calibration.py ``Calibrated``) and
    the slow states (force/slow_states/coordinator.py ``Reference``, ``InUse``, ``Frame``). A name the pipeline or its frame's
    record lacked would fail only at the first tare, calibration or frame that reads it."""
    from typing import get_type_hints

    from cstomo_sensor.force.reference.calibration import Calibrated
    from cstomo_sensor.force.reference.tare_rules import Pipe
    from cstomo_sensor.force.slow_states.coordinator import Frame, InUse, Reference
    from cstomo_sensor.frame_path.pipeline import Pipeline

    pipe = Pipeline(warm_model.geometry, warm_model.model, warm_model.estimator)  # the module's own stays untared
    pipe.set_reference(pipe.model_reference)
    record = pipe.step(pipe.model_reference * 1.0001)
    for protocol, value in [(Pipe, pipe), (Calibrated, pipe), (Reference, pipe), (InUse, pipe.in_use), (Frame, record)]:
        methods = {n for n, v in vars(protocol).items() if callable(v) and not n.startswith("_")}
        names = set(get_type_hints(protocol)) | methods
        assert len(names) >= 4, (protocol, names)  # the annotations are read
        assert not [n for n in names if not hasattr(value, n)], (protocol.__name__, type(value).__name__)
