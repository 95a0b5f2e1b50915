"""Serial driver for the board: a pyserial port opened by URL, a bounded queue, and a reader thread
or none (``thread=False``: the thread calling :meth:`BoardDriver.get` reads, as
:class:`cstomo_sensor.frame_path.sources.SerialSource` does: no hand-over between threads).

The reader decodes frames (binary or text mode, docs/protocol.md), counts lost frames once
each (by sequence number: lost to corruption or to a gap), drops and counts duplicated and late
(reordered) frames, drops the oldest frame when the user falls behind, and reconnects when the port
disappears (retrying every 0.05..0.25 s: a replugged board is back within a second) or the board
stops sending for longer than a few of its own frame periods (``on_reconnect`` is called when it
is back). Nothing raises out of the reader.
"""
from __future__ import annotations

import errno
import logging
import math
import os
import select
import stat
import threading
import time
from collections import OrderedDict, deque
from dataclasses import dataclass
from typing import Literal

import serial

from ..errors import ConfigError
from ..settings import PROTOCOLS
from .wire import DataFrame, Decoder, Error, Identify, Identity, Start, TextDecoder, encode

log = logging.getLogger(__name__)

#: The OS-level names (``/proc/<pid>/task/<tid>/comm``) of the driver's reader thread and of the
#: node's frame thread, so per-thread CPU (``cstomo bench-node``, ``top -H``) can tell them apart.
READER_THREAD = "cstomo_reader"


def set_os_thread_name(name: str) -> None:
    """Name the calling thread for the OS (Linux ``prctl(PR_SET_NAME)``, 15 bytes at most): Python
    sets ``threading.Thread.name`` for the OS only from 3.14. A no-op where it cannot."""
    try:
        import ctypes

        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(15, ctypes.c_char_p(name.encode()[:15]), 0, 0, 0)  # 15 = PR_SET_NAME
    except (OSError, AttributeError):
        pass

def _fd_ports() -> tuple[type, ...]:
    """The port classes read through their file descriptor (:meth:`BoardDriver._read`)."""
    from .protocol_virtual import Serial as VirtualSerial

    posix = getattr(getattr(serial, "serialposix", None), "Serial", None)
    return (VirtualSerial,) if posix is None else (VirtualSerial, posix)


if __package__ not in serial.protocol_handler_packages:  # virtual://NAME: .protocol_virtual, an in-process board
    serial.protocol_handler_packages.append(__package__)

#: The board has stalled when no byte came for this many of its frame periods (and at least the
#: driver's ``stall_timeout``): a 1 frame/s board is not reopened every second.
STALL_PERIODS = 3.0
#: Before the frame period is known (fewer than two frames since the driver started) a stall is
#: declared only after this many seconds: a slow board's first two frames are awaited.
FIRST_PERIOD_WAIT = 2.5
#: A frame up to this many sequence numbers behind the newest is a late (reordered) one or a
#: duplicate; further back, the board restarted its counter.
REORDER_WINDOW = 256
_FD_PORTS = _fd_ports()

