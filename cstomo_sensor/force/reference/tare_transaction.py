"""The tare transaction of one sensor: its frames, its end, its file. No ROS, no serial.

A stage of the frame stream (frame_path/stream.py), which calls it under its frame lock: a tare pending
(:meth:`Taring.start`) takes the next frames (:meth:`Taring.add`) until it ends, accepted or refused by
the rules of force/reference/tare_rules.py, or is cancelled (:meth:`Taring.cancel`, :meth:`Taring.interrupt` on a
reconnect). Its end is queued (:meth:`Taring.end`) and, once the frame lock is released
(:meth:`Taring.finish`), an accepted tare is written to the tare file by a thread of its own (frames
never wait for the disk: a hung disk delays the file, not the wrench) and every end is reported to
the :meth:`Taring.wait` of a transaction and to ``on_tare``.
"""
from __future__ import annotations

import logging
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path

import numpy as np

from ...errors import ConfigError, CstomoError
from .files import noise_path, read_reference, write_reference
from .tare_rules import TARE_RECONNECTED, Pipe, TareOutcome, judge_tare

log = logging.getLogger(__name__)


class Taring:
    """The tare transaction: the frames of a pending tare and the reference's history (when it was
    tared, the latest refusal, the file's state). ``n_meas`` values per frame; ``tare_file`` where an
    accepted tare is saved (None: not saved) with ``comment`` first; ``on_tare`` called with every
    :class:`~.tare_rules.TareOutcome`, outside the frame lock; ``started`` the monotonic time the log's
    seconds count from."""

    def __init__(self, n_meas: int, tare_file: str | Path | None = None, comment: str = "",
                 on_tare: Callable[[TareOutcome], None] | None = None, started: float | None = None) -> None:
        self.tare_file = Path(tare_file) if tare_file else None
        self.comment = comment
        self.on_tare = on_tare
        self._t_start = time.monotonic() if started is None else started
        self._x0 = np.zeros(n_meas)  # the first tare frame (the sums are taken around it)
        self._s1 = np.zeros(n_meas)
        self._s2 = np.zeros(n_meas)
        self._d = np.zeros(n_meas)
        self._st = np.zeros(n_meas)  # sum of k * (frame k - first frame): the linear trend
        self._mask = np.zeros(n_meas, bool)  # channels excluded during the tare
        self.left = self.n = 0
        self.forced = False
        self._lock = threading.Lock()  # the transaction's outcome, between the frames and the writer
        self._over = threading.Event()  # the transaction's tare ended (accepted or refused)
        self._done = threading.Event()  # ... and was reported (an accepted one saved, or not)
        self._outcome: TareOutcome | None = None
        self._ended: deque[tuple[TareOutcome, int]] = deque()  # ended, to save (the save's number) and report
        self._saves = 0  # accepted tares handed to a writer thread
        self._save_lock = threading.Lock()  # one write at a time
        self._writers: list[threading.Thread] = []  # tare files being written (close() waits for them)
        self.unsaved = ""  # why the latest accepted tare was not saved ('' when it was)
        self.source = "none"  # where the reference in use comes from, in words
        self.taken = ""  # when the reference in use was tared
        self.refused = ""  # the latest refused tare: when and why

    @property
    def pending(self) -> bool:
        return self.left > 0

    # --- under the frame lock --------------------------------------------------------------------

    def start(self, n: int, forced: bool = False) -> None:
        """A tare of the next ``n`` (>= 1) frames."""
        if isinstance(n, bool) or n < 1:
            raise ConfigError.bad_value("tare_frames", n, ">= 1")
        self.left = self.n = int(n)
        self.forced = bool(forced)

    def begin(self, n: int, forced: bool) -> None:
        """A transaction: :meth:`start`, its outcome awaited by :meth:`wait`."""
        self._over.clear()
        self._done.clear()
        with self._lock:
            self._outcome = None
        self.start(n, forced)

    def cancel(self, keep_pending: bool) -> int:
        """Drop a pending tare (``keep_pending``: no reference exists, so it stays pending from its
        first frame); returns the frames it had taken."""
        taken = self.n - self.left if self.left else 0
        self.left = self.n if keep_pending else 0
        self.forced = False
        return taken

    def settle(self, keep_pending: bool) -> tuple[TareOutcome | None, int]:
        """After :meth:`wait`: the transaction's outcome and its frames, or (None, the frames taken)
        with the tare cancelled when it has not ended."""
        with self._lock:
            ended = self._outcome
        return (ended, ended.frames) if ended is not None else (None, self.cancel(keep_pending))

    def interrupt(self) -> TareOutcome | None:
        """The board reconnected: a pending tare ends, refused (:data:`~.tare_rules.TARE_RECONNECTED`)."""
        if not self.left:
            return None
        taken, self.left = self.n - self.left, 0
        return TareOutcome(None, taken, 0.0, TARE_RECONNECTED)

    def add(self, v: np.ndarray, mask: np.ndarray, pipe: Pipe, max_spread: float) -> TareOutcome | None:
        """One frame ``v`` (``mask``: its excluded channels) into the pending tare; its outcome when it
        was the last (:func:`~.tare_rules.judge_tare` against ``pipe``), else None."""
        if self.left == self.n:  # the first frame
            self._x0[:] = v
            self._s1[:] = 0.0
            self._s2[:] = 0.0
            self._st[:] = 0.0
            self._mask[:] = mask
        self._mask |= mask
        np.subtract(v, self._x0, out=self._d)
        self._s1 += self._d
        self._st += (self.n - self.left) * self._d
        self._d **= 2
        self._s2 += self._d
        self.left -= 1
        if self.left:
            return None
        return judge_tare(pipe, self.n, self._x0, self._s1, self._s2, self._st, ~self._mask, max_spread, self.forced)

    def end(self, outcome: TareOutcome, has_reference: bool, noise_text: str = "", report=None) -> None:
        """A tare ended (the stream has set an accepted one as its reference: ``report`` the pipeline's
        :class:`~.files.ScaleReport`, ``noise_text`` its noise): recorded and logged, queued for
        :meth:`finish`. Without a reference (``has_reference`` False) a refused tare starts over."""
        when = time.strftime("%H:%M:%S")
        self.forced = False
        if outcome.ok:
            self.taken = f"{when}, {time.monotonic() - self._t_start:.1f} s after start, {outcome.frames} frames, " \
                         f"spread {outcome.spread:.2%}" + (", forced" if outcome.forced else "")
            log.info("tare taken at %s (noise %s; %s)", self.taken, noise_text,
                     outcome.check.summary() if outcome.check is not None else "no load check")
            if outcome.forced:
                log.warning("forced tare: %s", f"overrode: {outcome.overridden}" if outcome.overridden else
                            "the load checks passed anyway")
            (log.warning if report.warn else log.info)("tare: %s", report.message)
            self.source = "tare" if self.tare_file is None else f"tare, being saved to {self.tare_file}"
        else:
            self.refused = f"{when}: {outcome.reason}"
            if not has_reference:
                log.warning("%s; no reference yet: taring again on the next %d frames", outcome.reason, self.n)
                self.start(self.n)
            else:
                log.warning("%s; the previous reference stays", outcome.reason)
        if outcome.ok and self.tare_file is not None:
            self._saves += 1
        with self._lock:
            self._outcome = outcome
        self._over.set()
        self._ended.append((outcome, self._saves if outcome.ok else 0))

    def discard(self, why: str) -> None:
        """The reference in use, a first tare, carried a load (``why``, force/reference/first_tare.py): said once (WARN,
        and ``tare_refused`` in the diagnostics); its file is removed by a thread of its own (frames never
        wait for the disk), unless a later tare is saved first. The caller starts the next tare."""
        self.taken, self.refused = "", f"{time.strftime('%H:%M:%S')}: {why}"
        self.source = "tare pending (the first tare carried a load)"
        log.warning("%s", why)
        if self.tare_file is not None:
            self._saves += 1  # a write of the dropped tare not begun yet is not made
            writer = threading.Thread(target=self._remove, args=(self._saves,), name="cstomo_tare_drop", daemon=True)
            self._writers = [w for w in self._writers if w.is_alive()] + [writer]
            writer.start()

    def _remove(self, seq: int) -> None:
        with self._save_lock:
            if seq == self._saves:  # no later tare saved meanwhile
                try:
                    self.tare_file.unlink(missing_ok=True)
                    noise_path(self.tare_file).unlink(missing_ok=True)
                except OSError as err:
                    log.error("the loaded first tare %s not removed (%s): remove it before the next start",
                              self.tare_file, err)
                else:
                    log.info("loaded first tare removed: %s", self.tare_file)

    def reference_from(self, source: str) -> None:
        """The reference in use now comes from ``source`` (a file, or a tare pending)."""
        self.source = source

    def status(self, has_reference: bool) -> tuple[int, list[str], dict]:
        """The diagnostics' level (1 WARN), problems and figures."""
        kv = dict(tare_taken=self.taken, tare_refused=self.refused, tare_unsaved=self.unsaved)
        msgs = [self.unsaved] if self.unsaved else []
        if self.left and not has_reference:
            msgs.append("no reference yet: taring on the first frames (the joint must be unloaded); no force "
                        "published until then" + (f"; last tare refused at {self.refused}" if self.refused else ""))
        return int(bool(msgs)), msgs, kv

    # --- outside the frame lock ------------------------------------------------------------------

    def wait(self, timeout: float) -> bool:
        """Wait up to ``timeout`` s for the transaction's tare to end; True if it did."""
        return self._over.wait(timeout)

    def wait_saved(self, outcome: TareOutcome, timeout: float) -> TareOutcome:
        """The final outcome of the transaction's accepted or refused tare ``outcome``: once saved (its
        ``note``: why not saved), or after ``timeout`` s with a note that the save is under way."""
        if not self._done.wait(timeout):
            return replace(outcome, note=f"tare in use, still being saved to {self.tare_file} (a slow disk?): "
                                         "the diagnostics' reference says when it is saved")
        with self._lock:
            return self._outcome

    def saved(self, n_meas: int) -> tuple[tuple | None, str]:
        """At a start (the history starts anew): the saved tare (what :func:`~.files.read_reference`
        reads), else None and why not."""
        path = self.tare_file
        self.taken = self.refused = ""
        if path is None or not path.is_file():
            return None, f"no saved tare of this device at {path}"
        try:
            return read_reference(path, n_meas), ""
        except (CstomoError, OSError) as err:
            return None, f"saved tare {path} unusable ({err})"

    def finish(self) -> None:
        """Save and report the tares that ended (called once the frame lock is released): an accepted
        tare is written by a thread of its own, so frames keep flowing while a slow or hung disk
        writes it."""
        while self._ended:
            try:
                outcome, seq = self._ended.popleft()
            except IndexError:  # another thread took it
                return
            if seq:
                writer = threading.Thread(target=self._save, args=(outcome, seq), name="cstomo_tare_save", daemon=True)
                self._writers = [w for w in self._writers if w.is_alive()] + [writer]
                writer.start()
            else:
                self._report(outcome)

    def close(self, timeout: float = 5.0) -> list[str]:
        """Wait up to ``timeout`` s for the tare files still being written; returns the files not
        written by then (a hung disk)."""
        self.finish()
        deadline = time.monotonic() + timeout
        for w in self._writers:
            w.join(max(0.0, deadline - time.monotonic()))
        late = [str(self.tare_file) for w in self._writers if w.is_alive()]
        if late:
            log.error("tare not saved to %s within %.0f s (a hung disk?): the next start reads the older tare",
                      self.tare_file, timeout)
        return late

    def _report(self, outcome: TareOutcome, note: str = "") -> None:
        """The end of a tare, final (``note``: why an accepted one was not saved): to the transaction
        waiting for it and to ``on_tare``."""
        final = replace(outcome, note=note) if note else outcome
        with self._lock:
            if self._outcome is outcome:
                self._outcome = final
                self._done.set()
        if self.on_tare is not None:
            self.on_tare(final)

    def _save(self, outcome: TareOutcome, seq: int) -> None:
        """Write an accepted tare to ``tare_file`` (atomically) with its noise beside it, then report it
        with '' or why it was not saved as its ``note`` (logged at ERROR and shown in the diagnostics
        until a tare is saved). The writer thread of :meth:`finish`; ``seq``: a later tare replaces an
        earlier one whose write has not started."""
        path, note = self.tare_file, ""
        with self._save_lock:
            if seq == self._saves:
                try:
                    path.parent.mkdir(parents=True, exist_ok=True)
                    write_reference(path, outcome.reference, outcome.noise, frames=outcome.frames,
                                    comment=f"{self.comment}: mean of {outcome.frames} frames, "
                                            f"{time.strftime('%Y-%m-%dT%H:%M:%S%z')}")
                except OSError as err:
                    note = f"tare in use but not saved to {path} ({err}): fix tare_file and tare again"
                    log.error("%s", note)
                else:
                    log.info("tare saved to %s", path)
                if seq == self._saves:  # still the newest tare
                    self.unsaved = note
                    self.source = f"tare, not saved to {path}" if note else f"tare saved to {path}"
            else:
                note = f"tare in use, not saved: a later tare replaced it in {path}"
        self._report(outcome, note)
