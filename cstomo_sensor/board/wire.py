"""The board's wire protocol (docs/protocol.md): pure encoding and decoding, no port, no threads.

Binary mode: every packet is ``0x00, COBS(header | payload | crc32), 0x00`` with a little-endian
header ``u8 version, u8 type, u16 payload length`` and CRC-32 (zlib) over header and payload.
Text mode: one line of 208 comma-separated voltages per frame.

Decoders are fed bytes in any chunking, never raise, and count what they drop in a stats object.
"""
from __future__ import annotations

import math
import struct
import zlib
from dataclasses import dataclass, field
from enum import IntEnum
from typing import ClassVar

import numpy as np

from ..errors import FrameError
from ..model.geometry import DRIVE_CURRENT_A, N_ELECTRODES

PROTOCOL_VERSION = 1
N_VALUES = 208

_HEADER = struct.Struct("<BBH")  # version, type, payload length
_CRC = struct.Struct("<I")
_DATA_HEAD = struct.Struct("<IQH")  # seq, board time (us), contact mask
_SAT_BYTES = (N_VALUES + 7) // 8  # 26
_DATA_LEN = _DATA_HEAD.size + _SAT_BYTES + 4 * N_VALUES  # 872
_NO_SAT = bytes(_SAT_BYTES)  # the saturation bits of a frame without any
_ALL_CONTACTS = (1 << N_ELECTRODES) - 1
_CONTACT_BITS = 1 << np.arange(N_ELECTRODES)
#: The flags of a frame without any, shared by the decoded frames (read-only): no arrays per frame.
NO_SATURATION = np.zeros(N_VALUES, bool)
ALL_CONTACTS_OK = np.ones(N_ELECTRODES, bool)
NO_SATURATION.flags.writeable = ALL_CONTACTS_OK.flags.writeable = False
#: Bytes of one DATA frame on the wire at most: delimiters, COBS overhead (one code byte per 254 bytes
#: without a zero) and the 880-byte packet; 883..886 in practice (docs/protocol.md, section 1.9).
DATA_WIRE_BYTES = 2 + (_HEADER.size + _DATA_LEN + _CRC.size) + -(-(_HEADER.size + _DATA_LEN + _CRC.size) // 254)
#: Line bits per byte of an 8N1 serial link (start, 8 data, stop).
BITS_PER_BYTE = 10
MAX_PACKET = 1024  # decoded packet (header + payload + crc) bound
MAX_ENCODED = MAX_PACKET + MAX_PACKET // 254 + 2  # COBS worst case
MAX_TEXT_LINE = 16 * 1024


class MsgType(IntEnum):
    """Packet type byte. Host to board below 0x80, board to host from 0x80."""

    IDENTIFY = 0x01
    START = 0x02
    STOP = 0x03
    SET_CURRENT = 0x04
    SET_PATTERN = 0x05
    IDENTITY = 0x81
    ACK = 0x82
    ERROR = 0x83
    DATA = 0x90


class ErrorCode(IntEnum):
    """Error codes a board sends in an :class:`Error` packet."""

    UNKNOWN_COMMAND = 1
    BAD_ARGUMENT = 2
    NOT_SUPPORTED = 3
    BAD_VERSION = 4


def crc32(data: bytes) -> int:
    """CRC-32 (zlib, IEEE 802.3: poly 0x04C11DB7 reflected, init and xorout 0xFFFFFFFF).

    ``crc32(b"123456789") == 0xCBF43926``.
    """
    return zlib.crc32(data) & 0xFFFFFFFF


def cobs_encode(data: bytes) -> bytes:
    """Consistent Overhead Byte Stuffing: the result holds no 0x00 byte."""
    out = bytearray()
    for seg in bytes(data).split(b"\0"):
        while len(seg) >= 254:
            out += b"\xff" + seg[:254]
            seg = seg[254:]
        out.append(len(seg) + 1)
        out += seg
    return bytes(out)


def cobs_decode(data: bytes) -> bytes | None:
    """Invert :func:`cobs_encode`; ``None`` for input that no encoder could have produced.

    In place on a copy: each code byte becomes the zero it stands for (a block of 254 non-zero bytes,
    code 0xFF, stands for none: its code byte is cut out afterwards), so a frame costs one copy and a
    step per zero byte, not a slice per block."""
    out = bytearray(data)
    n = len(out)
    cut = []  # code bytes that stand for no zero (after a 0xFF block)
    i, code = 0, 0xFF
    while i < n:
        c = out[i]
        if c == 0 or i + c > n:
            return None
        if i:
            if code < 0xFF:
                out[i] = 0
            else:
                cut.append(i)
        code = c
        i += c
    for k in reversed(cut):
        del out[k]
    del out[0]
    return bytes(out)


# --- messages ---------------------------------------------------------------------------------


@dataclass(frozen=True)
class Identify:
    """Host asks the board who it is; the board answers :class:`Identity`."""

    TYPE: ClassVar[MsgType] = MsgType.IDENTIFY

    def payload(self) -> bytes:
        return b""


@dataclass(frozen=True)
class Start:
    """Host starts streaming at ``rate_hz`` frames per second (0: the board's default rate)."""

    rate_hz: float = 0.0
    TYPE: ClassVar[MsgType] = MsgType.START

    def payload(self) -> bytes:
        return struct.pack("<f", self.rate_hz)


@dataclass(frozen=True)
class Stop:
    """Host stops streaming."""

    TYPE: ClassVar[MsgType] = MsgType.STOP

    def payload(self) -> bytes:
        return b""


@dataclass(frozen=True)
class SetCurrent:
    """Host sets the drive current in amperes (the reference board drives 0.008 A)."""

    amps: float = DRIVE_CURRENT_A
    TYPE: ClassVar[MsgType] = MsgType.SET_CURRENT

    def payload(self) -> bytes:
        return struct.pack("<f", self.amps)


@dataclass(frozen=True)
class SetPattern:
    """Host selects the pair list: ``layers`` 1 (one ring of 16) or 2 (two rings of 8)."""

    layers: int = 2
    TYPE: ClassVar[MsgType] = MsgType.SET_PATTERN

    def payload(self) -> bytes:
        return struct.pack("<B", self.layers)


@dataclass(frozen=True)
class Identity:
    """Board's answer to :class:`Identify`."""

    firmware: str
    n_electrodes: int = N_ELECTRODES
    protocol_version: int = PROTOCOL_VERSION
    n_values: int = N_VALUES
    TYPE: ClassVar[MsgType] = MsgType.IDENTITY

    def payload(self) -> bytes:
        fw = self.firmware.encode("utf-8")[:64]
        return struct.pack("<HBH", self.protocol_version, self.n_electrodes, self.n_values) + fw


@dataclass(frozen=True)
class Ack:
    """Board accepted the command whose type byte is ``command``."""

    command: int
    TYPE: ClassVar[MsgType] = MsgType.ACK

    def payload(self) -> bytes:
        return struct.pack("<B", self.command)


@dataclass(frozen=True)
class Error:
    """Board refused command ``command`` (0: not tied to a command) with an :class:`ErrorCode`."""

    command: int
    code: int
    text: str = ""
    TYPE: ClassVar[MsgType] = MsgType.ERROR

    def payload(self) -> bytes:
        return struct.pack("<BB", self.command, self.code) + self.text.encode("utf-8")[:200]


@dataclass(frozen=True, eq=False)
class DataFrame:
    """One frame of 208 voltages.

    Parameters
    ----------
    seq : int or None
        Board's frame counter (u32, wraps); None in text mode.
    board_time_us : int or None
        Board's monotonic clock at the measurement, microseconds; None in text mode.
    values : (208,) float64 ndarray
        Volts, in the order of docs/physics.md#measurement-order (float32 on the binary wire).
    saturated : (208,) bool ndarray
        True where the board's voltage channel saturated for that value.
    contact_ok : (16,) bool ndarray
        True where the electrode's contact check passed (0-based electrode index).
    """

    seq: int | None
    board_time_us: int | None
    values: np.ndarray
    saturated: np.ndarray = field(default_factory=lambda: np.zeros(N_VALUES, bool))
    contact_ok: np.ndarray = field(default_factory=lambda: np.ones(N_ELECTRODES, bool))
    TYPE: ClassVar[MsgType] = MsgType.DATA

    def __post_init__(self) -> None:
        for name, shape in (("values", (N_VALUES,)), ("saturated", (N_VALUES,)), ("contact_ok", (N_ELECTRODES,))):
            a = getattr(self, name)
            if (a.shape if isinstance(a, np.ndarray) else np.shape(a)) != shape:
                raise FrameError(f"DataFrame.{name}.shape={np.shape(a)}, expected {shape}")

    def payload(self) -> bytes:
        contact = int(np.packbits(np.asarray(self.contact_ok, bool), bitorder="little").view("<u2")[0])
        sat = np.packbits(np.asarray(self.saturated, bool), bitorder="little").tobytes()
        head = _DATA_HEAD.pack((self.seq or 0) & 0xFFFFFFFF, (self.board_time_us or 0) & (2**64 - 1), contact)
        return head + sat + np.asarray(self.values, "<f4").tobytes()


Message = Identify | Start | Stop | SetCurrent | SetPattern | Identity | Ack | Error | DataFrame


def encode(msg: Message) -> bytes:
    """Bytes on the wire for one message: ``0x00 COBS(header payload crc32) 0x00``."""
    body = msg.payload()
    packet = _HEADER.pack(PROTOCOL_VERSION, int(msg.TYPE), len(body)) + body
    return b"\0" + cobs_encode(packet + _CRC.pack(crc32(packet))) + b"\0"


def link_frame_rate(baudrate: float) -> float:
    """Binary DATA frames per second that an 8N1 serial link at ``baudrate`` carries at most
    (``baudrate / (10 * DATA_WIRE_BYTES)``: 104 at 921600). USB CDC and ptys ignore the baud rate."""
    return baudrate / (BITS_PER_BYTE * DATA_WIRE_BYTES)


def encode_text(values: np.ndarray) -> bytes:
    """One text-mode line: 208 comma-separated volts (shortest round-trip repr), ``\\n``-terminated."""
    return (",".join(repr(float(v)) for v in values) + "\n").encode("ascii")


def _parse(kind: MsgType, p: bytes) -> Message | None:
    """Payload to message; None when the payload length does not fit the type."""
    n = len(p)
    if kind is MsgType.DATA:
        if n != _DATA_LEN:
            return None
        return _data_frame(p, 0)
    if kind in (MsgType.IDENTIFY, MsgType.STOP):
        return (Identify() if kind is MsgType.IDENTIFY else Stop()) if n == 0 else None
    if kind in (MsgType.START, MsgType.SET_CURRENT):
        if n != 4:
            return None
        (x,) = struct.unpack("<f", p)
        return Start(x) if kind is MsgType.START else SetCurrent(x)
    if kind in (MsgType.SET_PATTERN, MsgType.ACK):
        if n != 1:
            return None
        return SetPattern(p[0]) if kind is MsgType.SET_PATTERN else Ack(p[0])
    if kind is MsgType.IDENTITY:
        if n < 5:
            return None
        ver, n_el, n_val = struct.unpack_from("<HBH", p)
        return Identity(p[5:].decode("utf-8", "replace"), n_el, ver, n_val)
    if kind is MsgType.ERROR:
        if n < 2:
            return None
        return Error(p[0], p[1], p[2:].decode("utf-8", "replace"))
    return None


def _data_frame(p: bytes, at: int) -> DataFrame:
    """The :class:`DataFrame` of the DATA payload at ``p[at:]`` (its length checked): built without
    :meth:`DataFrame.__post_init__`'s checks (its arrays have their shapes by construction); a frame
    without flags shares :data:`NO_SATURATION` and :data:`ALL_CONTACTS_OK`."""
    seq, t_us, contact = _DATA_HEAD.unpack_from(p, at)
    sat = p[at + _DATA_HEAD.size:at + _DATA_HEAD.size + _SAT_BYTES]
    f = object.__new__(DataFrame)  # a frozen dataclass: its fields set as __init__ would set them
    f.__dict__.update(
        seq=seq,
        board_time_us=t_us,
        values=np.frombuffer(p, "<f4", N_VALUES, at + _DATA_HEAD.size + _SAT_BYTES).astype(np.float64),
        saturated=NO_SATURATION if sat == _NO_SAT else
        np.unpackbits(np.frombuffer(sat, np.uint8), count=N_VALUES, bitorder="little").view(bool),
        contact_ok=ALL_CONTACTS_OK if contact == _ALL_CONTACTS else (contact & _CONTACT_BITS) != 0)
    return f


# --- decoders ---------------------------------------------------------------------------------


@dataclass
class DecoderStats:
    """Running counts of a decoder (mutable; copy it for a snapshot).

    ``corrupt`` is the sum of every reason a frame was dropped.
    """

    bytes: int = 0
    messages: int = 0
    crc_errors: int = 0
    bad_length: int = 0
    unknown_type: int = 0
    bad_version: int = 0
    bad_values: int = 0

    @property
    def corrupt(self) -> int:
        return self.crc_errors + self.bad_length + self.unknown_type + self.bad_version + self.bad_values


class _Splitter:
    """Shared buffering: split the byte stream at ``DELIM``, drop a piece longer than ``MAX_PIECE``."""

    DELIM: ClassVar[bytes]
    MAX_PIECE: ClassVar[int]

    def __init__(self) -> None:
        self.stats = DecoderStats()
        self._buf = bytearray()

    def reset(self) -> None:
        """Forget a partial frame (after a reconnect); the counts stay."""
        self._buf.clear()

    def feed(self, data: bytes, marks: bool = False) -> list:
        """Add bytes; return the messages completed by them, in order. Never raises. With ``marks``
        a dropped piece appears as None in its place (the driver attributes losses to frames)."""
        self.stats.bytes += len(data)
        self._buf += data
        *pieces, rest = self._buf.split(self.DELIM)
        self._buf = bytearray(rest)
        out = []
        for p in pieces:
            if p:
                m = self._decode(p)
                if m is not _SKIPPED and (m is not None or marks):
                    out.append(m)
        if len(self._buf) > self.MAX_PIECE:  # no delimiter for too long: drop it
            self._buf.clear()
            self.stats.bad_length += 1
            if marks:
                out.append(None)
        return out

    def _decode(self, piece: bytearray):
        """The message of one piece; None for a piece dropped (and counted), :data:`_SKIPPED` for one
        that carries nothing (a comment line)."""
        raise NotImplementedError


_SKIPPED = object()  # a piece that is neither a message nor a loss
#: A decoded DATA packet starts with this header (version, type, payload length), and is this long.
_DATA_PACKET_HEADER = _HEADER.pack(PROTOCOL_VERSION, MsgType.DATA, _DATA_LEN)
_DATA_PACKET = _HEADER.size + _DATA_LEN + _CRC.size


class Decoder(_Splitter):
    """Binary-mode decoder: feed bytes in any chunking, get the complete valid messages.

    Frames are split at every 0x00; empty frames are ignored. A frame is dropped and counted when
    its COBS coding or length is wrong (``bad_length``), its CRC-32 fails (``crc_errors``), its
    version is not :data:`PROTOCOL_VERSION` (``bad_version``), its type is unknown
    (``unknown_type``), or a data frame holds a non-finite value (``bad_values``).
    """

    DELIM = b"\0"
    MAX_PIECE = MAX_ENCODED

    def _decode(self, frame: bytearray) -> Message | None:
        st = self.stats
        packet = cobs_decode(frame)
        if packet is not None and len(packet) == _DATA_PACKET and packet.startswith(_DATA_PACKET_HEADER):
            # the common case, per frame: a DATA packet (the same checks as below, in the same order)
            if zlib.crc32(packet[:-4]) != _CRC.unpack_from(packet, _DATA_PACKET - 4)[0]:
                st.crc_errors += 1
                return None
            msg = _data_frame(packet, _HEADER.size)
            if not math.isfinite(msg.values.dot(msg.values)):  # float32 volts: no overflow
                st.bad_values += 1
                return None
            st.messages += 1
            return msg
        if packet is None or not _HEADER.size + _CRC.size <= len(packet) <= MAX_PACKET:
            st.bad_length += 1
            return None
        body, (crc,) = packet[:-4], _CRC.unpack(packet[-4:])
        if crc32(body) != crc:
            st.crc_errors += 1
            return None
        version, kind, length = _HEADER.unpack_from(body)
        if version != PROTOCOL_VERSION:
            st.bad_version += 1
            return None
        if kind not in MsgType._value2member_map_:
            st.unknown_type += 1
            return None
        msg = _parse(MsgType(kind), body[_HEADER.size :]) if length == len(body) - _HEADER.size else None
        if msg is None:
            st.bad_length += 1
            return None
        if isinstance(msg, DataFrame) and not math.isfinite(msg.values.dot(msg.values)):  # float32 volts: no overflow
            st.bad_values += 1
            return None
        st.messages += 1
        return msg


class TextDecoder(_Splitter):
    """Text-mode decoder: one frame per ``\\n``-terminated line of 208 comma-separated volts.

    Blank lines and lines starting with ``#`` are skipped; a line with the wrong count
    (``bad_length``, also for a line longer than :data:`MAX_TEXT_LINE`), an unparsable or a
    non-finite value (``bad_values``) is dropped and counted. Never raises.
    """

    DELIM = b"\n"
    MAX_PIECE = MAX_TEXT_LINE

    def _decode(self, raw: bytearray) -> DataFrame | None:
        line = raw.strip()
        if not line or line.startswith(b"#"):
            return _SKIPPED
        if line.count(b",") != N_VALUES - 1:
            self.stats.bad_length += 1
            return None
        try:
            values = np.array([float(t) for t in line.split(b",")])
        except ValueError:
            self.stats.bad_values += 1
            return None
        if not np.isfinite(values).all():
            self.stats.bad_values += 1
            return None
        self.stats.messages += 1
        return DataFrame(None, None, values)
