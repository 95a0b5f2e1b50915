"""Board time to host time: the lower envelope of the host-minus-board offset over a sliding window."""
from __future__ import annotations

from collections import deque

from ..errors import ConfigError


class ClockMapper:
    """Maps a board's microsecond clock onto host time (nanoseconds) for header stamps.

    The offset is the minimum of ``host_time - board_time`` over a sliding window of the last
    ``window_s`` seconds of board time. Transport and scheduling only ever delay a frame, so the
    smallest observed offset is the one closest to the true one (the lower envelope); taking it
    over a sliding window (not since the start) lets the offset follow a board crystal that drifts
    against the host clock: with a drift of d (e.g. 1e-4) the stamps lag by at most about d *
    window_s. A stamp is never later than the host time at which its frame was handed over.
    When the board clock jumps backwards (board reset) the window restarts.

    The node maps onto the host's monotonic clock (``time.monotonic_ns``), which cannot step, and
    takes each frame's age from it; a wall-clock step then moves no offset here (docs/node.md).
    Text-mode boards carry no clock: the node stamps their frames with host time on reception.

    Parameters
    ----------
    window_s : float
        Length of the sliding window in seconds of board time.
    """

    def __init__(self, window_s: float = 10.0) -> None:
        if not window_s > 0:
            raise ConfigError(f"{window_s=}: expected a positive number of seconds")
        self.window_us = int(window_s * 1e6)
        self._q: deque[tuple[int, int]] = deque()  # (board_us, offset_ns), offsets increasing
        self._last_board: int | None = None

    def reset(self) -> None:
        self._q.clear()
        self._last_board = None

    @property
    def offset_ns(self) -> int | None:
        """Current offset host - board in nanoseconds; None before the first frame."""
        return self._q[0][1] if self._q else None

    def stamp_ns(self, board_us: int, host_ns: int) -> int:
        """Host-time stamp (ns) of a frame measured at ``board_us`` and received at ``host_ns``."""
        if self._last_board is not None and board_us < self._last_board:
            self.reset()
        self._last_board = board_us
        off = int(host_ns) - int(board_us) * 1000
        q = self._q
        while q and q[-1][1] >= off:
            q.pop()
        q.append((board_us, off))
        while board_us - q[0][0] > self.window_us:
            q.popleft()
        return int(board_us) * 1000 + q[0][1]
