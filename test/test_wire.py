"""The wire protocol: round trips, the CRC check value, and decoders that survive any input."""
import struct

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from cstomo_sensor.board import wire
from cstomo_sensor.board.wire import (
    Ack,
    DataFrame,
    Decoder,
    Error,
    Identify,
    Identity,
    SetCurrent,
    SetPattern,
    Start,
    Stop,
    TextDecoder,
    encode,
    encode_text,
)

COMMANDS = [Identify(), Start(250.0), Start(0.0), Stop(), SetCurrent(0.0078125), SetPattern(1), SetPattern(2)]
REPLIES = [Identity("fw 1.2.3", 16, 1, 208), Identity(""), Ack(0x02), Error(0x04, 2, "current too high"), Error(0, 1)]


def frame(seq=7, values=None, rng=None):
    rng = rng or np.random.default_rng(seq)
    v = rng.normal(0, 0.5, 208).astype(np.float32).astype(float) if values is None else values
    return DataFrame(seq, 10**12 + seq, v, rng.random(208) < 0.1, rng.random(16) < 0.9)


def same_frame(a: DataFrame, b: DataFrame) -> bool:
    return (
        a.seq == b.seq
        and a.board_time_us == b.board_time_us
        and np.array_equal(a.values.astype(np.float32).view(np.uint32), b.values.astype(np.float32).view(np.uint32))
        and np.array_equal(a.saturated, b.saturated)
        and np.array_equal(a.contact_ok, b.contact_ok)
    )


def test_crc32_check_value():
    assert wire.crc32(b"123456789") == 0xCBF43926


@pytest.mark.parametrize("msg", COMMANDS + REPLIES, ids=repr)
def test_round_trip_commands_and_replies(msg):
    d = Decoder()
    assert d.feed(encode(msg)) == [msg]
    assert d.stats.corrupt == 0 and d.stats.messages == 1


def test_round_trip_data_frame_bit_exact_float32():
    f = frame(values=np.array([np.float32(x) for x in np.linspace(-3, 3, 208)], float))
    (g,) = Decoder().feed(encode(f))
    assert same_frame(f, g)
    assert g.values.dtype == np.float64 and g.saturated.dtype == bool and g.contact_ok.dtype == bool


def test_data_frame_layout_is_the_documented_one():
    f = DataFrame(0x01020304, 0x0A0B0C0D0E0F1011, np.full(208, 1.5), np.eye(208, dtype=bool)[9],
                  np.arange(16) != 3)
    packet = wire.cobs_decode(encode(f)[1:-1])
    version, kind, length = struct.unpack_from("<BBH", packet)
    assert (version, kind, length) == (1, 0x90, 872) and len(packet) == 4 + 872 + 4
    seq, t_us, contact = struct.unpack_from("<IQH", packet, 4)
    assert (seq, t_us, contact) == (0x01020304, 0x0A0B0C0D0E0F1011, 0xFFF7)
    assert packet[18 + 1] == 0b10  # saturation bit 9: byte 1, bit 1 (LSB first)
    assert struct.unpack_from("<f", packet, 18 + 26)[0] == 1.5
    assert struct.unpack_from("<I", packet, len(packet) - 4)[0] == wire.crc32(packet[:-4])


def test_cobs_known_vectors():
    assert wire.cobs_encode(b"\x00") == b"\x01\x01"
    assert wire.cobs_encode(b"\x11\x22\x00\x33") == b"\x03\x11\x22\x02\x33"
    assert wire.cobs_encode(bytes(range(1, 255))) == b"\xff" + bytes(range(1, 255)) + b"\x01"
    assert wire.cobs_decode(b"\x05\x11") is None


