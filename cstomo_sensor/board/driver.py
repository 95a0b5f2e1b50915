"""Serial driver for the board: a pyserial port opened by URL, a reader thread, a bounded queue.

The reader thread decodes frames (binary or text mode, docs/protocol.md), counts sequence gaps and
corrupt frames, drops the oldest frame when the user falls behind, and reconnects with exponential
backoff when the port disappears or the board stops sending. Nothing raises out of the thread.
"""
from __future__ import annotations

import logging
import threading
import time
from collections import deque
from dataclasses import dataclass
from typing import Literal

import serial

from ..errors import ConfigError
from .wire import PROTOCOLS, DataFrame, Decoder, Error, Identify, Identity, Start, TextDecoder, encode

log = logging.getLogger(__name__)



@dataclass(frozen=True)
class DriverStats:
    """A snapshot of the driver's counters.

    Attributes
    ----------
    connected : bool
        The port is open now.
    frames : int
        Valid data frames decoded (including those later dropped by queue overflow).
    dropped_overflow : int
        Frames dropped (the oldest first) because the queue was full.
    corrupt : int
        Frames dropped by the decoder (CRC, length, type, version, non-finite values).
    seq_gaps : int
        Frames missing by sequence number (binary mode).
    reconnects : int
        Times the port was opened again after losing it (unplugged or stalled).
    last_error : str
        The latest error or board complaint, '' if none since the last data frame (a frame
        clears it: an old "open failed" is not blamed for today's trouble).
    bytes : int
        Bytes read from the port.
    """

    connected: bool
    frames: int
    dropped_overflow: int
    corrupt: int
    seq_gaps: int
    reconnects: int
    last_error: str
    bytes: int


def _set_low_latency(port: serial.SerialBase, url: str) -> None:
    """Best effort: set ASYNC_LOW_LATENCY (TIOCSSERIAL) on a real Linux tty; ignore failure."""
    setter = getattr(port, "set_low_latency_mode", None)  # pyserial's Linux ioctl wrapper
    if setter is None:
        return
    try:
        setter(True)
    except (OSError, ValueError, AttributeError) as err:  # ptys/ports without TIOCGSERIAL
        log.debug("low-latency flag not set on %s: %s", url, err)


