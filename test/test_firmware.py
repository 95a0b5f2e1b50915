"""The board's reference firmware (firmware/, issue 37), host build: built here with cc, served on a real
pseudo-terminal, read by the real BoardDriver. Its protocol constants against board/wire.py, the
worked examples of docs/protocol.md byte for byte, every command and error code, both measurement
orders, text mode, the faults, sequence numbers with zero gaps at 100 and 1000 frames/s."""
from __future__ import annotations

import os
import re
import select
import struct
import time

import numpy as np
import pytest
from firmware_harness import FIRMWARE, ROOT, Process, build_host, write_frames

from cstomo_sensor.board import wire
from cstomo_sensor.board.driver import BoardDriver
from cstomo_sensor.board.wire import (
    Ack,
    DataFrame,
    Decoder,
    Error,
    ErrorCode,
    Identify,
    Identity,
    MsgType,
    SetCurrent,
    SetPattern,
    Start,
    Stop,
    encode,
)
from cstomo_sensor.model.pattern import MeasurementPattern

# --- the constants ----------------------------------------------------------------------------

def header_constants() -> dict[str, float]:
    text = (FIRMWARE / "core" / "cstomo_protocol.h").read_text()
    out = {}
    for name, value in re.findall(r"^#define (CSTOMO_\w+) ([^\s/]+)", text, re.M):
        out[name[len("CSTOMO_"):]] = float(value.rstrip("f")) if "." in value else int(value, 0)
    return out


def test_the_c_headers_constants_are_wire_pys():
    c = header_constants()
    for t in MsgType:
        assert c.pop(f"MSG_{t.name}") == t.value, t.name
    for e in ErrorCode:
        assert c.pop(f"ERR_{e.name}") == e.value, e.name
    expected = {
        "PROTOCOL_VERSION": wire.PROTOCOL_VERSION, "N_ELECTRODES": wire.N_ELECTRODES, "N_VALUES": wire.N_VALUES,
        "HEADER_LEN": wire._HEADER.size, "CRC_LEN": wire._CRC.size, "MAX_PACKET": wire.MAX_PACKET,
        "MAX_ENCODED": wire.MAX_ENCODED, "SAT_BYTES": wire._SAT_BYTES, "DATA_HEAD_LEN": wire._DATA_HEAD.size,
        "DATA_LEN": wire._DATA_LEN, "DATA_PACKET": wire._DATA_PACKET, "DATA_WIRE_BYTES": wire.DATA_WIRE_BYTES,
        "BITS_PER_BYTE": wire.BITS_PER_BYTE, "IDENTITY_HEAD_LEN": struct.calcsize("<HBH"),
        "MAX_FIRMWARE_TEXT": 64, "MAX_ERROR_TEXT": 200,  # wire.Identity / wire.Error cut their text there
        "N_PAIRS": wire.N_ELECTRODES, "N_MEASURE": wire.N_VALUES // wire.N_ELECTRODES,
        "PATTERN_ONE_RING": 1, "PATTERN_TWO_RINGS": 2,
    }
    for name, value in expected.items():
        assert c.pop(name) == value, name
    assert c.pop("DRIVE_CURRENT_A") == pytest.approx(wire.DRIVE_CURRENT_A, rel=1e-7)
    assert not c, f"constants of the header this test does not check: {sorted(c)}"


# --- the host build ---------------------------------------------------------------------------

@pytest.fixture(scope="module")
def fw(tmp_path_factory):
    return build_host(tmp_path_factory.mktemp("fw"))


@pytest.fixture(scope="module")
def rows(tmp_path_factory):
    """Five distinct frames (volts, two-ring order) and their file."""
    path = write_frames(tmp_path_factory.mktemp("frames") / "frames.csv", np.random.default_rng(37).normal(0.0, 0.1, (5, 208)))
    return np.loadtxt(path, delimiter=","), path  # as written (%.9e): the firmware rounds these to float32


def doc_examples() -> dict[str, bytes]:
    """The wire bytes of docs/protocol.md section 1.8, read from the document."""
    text = (ROOT / "docs" / "protocol.md").read_text()
    block = text.split("### 1.8 Worked examples")[1].split("```")[1]
    out = {}
    for line in block.splitlines()[2:]:
        if line.strip():
            name, rest = re.split(r"\s{2,}", line.strip(), maxsplit=1)
            out[name] = bytes.fromhex(re.split(r"\s{3,}", rest)[-1])  # the "on the wire" column
    return out


