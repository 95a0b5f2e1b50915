"""A simulated board on a real pseudo-terminal or an in-process virtual link (:mod:`.links`),
speaking docs/protocol.md, with fault injection.

The board answers host commands (binary mode), streams frames from a voltage ``source`` at a fixed
rate (absolute-time schedule, board clock in monotonic microseconds) and can inject the faults of
:class:`FaultConfig`. ``cstomo board-sim`` runs it from the command line (:func:`main`).
"""
from __future__ import annotations

import logging
import os
import select
import threading
import time
from collections import Counter
from dataclasses import dataclass
from typing import Literal, Protocol

import numpy as np

from ..errors import ConfigError
from ..model.pattern import MeasurementPattern
from ..settings import PROTOCOLS
from .links import PtyLink, VirtualLink, open_link
from .wire import (
    DRIVE_CURRENT_A,
    N_ELECTRODES,
    N_VALUES,
    Ack,
    DataFrame,
    Decoder,
    Error,
    ErrorCode,
    Identify,
    Identity,
    SetCurrent,
    SetPattern,
    Start,
    Stop,
    encode,
    encode_text,
)

log = logging.getLogger(__name__)

FIRMWARE = "cstomo-sim 1.0"
#: The simulated board's frame rate when none is given (``cstomo board-sim --rate``, the launch's ``sim:=true``).
DEFAULT_RATE_HZ = 200.0
_RESYNC_S = 0.1  # a board more than this late skips the missed slots instead of bursting


class VoltageSourceLike(Protocol):
    """What the board measures: 208 volts at time t (noise included) and the true force."""

    def frame(self, t: float, rng: np.random.Generator) -> np.ndarray: ...

    def truth(self, t: float) -> np.ndarray: ...


@dataclass(frozen=True)
class FaultConfig:
    """Faults the simulated board injects (all off by default); times are seconds from the start.

    Attributes
    ----------
    bit_flip, drop, truncate, garbage, nan : float
        Probability per frame of: one flipped bit in the sent bytes; a frame measured (its seq
        used) but not sent; a frame cut short; a burst of ``garbage_bytes`` random bytes before
        the frame; one value replaced by NaN.
    stall_at, stall_for : float or None, float
        The board neither sends nor listens during [stall_at, stall_at + stall_for).
    disconnect_at, reappear_after : float or None, float
        The link (pty or virtual) closes at ``disconnect_at`` and a new one appears ``reappear_after`` s
        later (a symlink is re-pointed to it, a virtual name registered again); the board then waits for START again (binary mode).
    saturate_channel : int or None
        Value index (0-based) whose channel saturates: flag set, value clipped to +-``full_scale``.
    dead_electrode : int or None
        Electrode (0-based) with no contact: contact flag false, its rows read noise.
    no_contact_at, no_contact_for : float or None, float
        During [no_contact_at, no_contact_at + no_contact_for) every contact flag is false (a cable
        pulled off the sensor) and the values read noise.
    saturate_all_at, saturate_all_for : float or None, float
        During that window every value is flagged saturated and clipped to +-``full_scale``.
    """

    bit_flip: float = 0.0
    drop: float = 0.0
    truncate: float = 0.0
    garbage: float = 0.0
    garbage_bytes: int = 48
    nan: float = 0.0
    stall_at: float | None = None
    stall_for: float = 0.0
    disconnect_at: float | None = None
    reappear_after: float = 0.5
    saturate_channel: int | None = None
    full_scale: float = 2.5
    dead_electrode: int | None = None
    no_contact_at: float | None = None
    no_contact_for: float = 0.0
    saturate_all_at: float | None = None
    saturate_all_for: float = 0.0

    def __post_init__(self) -> None:
        for name in ("bit_flip", "drop", "truncate", "garbage", "nan"):
            p = getattr(self, name)
            if not 0.0 <= p <= 1.0:
                raise ConfigError(f"FaultConfig.{name}={p!r}: expected a probability in [0, 1]")
        for name in ("stall_for", "reappear_after", "full_scale", "garbage_bytes", "no_contact_for",
                     "saturate_all_for"):
            if getattr(self, name) < 0:
                raise ConfigError(f"FaultConfig.{name}={getattr(self, name)!r}: expected >= 0")
        if self.saturate_channel is not None and not 0 <= self.saturate_channel < N_VALUES:
            raise ConfigError(f"FaultConfig.saturate_channel={self.saturate_channel!r}: expected 0..{N_VALUES - 1}")
        if self.dead_electrode is not None and not 0 <= self.dead_electrode < N_ELECTRODES:
            raise ConfigError(f"FaultConfig.dead_electrode={self.dead_electrode!r}: expected 0..{N_ELECTRODES - 1}")


