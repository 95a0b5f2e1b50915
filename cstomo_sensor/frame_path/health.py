"""The health of one sensor's frame stream: its counts, and the diagnostics' level and figures of
them. No ROS, no serial.

A stage of the frame stream (frame_path/stream.py): frames, late frames, dropped frames and why,
implausible and foreign-load frames, uncertain forces, the processing time, the frame period, and
the losses over the last :data:`LOSS_WINDOW` s. Reading is a pure snapshot (:meth:`Health.status`:
the figures of the period so far); a period ends only when asked (:meth:`Health.end_period`).
"""
from __future__ import annotations

import logging
import math
import threading
import time
import traceback
from collections import deque
from typing import TYPE_CHECKING

from ..errors import FrameError, NoUsableChannelsError

if TYPE_CHECKING:
    from .pipeline import Pipeline

log = logging.getLogger(__name__)

#: Diagnostic levels (the values of diagnostic_msgs/DiagnosticStatus).
OK, WARN, ERROR = 0, 1, 2
#: Seconds over which lost and dropped frames are judged, and the fractions of the frames sent in
#: that time above which the status is WARN and ERROR.
LOSS_WINDOW = 5.0
LOSS_WARN = 0.01
LOSS_ERROR = 0.2
#: A repeated per-frame message (a dropped frame, a corrupt input) is logged at most once per this
#: many seconds, with the count of the ones left out.
LOG_EVERY = 5.0
#: The frame period is measured over the latest this many frames.
PERIOD_FRAMES = 32
#: The running totals a period's figures are the differences of.
_TOTALS = ("frames", "proc_sum", "proc_n", "foreign", "sigma_over", "rejected", "implausible")


class Counts:
    """The stream's counters, all time (guarded by :attr:`Health.lock`, but for the implausible ones:
    the frame lock's); ``period_*`` since the period began."""

    def __init__(self) -> None:
        self.frames = 0          # frames pushed
        self.corrupt = 0         # input messages that were no frame (counted by the caller: drop(corrupt=True))
        self.rejected = 0        # frames dropped by the frame path, all causes
        self.all_excluded = 0    # ... of which every measurement was excluded by the board's flags
        self.errors = 0          # ... of which an unexpected exception (a bug) was the cause
        self.reject_reason = ""  # why the latest frame was dropped; '' once a frame goes through
        self.period_reason = ""
        self.late = 0            # frames older than stale_timeout (dropped)
        self.proc_sum = 0.0      # s of processing of the frames with a result
        self.proc_n = 0
        self.period_proc_max = 0.0
        self.residual = math.nan
        self.consistency = math.nan
        self.foreign = 0
        self.sigma_n = math.nan      # the latest published frame's sigma_n
        self.sigma_over = 0          # frames whose sigma_n exceeded max_sigma_n
        self.period_sigma_max = 0.0
        self.implausible = 0         # frames the plausibility gate rejected
        self.implausible_reason = ""
        self.last_frame: float | None = None  # time.monotonic() of the latest frame
        self.arrivals: deque[float] = deque(maxlen=PERIOD_FRAMES)  # ... and of the ones before it


class _Throttle:
    """Log a repeated message at most once per :data:`LOG_EVERY` s, with how many were left out."""

    def __init__(self) -> None:
        self._last = -math.inf
        self._skipped = 0

    def __call__(self, level: int, msg: str) -> None:
        now = time.monotonic()
        if now - self._last < LOG_EVERY:
            self._skipped += 1
            return
        more = f" (and {self._skipped} more in the last {now - self._last:.0f} s)" if self._skipped else ""
        self._last, self._skipped = now, 0
        log.log(level, "%s%s", msg, more)