@pytest.mark.slow  # starts a process
def test_the_worked_examples_come_out_byte_for_byte(fw):
    import subprocess

    out = subprocess.run([str(fw), "--selftest"], capture_output=True, text=True, check=True).stdout
    ex = doc_examples()
    assert set(ex) == {"IDENTIFY", "START 200 Hz", "ACK of START"}
    lines = dict((k, bytes.fromhex(line[len(k):])) for k in ex for line in out.splitlines() if line.startswith(k + " "))
    assert lines == ex
    assert "crc32 123456789 cbf43926" in out  # docs/protocol.md 1.4
    assert "cobs 00 01 01" in out and "cobs 11 22 00 33 03 11 22 02 33" in out  # 1.2
    assert "round trip ok" in out and "603 encoded" in out  # 600 bytes: two 0xFF blocks and a rest


class Link:
    """The host's end of the firmware's pty, raw: send packets, collect what comes back."""

    def __init__(self, device: str) -> None:
        import tty

        self.fd = os.open(device, os.O_RDWR | os.O_NOCTTY)
        tty.setraw(self.fd)
        self.dec = Decoder()

    def send(self, data: bytes) -> None:
        os.write(self.fd, data)

    def read(self, wait: float = 0.3, until=None) -> list:
        out, deadline = [], time.monotonic() + wait
        while time.monotonic() < deadline:
            if select.select([self.fd], [], [], 0.02)[0]:
                out += self.dec.feed(os.read(self.fd, 65536))
                if until is not None and any(until(m) for m in out):
                    break
        return out

    def answers(self, data: bytes, wait: float = 0.5) -> list:
        self.send(data)
        return [m for m in self.read(wait, until=lambda m: not isinstance(m, DataFrame)) if not isinstance(m, DataFrame)]

    def close(self) -> None:
        os.close(self.fd)


def packet(version: int, kind: int, payload: bytes, length: int | None = None, crc_ok: bool = True) -> bytes:
    body = struct.pack("<BBH", version, kind, len(payload) if length is None else length) + payload
    crc = wire.crc32(body) ^ (0 if crc_ok else 1)
    return b"\0" + wire.cobs_encode(body + struct.pack("<I", crc)) + b"\0"


@pytest.mark.slow  # starts the firmware as a process
def test_every_command_and_error_code_is_answered_as_documented(fw, rows):
    with Process([str(fw), "--frames", str(rows[1]), "--patterns", "2"]) as board:
        link = Link(board.device)
        try:
            idn = link.answers(encode(Identify()))
            assert idn == [Identity("cstomo-fw 1.0 (host)", 16, 1, 208)]
            assert link.answers(encode(SetCurrent(0.008))) == [Ack(MsgType.SET_CURRENT)]
            assert link.answers(encode(SetPattern(2))) == [Ack(MsgType.SET_PATTERN)]
            for bad in (encode(Start(-1.0)), encode(Start(float("nan"))), encode(Start(2e4)),
                        encode(SetCurrent(0.0)), encode(SetCurrent(0.5)), encode(SetPattern(3)),
                        packet(1, MsgType.START, b"\0\0"), packet(1, MsgType.IDENTIFY, b"x"),
                        packet(1, MsgType.START, struct.pack("<f", 10.0), length=3)):
                (ans,) = link.answers(bad)
                assert isinstance(ans, Error) and ans.code == ErrorCode.BAD_ARGUMENT and ans.text, (bad.hex(), ans)
            (ans,) = link.answers(encode(SetPattern(1)))  # this board (--patterns 2) has two rings only
            assert (ans.command, ans.code) == (MsgType.SET_PATTERN, ErrorCode.NOT_SUPPORTED), ans
            for kind in (0x07, 0x00, 0x7F, MsgType.ACK, MsgType.DATA):  # not commands (board-to-host types too)
                (ans,) = link.answers(packet(1, kind, b""))
                assert (ans.command, ans.code) == (kind, ErrorCode.UNKNOWN_COMMAND), ans
            (ans,) = link.answers(packet(2, MsgType.IDENTIFY, b""))
            assert (ans.command, ans.code) == (MsgType.IDENTIFY, ErrorCode.BAD_VERSION), ans
            assert link.answers(packet(1, MsgType.IDENTIFY, b"", crc_ok=False)) == []  # bad CRC: ignored
            assert link.answers(b"\0\x05\x01\x02\0") == []  # bad COBS / too short: ignored
            assert link.answers(encode(Start(50.0))) == [Ack(MsgType.START)]
            frames = [m for m in link.read(0.5) if isinstance(m, DataFrame)]
            assert len(frames) >= 15 and [f.seq for f in frames] == list(range(frames[0].seq, frames[0].seq + len(frames)))
            assert link.answers(encode(Stop())) == [Ack(MsgType.STOP)]
            link.read(0.2)  # frames in flight
            assert [m for m in link.read(0.3) if isinstance(m, DataFrame)] == []  # idle after STOP
        finally:
            link.close()