def _within(t: float, start: float | None, length: float) -> bool:
    return start is not None and start <= t < start + length


@dataclass(frozen=True)
class SimStats:
    """Snapshot of what the simulated board did.

    Attributes
    ----------
    sent : int
        Data frames written whole and unharmed.
    next_seq : int
        Sequence number the next frame will carry (frames measured so far).
    generation_first_seq : tuple of int
        Per link (0: the first, 1: after a disconnect, ...) the seq of the first frame sent on it,
        -1 while none was.
    generation_opened : tuple of float
        Per link, the ``time.monotonic()`` at which it appeared (a replug's "board is back").
    injected : dict
        Count of each injected fault by name (``bit_flip``, ``drop``, ``nan``, ...), and
        ``overrun`` for frames the link had no room for.
    """

    sent: int
    next_seq: int
    generation_first_seq: tuple[int, ...]
    injected: dict
    generation_opened: tuple[float, ...] = ()

    def describe(self) -> list[str]:
        """The summary in words, one line per count (``cstomo board-sim`` prints it at its end)."""
        lines = [f"sent {self.sent} frames whole and unharmed"]
        for name, n in sorted(self.injected.items()):
            lines.append(f"{n} {name}: {INJECTED_MEANING.get(name, 'an injected fault')}")
        return lines


#: What each count of :attr:`SimStats.injected` is, in words.
INJECTED_MEANING = {
    "bit_flip": "frames sent with one bit flipped (injected; the host's CRC check drops them)",
    "drop": "frames measured but not sent (injected; the host sees a gap in seq)",
    "truncate": "frames cut short (injected)",
    "garbage": "bursts of random bytes before a frame (injected)",
    "nan": "frames with one value NaN (injected)",
    "stall": "stalls: neither sending nor listening (injected)",
    "disconnect": "disconnects: the link closed and a new one appeared (injected)",
    "overrun": "frames not written whole: the link was full because nothing read it (a host that "
               "stopped before the board, as `cstomo demo` stops the node first at its end, or stalled); "
               "not an injected fault",
}


