"""The simulated board's end of a link: a pseudo-terminal, or an in-process virtual link.

Both give the board one non-blocking file descriptor (:attr:`fd`) it selects on, reads and writes,
and a :attr:`device` a host opens:

- :class:`PtyLink`: ``os.openpty`` in raw mode; the host opens the slave's path (or a symlink to it
  the link keeps, removed while closed), as it opens a real board's tty.
- :class:`VirtualLink`: a ``socket.socketpair()`` registered in this process under ``virtual://NAME``
  (like python-can's virtual bus: no pty, no file); the host opens that URL through the pyserial
  handler :mod:`.protocol_virtual`, which :func:`connect` serves. Closing the link (a disconnect
  fault, the board's end) unregisters the name: an open then fails as for an absent device, and a
  host that held the link open reads end-of-file.
"""
from __future__ import annotations

import errno
import os
import socket
import threading
import tty

VIRTUAL = "virtual://"
#: The board end's send buffer (bytes asked of the kernel): it then holds about 17 kB of frames before a
#: write blocks, as a pseudo-terminal holds 16.5 kB (a socket pair's default holds 72 kB): a stalled
#: host sees the backlog a tty gives.
SEND_BUFFER = 24576

_lock = threading.Lock()
_hosts: dict[str, socket.socket] = {}  # virtual name -> the host end of its board's current link


def is_virtual(device: str | os.PathLike | None) -> bool:
    """True for a ``virtual://NAME`` URL."""
    return isinstance(device, str) and device.lower().startswith(VIRTUAL)


def _name(url: str) -> str:
    name = url[len(VIRTUAL):]
    if not is_virtual(url) or not name:
        raise ValueError(f"{url!r}: expected virtual://NAME")
    return name


class PtyLink:
    """A pseudo-terminal: the board holds the master (:attr:`fd`) and the slave (so a host may close
    and reopen it); ``link``: a symlink kept pointing at the slave while open."""

    def __init__(self, link: str | None = None) -> None:
        master, self._slave = os.openpty()
        tty.setraw(self._slave)
        os.set_blocking(master, False)
        self.fd, self.link, self.path = master, link, os.ttyname(self._slave)
        if link:
            tmp = f"{link}.{os.getpid()}.tmp"
            os.symlink(self.path, tmp)
            os.replace(tmp, link)

    @property
    def device(self) -> str:
        return self.link or self.path

    def close(self) -> None:
        if self.link and os.path.islink(self.link):
            os.unlink(self.link)
        for fd in (self.fd, self._slave):
            os.close(fd)


class VirtualLink:
    """A socket pair registered as ``url`` (``virtual://NAME``); the board holds both ends.

    Raises
    ------
    ValueError
        If ``url`` is not ``virtual://NAME``; FileExistsError if another link holds the name.
    """

    def __init__(self, url: str) -> None:
        self._name, self.device = _name(url), url
        board, self._host = socket.socketpair()
        board.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, SEND_BUFFER)  # a tty's backlog, not 4 x it
        board.setblocking(False)
        with _lock:
            if self._name in _hosts:
                board.close()
                self._host.close()
                raise FileExistsError(errno.EEXIST, "a virtual board already holds this name", url)
            _hosts[self._name] = self._host
        self._board, self.fd = board, board.fileno()

    def close(self) -> None:
        with _lock:
            if _hosts.get(self._name) is self._host:
                del _hosts[self._name]
        self._board.close()
        self._host.close()


def holds(url: str) -> bool:
    """True when a board of this process holds the virtual link ``url`` now."""
    with _lock:
        return _name(url) in _hosts


def connect(url: str) -> socket.socket:
    """A new host end of the virtual board ``url`` (a duplicate, as opening a tty is a new file of
    one device: closing it leaves the board's link open).

    Raises
    ------
    FileNotFoundError
        No board holds ``url`` now (never started, closed, or disconnected by a fault).
    """
    with _lock:
        host = _hosts.get(_name(url))
        if host is None:
            raise FileNotFoundError(errno.ENOENT, "no virtual board", url)
        return host.dup()


def open_link(link: str | os.PathLike | None) -> PtyLink | VirtualLink:
    """The link a board's ``link`` argument names: virtual for ``virtual://NAME``, else a pty."""
    return VirtualLink(link) if is_virtual(link) else PtyLink(os.fspath(link) if link is not None else None)