class Health:
    """The counts of a stream whose forces are uncertain above ``max_sigma_n`` N (0: no check)."""

    def __init__(self, max_sigma_n: float) -> None:
        self.max_sigma_n = max_sigma_n
        self.lock = threading.Lock()
        self.counts = Counts()
        self._created = time.monotonic()
        self._start = {"t": self._created, **{k: 0 for k in _TOTALS}}  # the period's start: its totals
        self._loss_history: deque = deque([(self._created, 0, {})])  # (time, frames, losses) of the periods
        self.implausible_run = 0  # implausible frames in a row so far
        self._run_said, self._run_said_at, self._runs_unsaid = False, -math.inf, 0  # the runs' log (plausible())
        self._drop_log = _Throttle()

    # --- per frame -------------------------------------------------------------------------------

    def arrived(self, late: bool) -> bool:
        """A frame arrived, ``late`` or not: counted; returns ``late``."""
        c = self.counts
        with self.lock:
            c.frames += 1
            c.last_frame = time.monotonic()
            c.arrivals.append(c.last_frame)
            c.late += late
        return late

    def plausible(self, result) -> None:
        """Under the frame lock: a result of the gate; a run of implausible ones is logged once when it
        starts and once when it ends, and runs that start within :data:`LOG_EVERY` s of a logged one not
        at all (counted, said with the next logged one): a flapping gate does not flood the log."""
        c = self.counts
        if not result.valid:
            c.implausible += 1
            c.implausible_reason = result.reason
            if not self.implausible_run:  # a run starts: said at most once per LOG_EVERY s
                now = time.monotonic()
                self._run_said = now - self._run_said_at >= LOG_EVERY
                if self._run_said:
                    more = (f" ({self._runs_unsaid} shorter runs before it not logged; /diagnostics counts them)"
                            if self._runs_unsaid else "")
                    log.warning("implausible frames (no force output): %s%s", result.reason, more)
                    self._run_said_at, self._runs_unsaid = now, 0
                else:
                    self._runs_unsaid += 1
            self.implausible_run += 1
        elif self.implausible_run:
            if self._run_said:  # its end only when its start was said
                log.warning("plausible frames again after %d implausible ones", self.implausible_run)
            self.implausible_run = 0  # implausible frames in a row so far

    def passed(self, result, seconds: float) -> None:
        """A frame went through (``result`` None: into a tare) in ``seconds``."""
        c = self.counts
        with self.lock:
            c.reject_reason = ""  # frames go through again
            if result is None or not result.valid:
                return
            c.proc_sum += seconds
            c.proc_n += 1
            c.period_proc_max = max(c.period_proc_max, seconds)
            if not math.isnan(result.residual):
                c.residual = result.residual
            c.consistency = result.consistency
            c.foreign += result.foreign_load
            sn = result.sigma_n
            c.sigma_n = sn
            if sn > c.period_sigma_max:
                c.period_sigma_max = sn
            if self.max_sigma_n and sn > self.max_sigma_n:
                c.sigma_over += 1

    def drop(self, err: BaseException, corrupt: bool = False) -> None:
        """Count and log (throttled) a frame that could not be used (:meth:`FrameStream.drop`)."""
        c = self.counts
        if corrupt:
            with self.lock:
                c.corrupt += 1
            self._drop_log(logging.WARNING, f"dropped input frame: {err}")
            return
        bug = not isinstance(err, FrameError)
        reason = f"{type(err).__name__}: {err}" if bug else str(err)
        with self.lock:
            c.rejected += 1
            c.all_excluded += isinstance(err, NoUsableChannelsError)
            c.errors += bug
            c.reject_reason = c.period_reason = reason
        if bug:
            self._drop_log(logging.ERROR, "frame dropped on an unexpected error (a bug: please report it with "
                                          f"this trace):\n{''.join(traceback.format_exception(err))}")
        else:
            self._drop_log(logging.WARNING, f"dropped frame: {reason}")

    @property
    def frame_period(self) -> float:
        """The frames' period (s) as they arrive, over the latest :data:`PERIOD_FRAMES` (an outage
        among them lengthens it); nan before 3 frames."""
        with self.lock:
            t = self.counts.arrivals
            return (t[-1] - t[0]) / (len(t) - 1) if len(t) >= 3 else math.nan

    # --- the diagnostics -------------------------------------------------------------------------

    def status(self, now: float, board_losses: dict[str, int] | None, pipe: Pipeline, excluded: tuple[list[str], dict],
               sigma_source: str, tare: tuple, slow: tuple, noise_text: str) -> tuple[int, list[str], dict]:
        """The level, problems and figures of the period so far (nothing changes). ``board_losses``: the
        board driver's running totals of lost frames by kind (corrupt, gaps, duplicates, reordered,
        overflow), None without a board; ``pipe`` the pipeline (its reference, calibration and
        foreign-load limit); ``excluded`` the channel mask's problems (WARN) and figures, ``tare`` and
        ``slow`` the (level, problems, figures) of the tare and the slow states, each in its place;
        ``sigma_source`` where the calibration residual of the sigma comes from, ``noise_text`` the
        noise in use."""
        c, s = self.counts, self._start
        with self.lock:
            totals = {k: getattr(c, k) for k in _TOTALS}
            proc_max, sigma_max, period_reason = c.period_proc_max, c.period_sigma_max, c.period_reason
            late, corrupt, sigma_n, residual, consistency = c.late, c.corrupt, c.sigma_n, c.residual, c.consistency
            kv_rejected = {"frames_rejected": c.rejected, "frames_all_excluded": c.all_excluded,
                           "frame_errors": c.errors, "reject_reason": c.reject_reason}
            imp_reason = c.implausible_reason
        d = {k: totals[k] - s[k] for k in _TOTALS}
        rate = d["frames"] / max(now - s["t"], 1e-9)
        proc_n = d["proc_n"]
        kv = {"frames": totals["frames"], "frame_rate_hz": f"{rate:.1f}", "late_dropped": late}
        level, msgs = OK, []
        losses = self._losses(corrupt, late, board_losses)
        kv["corrupt"] = losses["corrupt"]
        loss_level, loss_msg = self._loss_level(now, totals["frames"], losses)
        if loss_msg:
            level = max(level, loss_level)
            msgs.append(loss_msg)
        kv.update(kv_rejected)
        if d["rejected"] > 0:
            level = max(level, WARN)
            msgs.append(f"{d['rejected']} frames rejected ({period_reason})")
        if excluded[0]:
            level = max(level, WARN)
            msgs += excluded[0]
        kv.update(excluded[1])
        imp = totals["implausible"]
        new_imp = d["implausible"] if d["implausible"] >= 0 else imp
        kv.update(implausible=imp, implausible_reason=imp_reason)
        if new_imp:
            level = max(level, WARN)
            msgs.append(f"{new_imp} implausible frames not published ({imp_reason})")
        kv.update(consistency=f"{consistency:.4g}", foreign_load_frames=totals["foreign"])
        if d["foreign"]:
            level = max(level, WARN)
            msgs.append(f"foreign load: {d['foreign']} frames not explained by a load on the socket (consistency "
                        f"{consistency:.3g}, limit {pipe.consistency.threshold:g}); something else presses the "
                        "sensor or an electrode changed; forces still published")
        bound = self.max_sigma_n
        kv.update(sigma_n=f"{sigma_n:.4g}", sigma_n_period_max=f"{sigma_max:.4g}",
                  max_sigma_n=f"{bound:g}" if bound else "0 (no check)", sigma_over_frames=totals["sigma_over"],
                  sigma_calibration=sigma_source)
        if bound and d["sigma_over"]:
            level = max(level, WARN)
            msgs.append(f"uncertain forces: {d['sigma_over']} frames with a 1-sigma above max_sigma_n {bound:g} N "
                        f"(largest {sigma_max:.3g} N): the noise, the device's untracked change (a long load "
                        "since the last rest) or the calibration; forces still published")
        proc_mean = d["proc_sum"] / proc_n if proc_n else math.nan
        kv.update(residual="" if math.isnan(residual) else f"{residual:.4g}",  # none before a stress field
                  processing_time_mean_ms=f"{proc_mean * 1e3:.3f}",
                  processing_time_max_ms=f"{(proc_max if proc_n else math.nan) * 1e3:.3f}")
        level = max(level, self._part(tare, msgs, kv))
        report = pipe.scale_report
        if report is not None:
            kv.update(reference_scale=f"{report.factor:.4g}", reference_unexplained=f"{report.unexplained:.4f}",
                      noise=noise_text)
            if report.warn:
                level = max(level, WARN)
                msgs.append(report.message)
        cal = pipe.calibration
        kv.update(calibration=cal.path if cal else "none (nominal model)", calibration_accuracy=cal.accuracy if cal else "")
        return max(level, self._part(slow, msgs, kv)), msgs, kv

    @staticmethod
    def _part(part: tuple[int, list[str], dict], msgs: list[str], kv: dict) -> int:
        """A stage's (level, problems, figures) into ``msgs`` and ``kv``; its level."""
        msgs += part[1]
        kv.update(part[2])
        return part[0]

    def end_period(self, now: float, board_losses: dict[str, int] | None = None) -> None:
        """The period ends at ``now``: the next :meth:`status` counts from here (the losses of
        ``board_losses`` join the :data:`LOSS_WINDOW`)."""
        c = self.counts
        with self.lock:
            self._start = {"t": now, **{k: getattr(c, k) for k in _TOTALS}}
            c.period_proc_max = c.period_sigma_max = 0.0
            c.period_reason = ""
            losses, frames = self._losses(c.corrupt, c.late, board_losses), c.frames
        hist = self._loss_history
        hist.append((now, frames, losses))
        while len(hist) > 2 and now - hist[1][0] >= LOSS_WINDOW:
            hist.popleft()

    @staticmethod
    def _losses(corrupt: int, late: int, board_losses: dict[str, int] | None) -> dict:
        losses = {"corrupt": corrupt, "late": late}
        if board_losses is not None:
            losses.update(board_losses, corrupt=corrupt + board_losses.get("corrupt", 0))
        return losses

    def _loss_level(self, now: float, frames: int, losses: dict) -> tuple[int, str]:
        """The level and message of the frames lost or dropped over the last :data:`LOSS_WINDOW` s
        (``losses``: running totals by kind, now); WARN above :data:`LOSS_WARN`, ERROR above
        :data:`LOSS_ERROR` of the frames the board sent meanwhile."""
        hist = list(self._loss_history)
        while len(hist) > 1 and now - hist[1][0] >= LOSS_WINDOW:
            hist.pop(0)
        t0, f0, old = hist[0]
        d = {k: v - old.get(k, 0) for k, v in losses.items()}
        lost = sum(d.values())
        sent = frames - f0 + lost - d["late"]  # late frames were received (and counted in frames)
        if lost <= 0 or sent <= 0 or lost <= LOSS_WARN * sent:
            return OK, ""
        level = ERROR if lost > LOSS_ERROR * sent else WARN
        parts = ", ".join(f"{k} {v}" for k, v in d.items() if v)
        return level, f"{lost} of {sent} frames lost or dropped in the last {now - t0:.0f} s ({parts})"
