"""The node's self-serialised messages (ros/messages.py) against rclpy's own serialisation: for
varied values (stamps, frame ids of every string padding, extremes), ``deserialize_message`` of the
bytes equals, field by field (the message classes' ``==``), the same message built with the rclpy
classes, and the bytes equal ``serialize_message`` of it everywhere but in CDR's alignment padding
(whose content rclpy leaves unspecified: it holds whatever its buffer held)."""
from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("rclpy")

from builtin_interfaces.msg import Time  # noqa: E402
from geometry_msgs.msg import WrenchStamped  # noqa: E402
from rclpy.serialization import deserialize_message, serialize_message  # noqa: E402
from sensor_msgs.msg import PointCloud2, PointField  # noqa: E402
from std_msgs.msg import Float64  # noqa: E402

from cstomo_sensor.ros.messages import CLOUD_FIELDS, OutputMessages, RawVoltagesCdr  # noqa: E402

STAMPS = [0, 1, 999_999_999, 1_000_000_000, 1_763_851_234_567_890_123, 2**31 * 1_000_000_000 - 1]
FRAME_IDS = ["cstomo_socket", "a", "ns/joint_3_socket_frame"]  # string lengths with every padding


class _Field:
    def __init__(self, rng, n):
        self.conductivity_change = rng.normal(size=n)
        self.volumetric_compression = rng.normal(size=n) * 1e-3
        self.pressure = rng.normal(size=n) * 1e3


class _Result:
    def __init__(self, force, field):
        self.force = force
        self.magnitude, self.elevation, self.azimuth = float(np.linalg.norm(force)), 0.3, -2.1
        self.field = field


def _same_cdr(data: bytes, ref) -> None:
    """``data`` is the CDR of message ``ref``: field by field, and byte for byte outside padding."""
    want = serialize_message(ref)
    assert len(data) == len(want)
    back = deserialize_message(data, type(ref))
    assert back == ref  # every field (rclpy's generated __eq__)
    differ = [i for i, (a, b) in enumerate(zip(data, want)) if a != b]
    pads, size = _padding(ref)
    assert size == len(want)
    assert set(differ) <= pads, f"bytes {sorted(set(differ) - pads)} differ outside padding"


_SIZES = {"boolean": 1, "octet": 1, "uint8": 1, "int8": 1, "char": 1, "int16": 2, "uint16": 2,
          "int32": 4, "uint32": 4, "float": 4, "int64": 8, "uint64": 8, "double": 8}


def _padding(msg) -> tuple[set[int], int]:
    """(offsets of CDR's alignment padding, total size) of the serialisation of ``msg`` (XCDR1, little endian: a
    4-byte encapsulation header, then every primitive aligned to its size from the payload's start;
    a string or sequence is a uint32 count, then its elements), walking the message's own fields."""
    pads, pos = set(), 0

    def align(n):
        nonlocal pos
        skip = -pos % n
        pads.update(range(4 + pos, 4 + pos + skip))
        pos += skip

    def walk(value, typ):
        nonlocal pos
        if typ.startswith("sequence<"):
            inner = typ[len("sequence<"):-1]
            align(4)
            pos += 4
            for v in value:
                walk(v, inner)
        elif typ == "string":
            align(4)
            pos += 4 + len(value.encode()) + 1
        elif typ in _SIZES:
            align(_SIZES[typ])
            pos += _SIZES[typ]
        else:  # a nested message
            for name, t in value.get_fields_and_field_types().items():
                walk(getattr(value, name), t)

    walk(msg, "msg")
    return pads, 4 + pos


def _time(ns: int) -> Time:
    return Time(sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000)


@pytest.mark.parametrize("frame_id", FRAME_IDS)
def test_wrench_and_floats_equal_rclpy(frame_id):
    rng = np.random.default_rng(1)
    out = OutputMessages(rng.normal(size=(7, 3)) * 0.01, frame_id)
    for ns in STAMPS:
        f = rng.normal(size=3) * 20
        f[rng.integers(3)] = -0.0 if ns % 2 else 1e300  # signed zero and extremes survive
        ref = WrenchStamped()
        ref.header.stamp = _time(ns)
        ref.header.frame_id = frame_id
        ref.wrench.force.x, ref.wrench.force.y, ref.wrench.force.z = (float(v) for v in f)
        data = out.wrench(f, ns)
        _same_cdr(data, ref)
        back = deserialize_message(data, WrenchStamped)
        assert (back.header.stamp.sec, back.header.stamp.nanosec) == divmod(ns, 1_000_000_000)
        assert back.header.frame_id == frame_id
        assert [back.wrench.force.x, back.wrench.force.y, back.wrench.force.z] == [float(v) for v in f]
        assert [back.wrench.torque.x, back.wrench.torque.y, back.wrench.torque.z] == [0.0, 0.0, 0.0]
    for v in (0.0, -1.5, 3.141592653589793, float("inf"), 1e-300):
        _same_cdr(out.float64(v), Float64(data=v))
        assert deserialize_message(out.float64(v), Float64).data == v


