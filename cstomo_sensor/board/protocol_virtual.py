"""pyserial handler of ``virtual://NAME``: the host end of an in-process simulated board (:mod:`.links`).

:mod:`.driver` adds ``cstomo_sensor.board`` to ``serial.protocol_handler_packages``, so
``serial.serial_for_url("virtual://NAME")`` (and so :class:`~.driver.BoardDriver`, unchanged) opens
the link of the :class:`~.sim.SimulatedBoard` made with ``link="virtual://NAME"``. A name no board
holds fails to open with :class:`serial.SerialException`, as an absent device does; a link closed
under an open port (a disconnect fault) makes ``read`` raise it, as a pty's EIO does. The line
settings (baud rate, parity, ...) are accepted and ignored, as a pseudo-terminal ignores them.
"""
from __future__ import annotations

import fcntl
import select
import socket
import struct
import termios

from serial.serialutil import PortNotOpenError, SerialBase, SerialException, Timeout

from .links import connect


class Serial(SerialBase):
    """A :class:`serial.SerialBase` on the host end of a virtual board's socket pair."""

    _socket: socket.socket | None = None

    def open(self) -> None:
        if self._port is None:
            raise SerialException("Port must be configured before it can be used.")
        if self.is_open:
            raise SerialException("Port is already open.")
        try:
            self._socket = connect(self.portstr)
        except (OSError, ValueError) as err:
            raise SerialException(f"could not open port {self.portstr}: {err}") from None
        self.is_open = True
        self.reset_input_buffer()  # as a tty's open flushes: no bytes from before this open

    def _reconfigure_port(self, force_update: bool = False) -> None:
        """Line settings do not apply to a virtual link."""

    def close(self) -> None:
        self.is_open = False
        if self._socket is not None:
            self._socket.close()
            self._socket = None

    def _checked(self) -> socket.socket:
        if not self.is_open or self._socket is None:
            raise PortNotOpenError()
        return self._socket

    def fileno(self) -> int:
        """The link's socket: the driver waits on it and reads it directly (board/driver.py)."""
        return self._checked().fileno()

    @property
    def in_waiting(self) -> int:
        return struct.unpack("I", fcntl.ioctl(self._checked(), termios.FIONREAD, b"\0" * 4))[0]

    def read(self, size: int = 1) -> bytes:
        """Up to ``size`` bytes, waiting at most the port's timeout (None: until ``size`` came)."""
        sock, out, timeout = self._checked(), bytearray(), Timeout(self._timeout)
        while len(out) < size:
            if not select.select([sock], [], [], timeout.time_left())[0]:
                break
            try:
                data = sock.recv(size - len(out))
            except OSError as err:
                raise SerialException(f"read failed: {err}") from None
            if not data:
                raise SerialException("the board closed its link (device disconnected)")
            out += data
            if timeout.expired():
                break
        return bytes(out)

    def write(self, data: bytes) -> int:
        sock = self._checked()
        try:
            sock.sendall(data)
        except OSError as err:
            raise SerialException(f"write failed: {err}") from None
        return len(data)

    def reset_input_buffer(self) -> None:
        sock = self._checked()
        while select.select([sock], [], [], 0)[0]:
            try:
                if not sock.recv(65536):
                    break  # end of file: the next read says so
            except OSError:
                break

    def reset_output_buffer(self) -> None:
        """Nothing is buffered on the host side of the link."""

    def send_break(self, duration: float = 0.25) -> None:
        self._checked()

    def _update_break_state(self) -> None:
        pass

    def _update_rts_state(self) -> None:
        pass

    def _update_dtr_state(self) -> None:
        pass

    @property
    def cts(self) -> bool:
        return True

    @property
    def dsr(self) -> bool:
        return True

    @property
    def ri(self) -> bool:
        return False

    @property
    def cd(self) -> bool:
        return True