def test_each_kind_of_corruption_is_counted():
    good = encode(frame())
    flipped = bytearray(good)
    flipped[100] ^= 0x10
    bad_version = wire.cobs_encode(bytes([2, 0x90, 0, 0]) + struct.pack("<I", wire.crc32(bytes([2, 0x90, 0, 0]))))
    unknown = wire.cobs_encode(bytes([1, 0x42, 0, 0]) + struct.pack("<I", wire.crc32(bytes([1, 0x42, 0, 0]))))
    nan = frame(values=np.full(208, np.nan))
    d = Decoder()
    out = d.feed(bytes(flipped) + b"\x00" + bad_version + b"\x00" + unknown + b"\x00" + good[:50] + encode(nan) + good)
    assert len(out) == 1 and same_frame(out[0], frame())
    s = d.stats
    assert (s.bad_version, s.unknown_type, s.bad_values) == (1, 1, 1)
    assert s.crc_errors >= 1 and s.crc_errors + s.bad_length == 2  # the cut frame may fail COBS first
    assert s.corrupt == 5 and s.messages == 1


def test_text_decoder():
    v = np.linspace(-1, 1, 208)
    line = encode_text(v)
    d = TextDecoder()
    bad = [b"1,2,3\n", line.replace(b",", b",x", 1), encode_text(np.r_[v[:-1], np.nan]), b"\xff" * 10 + b"\n"]
    out = d.feed(b"# comment\n\n" + b"".join(bad) + line[:100])
    assert out == [] and d.stats.corrupt == 4
    (f,) = d.feed(line[100:])
    assert np.array_equal(f.values, v) and f.seq is None and f.board_time_us is None
    assert not f.saturated.any() and f.contact_ok.all()


@settings(max_examples=300, deadline=None)
@given(st.binary(max_size=3000))
def test_arbitrary_bytes_never_raise(data):
    d, t = Decoder(), TextDecoder()
    for m in d.feed(data):
        assert isinstance(m, (Identify, Start, Stop, SetCurrent, SetPattern, Identity, Ack, Error, DataFrame))
    t.feed(data)
    assert d.stats.bytes == t.stats.bytes == len(data)


def finite_float32(raw: bytes) -> np.ndarray:
    """Any 208 float32 bit patterns (subnormals, -0.0 included), non-finite ones replaced by 1.0."""
    u = np.frombuffer(raw, "<u4")
    u = np.where(u & 0x7F800000 == 0x7F800000, np.uint32(0x3F800000), u)  # exponent all ones: not finite
    return u.astype("<u4").view("<f4").astype(float)


values32 = st.binary(min_size=4 * 208, max_size=4 * 208).map(finite_float32)


@settings(max_examples=100, deadline=None)
@given(before=st.binary(max_size=400), after=st.binary(max_size=400), values=values32,
       seq=st.integers(0, 2**32 - 1), t_us=st.integers(0, 2**64 - 1))
def test_frame_inside_garbage_is_recovered_exactly(before, after, values, seq, t_us):
    f = DataFrame(seq, t_us, values, values > 0, np.arange(16) % 3 > 0)
    out = [m for m in Decoder().feed(before + encode(f) + after) if isinstance(m, DataFrame)]
    assert [m for m in out if same_frame(m, f)], "the valid frame was not recovered"
    # garbage can only add frames by carrying a valid CRC-32; random bytes practically never do
    assert all(same_frame(m, f) for m in out)


@settings(max_examples=100, deadline=None)
@given(st.data())
def test_split_feeding_gives_the_same_messages(data):
    msgs = [frame(seq=i) for i in range(3)] + [REPLIES[0], COMMANDS[1]]
    stream = b"junk" + b"".join(encode(m) for m in msgs)
    cuts = sorted(data.draw(st.lists(st.integers(0, len(stream)), max_size=20)))
    d = Decoder()
    out = []
    for a, b in zip([0] + cuts, cuts + [len(stream)]):
        out += d.feed(stream[a:b])
    assert len(out) == len(msgs)
    for got, want in zip(out, msgs):
        assert same_frame(got, want) if isinstance(want, DataFrame) else got == want
    assert d.stats.corrupt == 1  # the leading junk


def test_text_split_feeding():
    lines = [np.arange(208) * 0.5 + k for k in range(3)]
    stream = b"".join(encode_text(v) for v in lines)
    d = TextDecoder()
    out = [f for i in range(0, len(stream), 7) for f in d.feed(stream[i : i + 7])]
    assert [f.values.tolist() for f in out] == [v.tolist() for v in lines]