@pytest.mark.parametrize("frame_id", ["cstomo_socket", "knee_left/socket_frame"])
def test_wrench_sigma_equals_rclpy(frame_id):
    """~/wrench_sigma (Vector3Stamped) from the template is rclpy's serialisation, under the wrench's
    stamp and frame_id; build() adds it for a result with a sigma, and only then."""
    from geometry_msgs.msg import Vector3Stamped

    rng = np.random.default_rng(3)
    out = OutputMessages(rng.normal(size=(7, 3)) * 0.01, frame_id)
    for ns in STAMPS:
        v = np.abs(rng.normal(size=3))
        ref = Vector3Stamped()
        ref.header.stamp = _time(ns)
        ref.header.frame_id = frame_id
        ref.vector.x, ref.vector.y, ref.vector.z = (float(x) for x in v)
        _same_cdr(out.vector(v, ns), ref)
        r = _Result(rng.normal(size=3), None)
        r.sigma = tuple(v)
        msgs = out.build(r, ns)
        assert list(msgs)[:2] == ["wrench", "wrench_sigma"]
        _same_cdr(msgs["wrench_sigma"], ref)
        w = deserialize_message(msgs["wrench"], WrenchStamped)
        assert deserialize_message(msgs["wrench_sigma"], Vector3Stamped).header == w.header
    assert "wrench_sigma" not in out.build(_Result(np.ones(3), None), 0)


@pytest.mark.parametrize("n_cells", [1, 5, 256])
def test_stress_cloud_and_build_equal_rclpy(n_cells):
    rng = np.random.default_rng(n_cells)
    centers = rng.normal(size=(n_cells, 3)) * 0.01
    out = OutputMessages(centers, "cstomo_socket")
    for ns in STAMPS[:3]:
        field = _Field(rng, n_cells)
        ref = PointCloud2()
        ref.header.stamp = _time(ns)
        ref.header.frame_id = "cstomo_socket"
        ref.height, ref.width = 1, n_cells
        ref.fields = [PointField(name=n, offset=4 * i, datatype=PointField.FLOAT32, count=1)
                      for i, n in enumerate(CLOUD_FIELDS)]
        ref.is_bigendian = False
        ref.point_step, ref.row_step = 24, 24 * n_cells
        cols = np.column_stack([centers, field.conductivity_change, field.volumetric_compression, field.pressure])
        ref.data = cols.astype("<f4").tobytes()
        ref.is_dense = True
        msgs = out.build(_Result(rng.normal(size=3), field), ns)
        _same_cdr(msgs["stress_field"], ref)
        back = deserialize_message(msgs["stress_field"], PointCloud2)
        assert back.width == n_cells and back.point_step == 24 and back.is_dense
        assert [f.name for f in back.fields] == list(CLOUD_FIELDS)
        np.testing.assert_array_equal(np.frombuffer(bytes(back.data), "<f4").reshape(n_cells, 6),
                                      cols.astype(np.float32))
        assert set(msgs) == {"wrench", "force_magnitude", "force_elevation", "force_azimuth", "stress_field"}
        assert deserialize_message(msgs["force_azimuth"], Float64).data == -2.1
    assert "stress_field" not in out.build(_Result(np.ones(3), None), 0)


def test_scene_cloud_and_consistency_equal_rclpy():
    """A result with the scene's field and the consistency statistic: ~/scene_stress_field is the same
    cloud layout as ~/stress_field with the scene's values; ~/consistency a Float64."""
    rng = np.random.default_rng(8)
    centers = rng.normal(size=(9, 3)) * 0.01
    out = OutputMessages(centers, "cstomo_socket")
    r = _Result(rng.normal(size=3), _Field(rng, 9))
    r.scene_field, r.consistency = _Field(rng, 9), 3.25
    msgs = out.build(r, STAMPS[1])
    assert set(msgs) == {"wrench", "force_magnitude", "force_elevation", "force_azimuth", "stress_field",
                         "scene_stress_field", "consistency"}
    _same_cdr(msgs["consistency"], Float64(data=3.25))
    ref = deserialize_message(msgs["stress_field"], PointCloud2)  # held equal to rclpy above
    cols = np.column_stack([centers, r.scene_field.conductivity_change, r.scene_field.volumetric_compression,
                            r.scene_field.pressure])
    ref.data = cols.astype("<f4").tobytes()
    _same_cdr(msgs["scene_stress_field"], ref)
    r.consistency = float("nan")  # no statistic: no message
    assert "consistency" not in out.build(r, 0)


def test_raw_voltages_equal_rclpy():
    """The stamped raw frame (sensor_msgs/Image 32FC1, 1 x 208) from the template equals rclpy's own
    serialisation of the message, reads back with its stamp, and NaN marks the flagged measurements."""
    from sensor_msgs.msg import Image

    from cstomo_sensor.ros.messages import frame_from_raw_msg, legacy_raw_voltages_msg

    rng = np.random.default_rng(5)
    cdr = RawVoltagesCdr("left_socket")
    for ns in (0, 1_700_000_000_123_456_789, 2**31 * 10**9 - 1):
        v = rng.normal(size=208) * 0.1
        ref = Image()
        ref.header.stamp = _time(ns)
        ref.header.frame_id = "left_socket"
        ref.height, ref.width, ref.encoding, ref.is_bigendian, ref.step = 1, 208, "32FC1", 0, 832
        ref.data = v.astype("<f4").tobytes()
        data = cdr(v, ns)
        _same_cdr(data, ref)
        values, flagged, stamp = frame_from_raw_msg(deserialize_message(data, Image))
        np.testing.assert_array_equal(values, v.astype(np.float32))
        assert flagged is None and stamp == (ns or None)
    flag = np.zeros(208, bool)
    flag[[3, 100]] = True
    values, flagged, _ = frame_from_raw_msg(deserialize_message(cdr(v, 5, flag), Image))
    assert np.array_equal(flagged, flag) and np.isnan(values[flag]).all() and np.isfinite(values[~flag]).all()
    legacy = legacy_raw_voltages_msg(v)  # older recordings: no stamp
    assert legacy.layout.dim[0].label == "measurement"
    values, flagged, stamp = frame_from_raw_msg(legacy)
    np.testing.assert_array_equal(values, v.astype(np.float32))
    assert flagged is None and stamp is None