class SimulatedBoard:
    """A board on a pseudo-terminal or a virtual link, ready when constructed; :meth:`run` or :meth:`start` it.

    Parameters
    ----------
    source : object with ``frame(t, rng) -> (208,) volts`` and ``truth(t) -> (3,) newtons``
        Voltages at time t of the load script (at 8 mA; scaled by SET_CURRENT), noise included. The
        script's clock starts at the first START (text boards: when the board starts), so a host that
        connects late still sees the whole script.
    protocol : {'binary', 'text'}
        Binary boards wait for START and answer commands; text boards stream at once, deaf.
    rate_hz : float
        Default frame rate (START with rate 0 keeps it).
    duration : float or None
        Seconds of the load script to stream (from its start, see ``source``); None runs until :meth:`stop`.
    link : str or None
        Path of a symlink kept pointing at the current pty (removed while disconnected), or
        ``virtual://NAME``: an in-process link (no pty) the driver opens by that URL (:mod:`.links`).
    faults : FaultConfig
        Faults to inject.
    seed : int
        Seed of the generator handed to ``source.frame`` and used for faults.
    layers : int
        Pair list of the electrodes (1 or 2 rings), for the dead-electrode rows and SET_PATTERN.
    """

    def __init__(
        self,
        source: VoltageSourceLike,
        *,
        protocol: Literal["binary", "text"] = "binary",
        rate_hz: float = DEFAULT_RATE_HZ,
        duration: float | None = None,
        link: str | os.PathLike | None = None,
        faults: FaultConfig = FaultConfig(),
        seed: int = 0,
        layers: int = 2,
    ) -> None:
        if protocol not in PROTOCOLS:
            raise ConfigError(f"{protocol=}: expected one of {PROTOCOLS}")
        if not rate_hz > 0:
            raise ConfigError(f"{rate_hz=}: expected a positive rate in Hz")
        if duration is not None and not duration > 0:
            raise ConfigError(f"{duration=}: expected a positive number of seconds or None")
        self.source = source
        self.protocol = protocol
        self.rate_hz = float(rate_hz)
        self.duration = duration
        self._script_t0: float | None = None  # monotonic time of the load script's t = 0
        self.script_started = threading.Event()  # set when the load script's clock starts
        self.link = os.fspath(link) if link is not None else None
        self.faults = faults
        self.layers = layers
        self._dead_rows = (
            MeasurementPattern(N_ELECTRODES, layers).electrode_rows(faults.dead_electrode)
            if faults.dead_electrode is not None
            else None
        )
        self._rng = np.random.default_rng(seed)
        self._fault_rng = np.random.default_rng([seed, 1])
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._decoder = Decoder()
        self._seq = 0
        self._sent = 0
        self._first_seq: list[int] = []
        self._opened: list[float] = []
        self._injected: Counter[str] = Counter()
        self._current = DRIVE_CURRENT_A
        self._link: PtyLink | VirtualLink | None = None
        self._master = -1
        self._open_link()

    # --- link ----------------------------------------------------------------------------

    def _open_link(self) -> None:
        self._link = open_link(self.link)
        self._master, self._device = self._link.fd, self._link.device
        self._first_seq.append(-1)
        self._streaming = self.protocol == "text"
        self._decoder.reset()
        self._opened.append(time.monotonic())
        log.info("board on %s", self.device)

    def _close_link(self) -> None:
        if self._link is not None:
            self._link.close()
        self._link, self._master = None, -1

    @property
    def device(self) -> str:
        """What a driver opens: the link if given (a symlink's path or ``virtual://NAME``), else the
        current pty slave."""
        return self._device

    # --- control -----------------------------------------------------------------------------

    def start(self) -> SimulatedBoard:
        """Run in a background thread; returns self."""
        self._thread = threading.Thread(target=self.run, name="SimulatedBoard", daemon=True)
        self._thread.start()
        return self

    def join(self, timeout: float | None = None) -> bool:
        """Wait for the :meth:`start` thread to end (duration over or stopped); True if it did."""
        if self._thread is not None:
            self._thread.join(timeout)
            return not self._thread.is_alive()
        return True

    def stop(self) -> None:
        """Ask :meth:`run` to return (from any thread or a signal handler)."""
        self._stop.set()

    def close(self) -> None:
        """Stop, wait for the thread, close the pty (or virtual link) and remove the link; idempotent."""
        self.stop()
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join()
        self._close_link()

    def __enter__(self) -> SimulatedBoard:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def stats(self) -> SimStats:
        return SimStats(self._sent, self._seq, tuple(self._first_seq), dict(self._injected), tuple(self._opened))

    # --- the board's loop --------------------------------------------------------------------

    def run(self) -> None:
        """Stream and answer commands until the duration ends or :meth:`stop` is called."""
        f = self.faults
        t0 = time.monotonic()
        self._t0_ns = time.monotonic_ns()
        self._stream_t0, self._k = t0, 0
        self._script_t0 = None
        if self.protocol == "text":  # binary boards: at the first START
            self._start_script(t0)
        disconnected = stalled = False
        while not self._stop.is_set():
            now = time.monotonic() - t0
            if self.duration is not None and self._script_t0 is not None and \
                    time.monotonic() - self._script_t0 >= self.duration:
                break
            if f.disconnect_at is not None and not disconnected and now >= f.disconnect_at:
                disconnected = True
                self._injected["disconnect"] += 1
                self._close_link()
                if self._stop.wait(f.reappear_after):
                    break
                self._open_link()
                self._resync()
                continue
            if f.stall_at is not None and f.stall_at <= now < f.stall_at + f.stall_for:
                if not stalled:
                    stalled = True
                    self._injected["stall"] += 1
                self._stop.wait(min(0.01, f.stall_at + f.stall_for - now))
                self._resync()
                continue
            due = self._stream_t0 + self._k / self.rate_hz
            wait = due - time.monotonic() if self._streaming else 0.02
            if wait > 0:
                self._serve_commands(min(wait, 0.02))
                continue
            if time.monotonic() - due > _RESYNC_S:
                self._resync()
                continue
            self._emit(due - self._script_t0)
            self._k += 1

    @property
    def script_start(self) -> float | None:
        """``time.monotonic()`` of the load script's t = 0 (None before it started): a frame measured at
        script time t was due at ``script_start + t`` (its ``board_time_us`` is its write time)."""
        return self._script_t0

    def _start_script(self, t0: float) -> None:
        self._script_t0 = t0
        self.script_started.set()

    def _resync(self) -> None:
        """Next frame slot at or after now (missed slots are not measured)."""
        elapsed = time.monotonic() - self._stream_t0
        self._k = max(self._k, int(np.ceil(elapsed * self.rate_hz)))

    def _serve_commands(self, timeout: float) -> None:
        ready, _, _ = select.select([self._master], [], [], timeout)
        if not ready:
            return
        try:
            data = os.read(self._master, 4096)
        except BlockingIOError:
            return
        except OSError as err:  # EIO: no process holds the slave open (not with ours open)
            log.debug("link read: %s", err)
            return
        if self.protocol == "text":
            return
        for msg in self._decoder.feed(data):
            self._write(encode(self._answer(msg)))

    def _answer(self, msg: object):
        kind = int(getattr(msg, "TYPE", 0))
        if isinstance(msg, Identify):
            return Identity(FIRMWARE, N_ELECTRODES)
        if isinstance(msg, Start):
            if not 0 <= msg.rate_hz <= 10_000:
                return Error(kind, ErrorCode.BAD_ARGUMENT, f"rate {msg.rate_hz} Hz not in 0..10000")
            if msg.rate_hz > 0:
                self.rate_hz = float(msg.rate_hz)
            self._streaming = True
            self._stream_t0, self._k = time.monotonic(), 0
            if self._script_t0 is None:
                self._start_script(self._stream_t0)
            return Ack(kind)
        if isinstance(msg, Stop):
            self._streaming = False
            return Ack(kind)
        if isinstance(msg, SetCurrent):
            if not 0 < msg.amps <= 0.05:
                return Error(kind, ErrorCode.BAD_ARGUMENT, f"current {msg.amps} A not in (0, 0.05]")
            self._current = float(msg.amps)
            return Ack(kind)
        if isinstance(msg, SetPattern) and msg.layers == self.layers:
            return Ack(kind)
        if isinstance(msg, SetPattern):
            return Error(kind, ErrorCode.NOT_SUPPORTED, f"pattern {msg.layers} rings; this board has {self.layers}")
        return Error(kind, ErrorCode.UNKNOWN_COMMAND, f"not a command: type 0x{kind:02x}")

    def _write(self, data: bytes, patience: float = 0.05) -> int:
        """Write into the link, waiting up to ``patience`` s for room; returns the bytes written."""
        done, deadline = 0, time.monotonic() + patience
        while done < len(data):
            try:
                done += os.write(self._master, data[done:])
            except BlockingIOError:
                left = deadline - time.monotonic()
                if left <= 0 or not select.select([], [self._master], [], left)[1]:
                    break
            except OSError as err:
                log.debug("link write: %s", err)
                break
        return done

    def _emit(self, t: float) -> None:
        f, rng = self.faults, self._fault_rng
        seq = self._seq
        self._seq += 1
        values = np.asarray(self.source.frame(t, self._rng), float) * (self._current / DRIVE_CURRENT_A)
        saturated = np.zeros(N_VALUES, bool)
        contact = np.ones(N_ELECTRODES, bool)
        if f.saturate_channel is not None:
            i = f.saturate_channel
            saturated[i] = True
            values[i] = f.full_scale if values[i] >= 0 else -f.full_scale
        if self._dead_rows is not None:
            contact[f.dead_electrode] = False
            values[self._dead_rows] = self._rng.normal(0.0, 1e-3, int(self._dead_rows.sum()))
        if _within(t, f.no_contact_at, f.no_contact_for):
            contact[:] = False
            values[:] = self._rng.normal(0.0, 1e-3, N_VALUES)
        if _within(t, f.saturate_all_at, f.saturate_all_for):
            saturated[:] = True
            values[:] = np.where(values >= 0, f.full_scale, -f.full_scale)
        harmed = False
        if rng.random() < f.drop:
            self._injected["drop"] += 1
            return
        if rng.random() < f.nan:
            self._injected["nan"] += 1
            values[rng.integers(N_VALUES)] = np.nan
            harmed = True
        if self.protocol == "binary":
            t_us = (time.monotonic_ns() - self._t0_ns) // 1000
            data = encode(DataFrame(seq, t_us, values, saturated, contact))
        else:
            data = encode_text(values)
        if rng.random() < f.garbage:
            self._injected["garbage"] += 1
            self._write(rng.bytes(f.garbage_bytes))
        if rng.random() < f.truncate:
            self._injected["truncate"] += 1
            data = data[: int(rng.integers(2, len(data) - 2))]
            harmed = True
        if rng.random() < f.bit_flip:
            self._injected["bit_flip"] += 1
            buf = bytearray(data)
            i = int(rng.integers(1, len(buf) - 1))  # inside the frame, not its delimiters
            buf[i] ^= 1 << int(rng.integers(8))
            data = bytes(buf)
            harmed = True
        n = self._write(data)
        if n < len(data):
            self._injected["overrun"] += 1
        elif not harmed:
            self._sent += 1
            if self._first_seq[-1] < 0:
                self._first_seq[-1] = seq