@pytest.mark.slow  # starts the firmware as a process
def test_both_patterns_measure_in_docs_physics_order(fw, rows):
    """After SET_PATTERN 1 the values come in the one-ring order: the front-end answers each value by its
    electrodes from the file (two-ring order), so value i of a one-ring frame is the file's value of the
    same drive and measure electrodes, 0 where the two-ring order has no such pair (noise off)."""
    r, path = rows
    two, one = MeasurementPattern(16, 2), MeasurementPattern(16, 1)
    by_electrodes = {(*d, *m): i for i, (d, m) in enumerate(zip(two.drive.tolist(), two.measure.tolist()))}
    with Process([str(fw), "--frames", str(path)]) as board:
        link = Link(board.device)
        try:
            for layers, order in ((2, two), (1, one), (2, two)):
                assert link.answers(encode(SetPattern(layers))) == [Ack(MsgType.SET_PATTERN)]
                link.answers(encode(Start(100.0)))
                frames = [m for m in link.read(0.5) if isinstance(m, DataFrame)]
                link.answers(encode(Stop()))
                link.read(0.1)
                assert len(frames) >= 10
                for f in frames[1:]:  # each frame plays one row of the file, in turn
                    row = next(k for k in range(5) if np.isclose(f.values[0], np.float32(r[k, 0])) or layers == 1)
                    cols = [by_electrodes.get((*d, *m)) for d, m in zip(order.drive.tolist(), order.measure.tolist())]
                    if layers == 1:  # find the row by a value both orders share
                        shared = next(i for i, c in enumerate(cols) if c is not None)
                        row = next(k for k in range(5) if np.float32(r[k, cols[shared]]) == f.values[shared])
                    want = np.array([0.0 if c is None else np.float32(r[row, c]) for c in cols])
                    np.testing.assert_array_equal(f.values, want)
                if layers == 1:
                    assert sum(c is None for c in cols) > 0  # the orders differ: the test can tell them apart
        finally:
            link.close()


def read_driver(device: str, rate: float, seconds: float, protocol: str = "binary"):
    driver = BoardDriver(device, protocol=protocol, rate_hz=rate if protocol == "binary" else None, queue_size=1 << 16)
    try:
        deadline = time.monotonic() + 20
        while driver.identity is None and protocol == "binary" and time.monotonic() < deadline:
            time.sleep(0.02)
        frames, end = [], time.monotonic() + seconds
        while time.monotonic() < end:
            f = driver.get(0.05)
            if f is not None:
                frames.append(f)
        return frames, driver.stats(), driver.identity
    finally:
        driver.close()