@dataclass(frozen=True)
class DriverStats:
    """A snapshot of the driver's counters.

    Attributes
    ----------
    connected : bool
        The port is open now.
    frames : int
        Valid data frames delivered to the queue (including those later dropped by queue overflow;
        not duplicates or late frames).
    dropped_overflow : int
        Frames dropped (the oldest first) because the queue was full.
    corrupt : int
        Frames lost to corruption, each counted once. Binary mode: the frames missing by sequence
        number where the decoder dropped something (CRC, length, type, version, NaN) in between; text
        mode (no sequence number): lines dropped by the decoder.
    seq_gaps : int
        Frames missing by sequence number with nothing corrupt in between (the board or the link
        dropped them whole); binary mode. ``corrupt + seq_gaps`` is every lost frame, once.
    duplicates : int
        Frames dropped because their sequence number was already delivered.
    reordered : int
        Frames dropped because a newer one was already delivered (too late to publish in order);
        they were not lost, so they no longer count in ``corrupt`` or ``seq_gaps``.
    resyncs : int
        Times the decoder dropped bytes (line noise, a cut-off frame) and no frame was lost.
    period : float
        The board's frame period in seconds as measured on its clock (on arrival in text mode; nan until
        two frames came).
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
    duplicates: int
    reordered: int
    resyncs: int
    period: float
    reconnects: int
    last_error: str
    bytes: int


def check_port(url: str) -> None:
    """Refuse (:class:`ConfigError`) a port that exists and is no device: a regular file or a
    directory is a configuration error, said once, where a missing device is a board not yet plugged
    in (opened again and again). URLs (``scheme://...``) are left to pyserial."""
    if "://" in url or not os.path.exists(url):
        return
    mode = os.stat(url).st_mode
    if not stat.S_ISCHR(mode):
        kind = "a directory" if stat.S_ISDIR(mode) else "a regular file" if stat.S_ISREG(mode) else "not a device"
        raise ConfigError(f"port {url!r}: {kind}; expected a serial device (e.g. /dev/ttyACM0, a udev link "
                          "such as /dev/cstomo) or a pyserial URL")


def _set_low_latency(port: serial.SerialBase, url: str) -> None:
    """Best effort: set ASYNC_LOW_LATENCY (TIOCSSERIAL) on a real Linux tty; ignore failure."""
    setter = getattr(port, "set_low_latency_mode", None)  # pyserial's Linux ioctl wrapper
    if setter is None:
        return
    try:
        setter(True)
    except (OSError, ValueError, AttributeError) as err:  # ptys/ports without TIOCGSERIAL
        log.debug("low-latency flag not set on %s: %s", url, err)


def _open_failed(err: Exception) -> str:
    """One sentence for a port that does not open: a missing device names what to check; else the
    cause once (pyserial's own message repeats '[Errno N]': 'could not open port X: [Errno N] ...')."""
    if getattr(err, "errno", None) == errno.ENOENT:
        return ("open failed: no such device (check the cable and the board's power, the node's 'port' "
                "parameter, and the udev rule config/99-cstomo.rules that makes the name: docs/node.md#udev)")
    text = err.strerror if isinstance(err, OSError) and isinstance(err.strerror, str) else str(err)
    return f"open failed: {text}"


class BoardDriver:
    """Reads frames from a board over a serial port in a background thread.

    Parameters
    ----------
    url : str
        Anything :func:`serial.serial_for_url` opens: a device path, ``socket://host:port``,
        ``rfc2217://host:port``, ``loop://``, and ``virtual://NAME``: a simulated board in this
        process (:mod:`.protocol_virtual`).
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
        Least number of seconds without any byte after which the port is closed and reopened; the
        wait is at least :data:`STALL_PERIODS` frame periods of the board (measured, else
        ``1 / rate_hz``), and :data:`FIRST_PERIOD_WAIT` while the period is unknown (at the start
        and after a stall), so boards down to 1 / FIRST_PERIOD_WAIT = 0.4 frames/s are followed.
    reconnect_backoff : (float, float)
        First and largest wait in seconds between reopening attempts (doubling in between); the
        largest bounds how long a replugged board waits to be opened again.
    rate_hz : float or None
        Rate asked for in START; None asks for the board's default rate.
    thread : bool
        Read in a background thread (default); False: :meth:`get` reads in the caller's thread.
    on_reconnect : callable or None
        Called (by the reading thread) when the port is open again after losing it.

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
        reconnect_backoff: tuple[float, float] = (0.05, 0.25),
        rate_hz: float | None = None,
        thread: bool = True,
        on_reconnect=None,
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
        check_port(url)
        self.url = url
        self.protocol = protocol
        self._baudrate = baudrate
        self._read_timeout = read_timeout
        self._stall_timeout = stall_timeout
        self._backoff = (float(lo), float(hi))
        self._rate_hz = rate_hz
        self._decoder = Decoder() if protocol == "binary" else TextDecoder()
        self._queue: deque[DataFrame] = deque(maxlen=queue_size)
        # the counters' and the queue's lock; per frame it is taken directly (a Condition's ``with`` is a Python call)
        self._lock = threading.Lock()
        self._cond = threading.Condition(self._lock)
        self._port_lock = threading.Lock()
        self._port: serial.SerialBase | None = None
        self._closing = threading.Event()
        self._frames = self._dropped = self._gaps = self._reconnects = self._opens = 0
        self._corrupt = self._duplicates = self._reordered = self._resyncs = self._bad = 0
        self._logged_error: str | None = None  # the error last logged (not logged again until it changes)
        self._open_failures = 0  # failed opens since the last successful one
        self._silent_reopens = 0  # stall reopens since the board's last byte (logged once, not each)
        self._last_seq: int | None = None
        self._fresh = True
        self._missing: OrderedDict[int, str] = OrderedDict()  # recently lost seq -> 'corrupt' or 'gap'
        self._intervals: deque[float] = deque(maxlen=16)  # recent frame periods (s)
        self._last_frame_at: tuple[float, int | None] | None = None  # (board or monotonic s, seq) of the last frame
        self._last_error = ""
        self.identity: Identity | None = None
        self.on_reconnect = on_reconnect
        self._backoff_now = self._backoff[0]
        self._fd: int | None = None  # the open port's file descriptor, when it is read directly (_read)
        self._next_open = 0.0  # monotonic time of the next attempt to open the port
        self._last_byte = 0.0
        self._thread: threading.Thread | None = None
        if thread:
            self._thread = threading.Thread(target=self._run, name=f"BoardDriver({url})", daemon=True)
            self._thread.start()

    # --- user side ---------------------------------------------------------------------------

    def get(self, timeout: float) -> DataFrame | None:
        """The oldest queued frame, waiting up to ``timeout`` seconds; None if none came. Without a
        reader thread the caller reads the port meanwhile."""
        if self._thread is None:
            q = self._queue
            if not q:
                deadline = time.monotonic() + timeout
                while not self._closing.is_set():
                    self._step(deadline)
                    if q or time.monotonic() >= deadline:
                        break
            return q.popleft() if q else None
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
        with self._lock:
            return DriverStats(
                connected=self._port is not None,
                frames=self._frames,
                dropped_overflow=self._dropped,
                corrupt=self._corrupt,
                seq_gaps=self._gaps,
                duplicates=self._duplicates,
                reordered=self._reordered,
                resyncs=self._resyncs,
                period=self._period(),
                reconnects=self._reconnects,
                last_error=self._last_error,
                bytes=self._decoder.stats.bytes,
            )

    def close(self) -> None:
        """Stop the reader thread and close the port; safe to call more than once."""
        self._closing.set()
        with self._cond:
            self._cond.notify_all()
        if self._thread is not None and self._thread is not threading.current_thread():
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

    def _period(self) -> float:
        """The board's frame period (s): the median of the recent intervals; nan before two frames."""
        if not self._intervals:
            return float("nan")
        return sorted(self._intervals)[len(self._intervals) // 2]

    def _stall_after(self) -> float:
        """Seconds without a byte that make a stall: STALL_PERIODS frame periods (measured, else the
        rate asked for), FIRST_PERIOD_WAIT while neither is known; never less than stall_timeout."""
        period = self._period()
        if math.isnan(period) and self._rate_hz:
            period = 1.0 / self._rate_hz
        wait = FIRST_PERIOD_WAIT if math.isnan(period) else STALL_PERIODS * period
        return max(self._stall_timeout, wait)

    def _open(self) -> bool:
        try:
            port = serial.serial_for_url(self.url, baudrate=self._baudrate, timeout=self._read_timeout)
        except (serial.SerialException, OSError, ValueError) as err:
            self._open_failures += 1
            self._error(_open_failed(err))
            return False
        _set_low_latency(port, self.url)
        self._fd = port.fileno() if isinstance(port, _FD_PORTS) else None
        self._decoder.reset()
        with self._port_lock:
            self._port = port
        self._opens += 1
        self._fresh = True  # the first frame on a new connection may restart the counter
        self.identity = None  # this connection's: a board that answers queued IDENTIFYs is logged once
        self._reconnects = max(self._opens - 1, 0)
        failed, self._open_failures = self._open_failures, 0
        if self._silent_reopens and not failed:  # reopened after a stall: the board is back when its bytes are
            log.debug("%s: connected (reopen %d after a stall)", self.url, self._silent_reopens)
        else:
            self._silent_reopens, self._logged_error = 0, None
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
        set_os_thread_name(READER_THREAD)
        while not self._closing.is_set():
            self._step(math.inf)

    def _step(self, deadline: float) -> None:
        """One read of the port (up to ``read_timeout``), or one attempt to open it (waiting for the
        back-off, at most until ``deadline``): its frames are queued."""
        if self._port is None:
            now = time.monotonic()
            if now < self._next_open:
                self._closing.wait(min(self._next_open, deadline) - now)
                return
            if not self._open():
                self._next_open = time.monotonic() + self._backoff_now
                self._backoff_now = min(2 * self._backoff_now, self._backoff[1])
                return
            self._backoff_now = self._backoff[0]
            self._last_byte = time.monotonic()
            self._last_frame_at = None  # no period across a reconnect
            if self._opens > 1 and self.on_reconnect is not None:
                self.on_reconnect()
        # without a reader thread up to the caller's deadline (the node's 0.1 s: one wake-up per timeout
        # when idle, not two), at most 2 read_timeouts (a close() from elsewhere is seen)
        wait = self._read_timeout if deadline == math.inf else min(max(deadline - time.monotonic(), 0.0),
                                                                    2 * self._read_timeout)
        try:
            data = self._read(wait)
        except (serial.SerialException, OSError) as err:
            self._error(f"read failed: {err}")
            self._close_port()
            return
        now = time.monotonic()
        if not data:
            stall = self._stall_after()
            if now - self._last_byte > stall:
                self._silent_reopens += 1
                self._error(f"stalled: no bytes for {stall:.2g} s, reopening")
                self._intervals.clear()  # its rate may have changed: measured again
                self._close_port()
            return
        self._last_byte = now
        if self._silent_reopens:
            log.info("%s: receiving again after %d reopens", self.url, self._silent_reopens)
            self._silent_reopens, self._logged_error = 0, None
        self._handle(self._decoder.feed(data, marks=True))

    def _read(self, wait: float) -> bytes:
        """What the port holds, waiting up to ``wait`` s for the first byte: on a device or a
        virtual link one wait and one read of the file descriptor (pyserial's own read of what is
        waiting costs an ioctl and two waits and reads per frame), else pyserial's read."""
        fd = self._fd
        if fd is None:
            return self._port.read(max(1, self._port.in_waiting))
        if not select.select((fd,), (), (), wait)[0]:
            return b""
        data = os.read(fd, 65536)
        if not data:  # ready, yet nothing: the device went away (pyserial says the same)
            raise serial.SerialException("device reports readiness to read but returned no data "
                                         "(device disconnected or multiple access on port?)")
        return data

    def _handle(self, messages: list) -> None:
        for msg in messages:
            if msg is None:  # a piece the decoder dropped
                self._bad += 1
            elif isinstance(msg, DataFrame):
                self._push(msg)
            elif isinstance(msg, Identity):
                # a board that stalled answers the IDENTIFY of every reopen at once when it is back
                (log.debug if msg == self.identity else log.info)("%s: %s", self.url, msg)
                self.identity = msg
            elif isinstance(msg, Error):
                self._error(f"board error {msg.code} on command 0x{msg.command:02x}: {msg.text}")
            else:
                log.debug("%s: %s", self.url, msg)

    def _push(self, frame: DataFrame) -> None:
        with self._lock:
            bad, self._bad = self._bad, 0  # pieces dropped since the last frame
            if frame.seq is None:
                self._corrupt += bad  # text mode: a dropped line is a lost frame
            elif not self._in_order(frame.seq, bad):
                return
            # the period on the board's clock where it has one: a loaded host (or a USB adapter) reads
            # frames in bursts, a few microseconds apart on arrival
            t_now = time.monotonic() if frame.board_time_us is None else frame.board_time_us * 1e-6
            if self._last_frame_at is not None:
                t, seq = self._last_frame_at
                steps = 1 if seq is None or frame.seq is None else max((frame.seq - seq) & 0xFFFFFFFF, 1)
                if (seq is None) == (frame.seq is None) and t_now > t:
                    self._intervals.append((t_now - t) / steps)
            self._last_frame_at = (t_now, frame.seq)
            self._frames += 1
            self._last_error = ""
            if len(self._queue) == self._queue.maxlen:
                self._dropped += 1
            self._queue.append(frame)
            if self._thread is not None:  # without a reader thread nobody waits (get reads)
                self._cond.notify()

    def _in_order(self, seq: int, bad: int) -> bool:
        """Count what the sequence number ``seq`` says (``bad`` pieces were dropped since the last
        frame); False for a frame to drop (a duplicate or a late one)."""
        last = self._last_seq
        step = (seq - last) & 0xFFFFFFFF if last is not None else 1
        if step == 1 and not bad and not self._fresh:  # the next frame, nothing lost (every frame but a few)
            self._last_seq = seq
            return True
        if step == 0:
            self._duplicates += 1
            return False
        fresh, self._fresh = self._fresh, False
        if not fresh and 2**32 - step <= REORDER_WINDOW:
            kind = self._missing.pop(seq, None)
            if kind is None:
                self._duplicates += 1
            else:  # counted as lost when the newer frame came: it was only late
                self._reordered += 1
                if kind == "corrupt":
                    self._corrupt -= 1
                else:
                    self._gaps -= 1
            return False
        if step >= 2**31:  # behind on a new connection or far behind: the board restarted its counter
            self._missing.clear()
            step = 1
        missing = step - 1
        corrupt = min(missing, bad)
        self._corrupt += corrupt
        self._gaps += missing - corrupt
        if bad and not missing:
            self._resyncs += 1
        for k in range(max(missing - REORDER_WINDOW, 0), missing):
            self._missing[(seq - missing + k) & 0xFFFFFFFF] = "corrupt" if k < corrupt else "gap"
        while len(self._missing) > REORDER_WINDOW:
            self._missing.popitem(last=False)
        self._last_seq = seq
        return True