class BoardDriver:
    """Reads frames from a board over a serial port in a background thread.

    Parameters
    ----------
    url : str
        Anything :func:`serial.serial_for_url` opens: a device path, ``socket://host:port``,
        ``rfc2217://host:port``, ``loop://``.
    protocol : {'binary', 'text'}
        Wire format (docs/protocol.md). In binary mode the driver sends IDENTIFY and START on
        every (re)connect.
    baudrate : int
        Serial speed (ignored by ptys and sockets).
    queue_size : int
        Frames kept for :meth:`get`; when full, the oldest is dropped and counted.
    read_timeout : float
        Seconds one port read waits; bounds how fast :meth:`close` returns.
    stall_timeout : float
        Seconds without any byte after which the port is closed and reopened.
    reconnect_backoff : (float, float)
        First and largest wait in seconds between reopening attempts (doubling in between).
    rate_hz : float or None
        Rate asked for in START; None asks for the board's default rate.

    Raises
    ------
    ConfigError
        On an unknown protocol or a non-positive size, timeout or rate.
    """

    def __init__(
        self,
        url: str,
        *,
        protocol: Literal["binary", "text"] = "binary",
        baudrate: int = 921600,
        queue_size: int = 64,
        read_timeout: float = 0.05,
        stall_timeout: float = 1.0,
        reconnect_backoff: tuple[float, float] = (0.05, 2.0),
        rate_hz: float | None = None,
    ) -> None:
        if protocol not in PROTOCOLS:
            raise ConfigError(f"{protocol=}: expected one of {PROTOCOLS}")
        for name, value in (("baudrate", baudrate), ("queue_size", queue_size), ("read_timeout", read_timeout),
                            ("stall_timeout", stall_timeout)):
            if not value > 0:
                raise ConfigError(f"{name}={value!r}: expected a positive number")
        if rate_hz is not None and not rate_hz > 0:
            raise ConfigError(f"{rate_hz=}: expected a positive rate in Hz or None (board default)")
        lo, hi = reconnect_backoff
        if not 0 < lo <= hi:
            raise ConfigError(f"{reconnect_backoff=}: expected (first, largest) seconds with 0 < first <= largest")
        self.url = url
        self.protocol = protocol
        self._baudrate = baudrate
        self._read_timeout = read_timeout
        self._stall_timeout = stall_timeout
        self._backoff = (float(lo), float(hi))
        self._rate_hz = rate_hz
        self._decoder = Decoder() if protocol == "binary" else TextDecoder()
        self._queue: deque[DataFrame] = deque(maxlen=queue_size)
        self._cond = threading.Condition()
        self._port_lock = threading.Lock()
        self._port: serial.SerialBase | None = None
        self._closing = threading.Event()
        self._frames = self._dropped = self._gaps = self._reconnects = self._opens = 0
        self._logged_error: str | None = None  # the error last logged (not logged again until it changes)
        self._open_failures = 0  # failed opens since the last successful one
        self._last_seq: int | None = None
        self._last_error = ""
        self.identity: Identity | None = None
        self._thread = threading.Thread(target=self._run, name=f"BoardDriver({url})", daemon=True)
        self._thread.start()

    # --- user side ---------------------------------------------------------------------------

    def get(self, timeout: float) -> DataFrame | None:
        """The oldest queued frame, waiting up to ``timeout`` seconds; None if none came."""
        with self._cond:
            if not self._queue:
                self._cond.wait_for(lambda: self._queue or self._closing.is_set(), timeout)
            return self._queue.popleft() if self._queue else None

    def send(self, data: bytes) -> bool:
        """Write raw bytes (e.g. :func:`.wire.encode` of a command); False if not connected or failed."""
        with self._port_lock:
            if self._port is None:
                return False
            try:
                self._port.write(data)
                return True
            except (serial.SerialException, OSError) as err:
                self._last_error = f"write failed: {err}"
                log.warning("%s: %s", self.url, self._last_error)
                return False

    def stats(self) -> DriverStats:
        """A consistent snapshot of the counters."""
        with self._cond:
            return DriverStats(
                connected=self._port is not None,
                frames=self._frames,
                dropped_overflow=self._dropped,
                corrupt=self._decoder.stats.corrupt,
                seq_gaps=self._gaps,
                reconnects=self._reconnects,
                last_error=self._last_error,
                bytes=self._decoder.stats.bytes,
            )

    def close(self) -> None:
        """Stop the reader thread and close the port; safe to call more than once."""
        self._closing.set()
        with self._cond:
            self._cond.notify_all()
        if self._thread is not threading.current_thread():
            self._thread.join()
        self._close_port()

    def __enter__(self) -> BoardDriver:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # --- reader thread -----------------------------------------------------------------------

    def _error(self, text: str) -> None:
        """Record an error; log it once per change of state (a port that stays absent is logged at
        the first failed open, then once more with the count when it opens)."""
        self._last_error = text
        if text == self._logged_error:
            log.debug("%s: %s (again)", self.url, text)
            return
        self._logged_error = text
        log.warning("%s: %s%s", self.url, text, "; retrying (logged again when it changes)" if text.startswith("open") else "")

    def _open(self) -> bool:
        try:
            port = serial.serial_for_url(self.url, baudrate=self._baudrate, timeout=self._read_timeout)
        except (serial.SerialException, OSError, ValueError) as err:
            self._open_failures += 1
            self._error(f"open failed: {err}")
            return False
        _set_low_latency(port, self.url)
        self._decoder.reset()
        with self._port_lock:
            self._port = port
        self._opens += 1
        self._reconnects = max(self._opens - 1, 0)
        failed, self._open_failures, self._logged_error = self._open_failures, 0, None
        log.info("%s: connected%s", self.url, f" after {failed} failed attempts to open" if failed else "")
        if self.protocol == "binary":
            self.send(encode(Identify()) + encode(Start(self._rate_hz or 0.0)))
        return True

    def _close_port(self) -> None:
        with self._port_lock:
            port, self._port = self._port, None
        if port is not None:
            try:
                port.close()
            except (serial.SerialException, OSError) as err:
                log.debug("%s: close: %s", self.url, err)

    def _run(self) -> None:
        backoff = self._backoff[0]
        while not self._closing.is_set():
            if self._port is None:
                if not self._open():
                    self._closing.wait(backoff)
                    backoff = min(2 * backoff, self._backoff[1])
                    continue
                backoff = self._backoff[0]
                last_byte = time.monotonic()
            try:
                data = self._port.read(max(1, self._port.in_waiting))
            except (serial.SerialException, OSError) as err:
                self._error(f"read failed: {err}")
                self._close_port()
                continue
            now = time.monotonic()
            if not data:
                if now - last_byte > self._stall_timeout:
                    self._error(f"stalled: no bytes for {self._stall_timeout} s, reopening")
                    self._close_port()
                continue
            last_byte = now
            self._handle(self._decoder.feed(data))

    def _handle(self, messages: list) -> None:
        for msg in messages:
            if isinstance(msg, DataFrame):
                self._push(msg)
            elif isinstance(msg, Identity):
                self.identity = msg
                log.info("%s: %s", self.url, msg)
            elif isinstance(msg, Error):
                self._error(f"board error {msg.code} on command 0x{msg.command:02x}: {msg.text}")
            else:
                log.debug("%s: %s", self.url, msg)

    def _push(self, frame: DataFrame) -> None:
        with self._cond:
            if frame.seq is not None:
                if self._last_seq is not None:
                    step = (frame.seq - self._last_seq) & 0xFFFFFFFF
                    if 1 < step < 2**31:
                        self._gaps += step - 1
                    # step >= 2**31: the board restarted its counter; follow it without counting
                self._last_seq = frame.seq
            self._frames += 1
            self._last_error = ""
            if len(self._queue) == self._queue.maxlen:
                self._dropped += 1
            self._queue.append(frame)
            self._cond.notify()
