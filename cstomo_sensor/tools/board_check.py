"""``cstomo board-check``: identify a board and report its frame rate, sequence gaps and noise from
``--seconds`` of frames (docs/firmware.md, *Build, flash, check*).

It opens the port with the node's driver (binary mode: IDENTIFY and START; text mode: it listens),
counts what the driver counts, and takes the noise as the spread of consecutive frames' differences
(a held or unloaded sensor: the differences are noise alone). Exit status 0 when frames came without
loss, 1 when some were lost or none came, 2 on a bad argument.
"""
from __future__ import annotations

import argparse
import math
import sys
import time

import numpy as np

from ..board.driver import BoardDriver
from ..board.wire import N_VALUES, PROTOCOL_VERSION
from ..errors import CstomoError
from .common import ToolParser, add_setting_arg


def parser() -> argparse.ArgumentParser:
    """This command's argument parser (cli.subcommand_parser)."""
    p = ToolParser(prog="cstomo board-check",
                                description="Identify a board; report its rate, sequence gaps and noise.")
    add_setting_arg(p, "port", note="e.g. /dev/ttyACM0, a pseudo-terminal /dev/pts/N, or a pyserial URL")
    add_setting_arg(p, "protocol")
    add_setting_arg(p, "baudrate")
    p.add_argument("--rate", type=float, default=None, help="frames per second to ask for (default: the board's)")
    p.add_argument("--seconds", type=float, default=10.0, help="seconds of frames to judge (default %(default)g)")
    return p


def main(argv: list[str] | None = None) -> int:
    a = parser().parse_args(argv)
    if not 0 < a.seconds < math.inf:
        print(f"cstomo board-check: error: --seconds {a.seconds:g}: expected a positive number of seconds", file=sys.stderr)
        return 2
    try:
        driver = BoardDriver(a.port, protocol=a.protocol, baudrate=a.baudrate, rate_hz=a.rate, queue_size=1 << 16)
    except CstomoError as err:
        print(f"cstomo board-check: error: {err}", file=sys.stderr)
        return 2
    frames = []
    try:
        deadline = time.monotonic() + 5.0  # the board answers IDENTIFY, or (text) its first line comes
        while time.monotonic() < deadline and not frames:
            f = driver.get(0.1)
            if f is not None:
                frames.append(f)
        end = time.monotonic() + a.seconds
        while frames and time.monotonic() < end:
            f = driver.get(0.1)
            if f is not None:
                frames.append(f)
        st = driver.stats()
        identity = driver.identity
    finally:
        driver.close()
    print(report(identity, st, frames, a))
    return 0 if frames and st.seq_gaps + st.corrupt == 0 else 1


def report(identity, st, frames, a) -> str:
    lines = []
    if identity is not None:
        ok = (identity.protocol_version, identity.n_values) == (PROTOCOL_VERSION, N_VALUES)
        lines.append(f"board: {identity.firmware!r}, protocol {identity.protocol_version}, "
                     f"{identity.n_electrodes} electrodes, {identity.n_values} values per frame"
                     f"{'' if ok else ' (NOT what this host reads: protocol 1, 208 values)'}")
    elif a.protocol == "binary":
        lines.append("board: no IDENTITY answer")
    else:
        lines.append("board: text mode (no identity)")
    if not frames:
        lines.append(f"frames: none in 5 s on {a.port} ({st.last_error or 'no bytes'})")
        return "\n".join(lines)
    seqs = [f.seq for f in frames if f.seq is not None]
    if len(seqs) >= 2 and frames[0].board_time_us is not None:
        span = (frames[-1].board_time_us - frames[0].board_time_us) * 1e-6
        rate = (seqs[-1] - seqs[0]) / span if span > 0 else float("nan")
        lines.append(f"rate: {rate:.2f} frames/s on the board's clock ({len(frames)} frames, seq {seqs[0]}..{seqs[-1]})")
    else:
        lines.append(f"rate: {1.0 / st.period:.2f} frames/s on arrival ({len(frames)} frames)")
    lost = st.seq_gaps + st.corrupt
    lines.append(f"lost: {lost} ({st.seq_gaps} sequence gaps, {st.corrupt} corrupt), {st.duplicates} duplicates, "
                 f"{st.reordered} reordered, {st.resyncs} resyncs, {st.reconnects} reconnects")
    v = np.array([f.values for f in frames])
    if len(v) >= 3:
        noise = np.std(np.diff(v, axis=0), axis=0, ddof=1) / np.sqrt(2.0)  # per channel, volts rms
        rms = float(np.sqrt(np.mean(v.mean(axis=0) ** 2)))
        snr = 20 * np.log10(rms / float(np.sqrt(np.mean(noise ** 2)))) if noise.any() else float("inf")
        lines.append(f"noise: median {np.median(noise) * 1e6:.2f} uV rms per channel (max {noise.max() * 1e6:.2f} uV), "
                     f"signal {rms * 1e3:.2f} mV rms: {snr:.1f} dB")
    sat = sum(bool(f.saturated.any()) for f in frames)
    bad_contact = sorted({e for f in frames for e in np.flatnonzero(~f.contact_ok)})
    lines.append(f"flags: {sat} frames with a saturated value; contact check failed on electrodes "
                 f"{[e + 1 for e in bad_contact] if bad_contact else 'none'}")
    return "\n".join(lines)