@pytest.mark.slow  # starts the firmware as a process
@pytest.mark.alone  # judges the board's real time: no neighbour (setup.cfg)
@pytest.mark.parametrize("rate,seconds", [(100.0, 3.0), (1000.0, 1.5)])
def test_the_driver_reads_every_frame_in_order(fw, rows, rate, seconds):
    r, path = rows
    with Process([str(fw), "--frames", str(path)]) as board:
        frames, st, identity = read_driver(board.device, rate, seconds)
        said = board.stop()
    assert identity == Identity("cstomo-fw 1.0 (host)", 16, 1, 208)
    assert len(frames) >= 0.8 * rate * seconds, (len(frames), st)
    assert (st.seq_gaps, st.corrupt, st.duplicates, st.reordered, st.dropped_overflow) == (0, 0, 0, 0, 0), st
    seqs = [f.seq for f in frames]
    assert seqs == list(range(seqs[0], seqs[0] + len(seqs)))
    # frames on absolute times t0 + k / rate: late by the host's scheduling (a loaded host wakes the
    # process milliseconds late), never early, and no drift over the run
    t = np.array([f.board_time_us for f in frames], float) * 1e-6
    late = t - (t[0] + (np.array(seqs) - seqs[0]) / rate)
    late -= late.min()
    assert np.median(late) < 0.02 and np.median(late[-len(late) // 4:]) < 0.02, late
    assert (t[-1] - t[0]) / (seqs[-1] - seqs[0]) == pytest.approx(1.0 / rate, rel=0.01)
    for f in frames:  # row k of the file is measured by the frame of seq k (mod 5): exact in float32
        np.testing.assert_array_equal(f.values, np.float32(r[f.seq % 5]))
        assert not f.saturated.any() and f.contact_ok.all()
    assert "not sent for want of room 0" in said, said


@pytest.mark.slow  # starts the firmware as a process
def test_text_mode_streams_the_frames_from_power_up(fw, rows):
    r, path = rows
    with Process([str(fw), "--frames", str(path), "--protocol", "text", "--rate", "50"]) as board:
        frames, st, _ = read_driver(board.device, 50.0, 1.5, protocol="text")
    assert len(frames) >= 50 and st.corrupt <= 1  # at most the line the driver joined in the middle of
    got = np.array([f.values for f in frames])
    k = next(k for k in range(5) if np.abs(got[0] - np.float32(r[k])).max() < 1e-9)  # the line the driver met first
    want = np.float32(r[(k + np.arange(len(got))) % 5])
    assert np.abs(got - want).max() <= 0.51e-9  # the float32 volts in integer nanovolts on the line


@pytest.mark.slow  # starts the firmware as a process
def test_faults_show_as_the_driver_counts_them(fw, rows):
    """board-sim's faults: frames measured and not sent are sequence gaps (their seq used), flipped bits
    and cut frames are corrupt, a dead electrode clears its contact bit, a saturated channel its flag."""
    r, path = rows
    argv = [str(fw), "--frames", str(path), "--drop", "0.1", "--bit-flip", "0.05", "--truncate", "0.05",
            "--garbage", "0.05", "--dead-electrode", "5", "--saturate-channel", "17", "--seed", "3"]
    with Process(argv) as board:
        frames, st, _ = read_driver(board.device, 200.0, 3.0)
        said = board.stop()
    m = re.search(r"measured (\d+) frames, sent (\d+).*drop (\d+), bit_flip (\d+), truncate (\d+), garbage (\d+)", said)
    measured, sent, drop, flip, trunc, garbage = map(int, m.groups())
    assert drop > 10 and flip > 3 and trunc > 3 and garbage > 3, said
    seqs = [f.seq for f in frames]
    span = seqs[-1] - seqs[0] + 1
    assert st.seq_gaps + st.corrupt == span - len(frames)  # every lost frame counted once, by seq
    assert st.seq_gaps >= 0.6 * drop * span / measured and st.corrupt >= 1, (st, said)
    for f in frames:
        assert f.contact_ok.tolist() == [e != 5 for e in range(16)]
        assert f.saturated.tolist() == [i == 17 for i in range(208)] and abs(f.values[17]) == 2.5
    dead = MeasurementPattern(16, 2).electrode_rows(5)
    f = frames[-1]
    np.testing.assert_array_equal(f.values[~dead & (np.arange(208) != 17)],
                                  np.float32(r[f.seq % 5])[~dead & (np.arange(208) != 17)])
    assert np.abs(f.values[dead]).max() < 0.01  # the open electrode's rows read noise (1 mV)


@pytest.mark.slow  # starts the firmware as a process
def test_board_check_identifies_the_firmware_and_reports_rate_gaps_and_noise(fw, tmp_path, capsys):
    """`cstomo board-check` on the host firmware: a held frame (one row) with 100 uV of noise."""
    from cstomo_sensor.tools.cli import main

    path = write_frames(tmp_path / "held.csv", np.random.default_rng(5).normal(0.0, 0.1, 208))
    with Process([str(fw), "--frames", str(path), "--noise", "1e-4", "--seed", "2"]) as board:
        code = main(["board-check", "--port", board.device, "--rate", "100", "--seconds", "2"])
    out = capsys.readouterr().out
    assert code == 0, out
    assert "'cstomo-fw 1.0 (host)', protocol 1, 16 electrodes, 208 values per frame" in out
    rate = float(re.search(r"rate: ([\d.]+) frames/s on the board's clock", out).group(1))
    assert rate == pytest.approx(100.0, rel=0.01)
    assert "lost: 0 (0 sequence gaps, 0 corrupt)" in out
    noise = float(re.search(r"noise: median ([\d.]+) uV", out).group(1))
    assert noise == pytest.approx(100.0, rel=0.15)  # the front-end's 100 uV rms
    assert "contact check failed on electrodes none" in out
