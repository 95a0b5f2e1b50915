"""The frame stream of one sensor: everything that happens to its frames between the board and the
outputs and needs state from frame to frame. No ROS, no serial.

The node (``ros/node.py``), ``cstomo replay`` and ``cstomo estimate`` all push their frames through a
:class:`FrameStream` and only turn what it emits into messages or rows, so they cannot disagree. It
owns, per sensor:

- the reference and the tare transaction with its rules (:data:`TARE_MAX_SPREAD`, a saved tare that
  is not of this sensor: :func:`tare_problem`, never a tare under load: :mod:`.tare`), the saved tare
  file, and the masks of flagged channels;
- the per-frame core (:class:`~.pipeline.Pipeline`: plausibility gate, estimator, consistency, fields);
- the filtered wrench (:class:`~.filter.LowPass`, reset on a tare, a reconnect and gaps);
- the zero that holds: the device's slow change since the tare (:class:`~.drift.DriftTracker`,
  ``drift_tracking``), followed frame by frame and applied by the pipeline;
- the noise the estimators use when the reference measured none (a one-frame reference): estimated
  from consecutive frames (:class:`~.noise.NoiseEstimate`, ``noise_estimation``) and handed to the
  pipeline now and then, or from a whole frames file first (:meth:`FrameStream.estimate_noise`);
- the accounting: frames, late frames, dropped frames and why, implausible and foreign-load frames,
  the processing time, and the losses over the last :data:`LOSS_WINDOW` s;
- the set of outputs a configuration produces (:data:`OUTPUTS`, :func:`output_set`): the node's
  publishers, replay's topics and the node's ``--help`` all come from it.

Why a module of ``force/`` and not a layer of its own: it needs nothing but the force layer (the
pipeline, the filter, the device's reference files), and the board's and ROS's layers above it use it.

Frames are pushed with a stamp (ns, the time the frame was measured on the caller's clock: the
filter runs on it) and an age (ns, how long ago it was measured on the monotonic clock: older than
``stale_timeout`` is late). A frame the stream cannot use (wrong length, NaN in a used channel, every
channel excluded, an unexpected error) is dropped and counted, and logged at most every
:data:`LOG_EVERY` s, never raised to the caller.
"""
from __future__ import annotations

import logging
import math
import threading
import time
import traceback
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from ..angles import force_angles3
from ..errors import ConfigError, CstomoError, FrameError, NoUsableChannelsError
from ..frames_io import check_frame
from ..model.pattern import MeasurementPattern
from .creep import DEFAULT_CREEP, CreepCompensator, creep_problem
from .device import read_reference, write_reference
from .drift import EXPECTED_HOLD, DriftTracker, JointScale, gradient_directions
from .filter import LowPass
from .noise import AGREE_FRACTION, MIN_PAIRS, RETUNE, SAMPLE_EVERY, UPDATE_EVERY, NoiseEstimate, noise_level, snr_db
from .pipeline import NOISE_ASSUMED, FrameResult, Pipeline
from .scene_field import change_noise
from .sigma import CREEP_REL_ASSUMED, CREEP_REL_FITTED, ForceSigma, relative_error
from .tare import TareCheck, check_tare

log = logging.getLogger(__name__)

#: Diagnostic levels (the values of diagnostic_msgs/DiagnosticStatus).
OK, WARN, ERROR = 0, 1, 2

#: Every output a stream can produce, in publishing order: name -> what it holds. The node publishes
#: each as ``~/<name>``, replay writes each as a topic, ``cstomo_sensor_node --help`` lists them.
OUTPUTS: dict[str, str] = {
    "wrench": "geometry_msgs/WrenchStamped: the force on the socket (N) in frame_id, zero torque",
    "wrench_sigma": "geometry_msgs/Vector3Stamped: the 1-sigma uncertainty (N) of the wrench's fx, fy, fz, "
                    "under the wrench's stamp and frame_id (force/sigma.py)",
    "wrench_filtered": "the wrench through a first-order low-pass (wrench_filter_hz; none when 0)",
    "force_magnitude": "std_msgs/Float64: |F| (N)",
    "force_elevation": "std_msgs/Float64: the force's elevation (rad)",
    "force_azimuth": "std_msgs/Float64: the force's azimuth (rad)",
    "consistency": "std_msgs/Float64: how well the frame fits a load on the socket (above its limit: "
                   "a foreign load)",
    "stress_field": "sensor_msgs/PointCloud2: the EIT image (conductivity change, compression, pressure) "
                    "every stress_field_every frames (none when 0)",
    "scene_stress_field": "sensor_msgs/PointCloud2: the mechanics' field of the estimated force, with "
                          "stress_field (socket sensors)",
}

#: Largest tare spread accepted: max over the used channels of std / rms(reference) of the tare
#: frames. 60 dB noise (std 0.1 % of rms) gives 0.15..0.35 % over 208 channels (2..50 frames); a
#: 20 N socket load moves a channel by up to 5.7 % of rms, so one arriving in the middle 80 % of
#: a tare gives 1.7 % or more.
TARE_MAX_SPREAD = 0.01
#: On a noisy board the limit is this many times the median channel's spread instead, when larger: a
#: 40 dB board (docs/physics.md#real-devices) has a std of 1 % of rms on every channel, and a load
#: arriving during the tare still shows as channels far noisier than the typical one (use >= 10 tare
#: frames there).
TARE_NOISE_FACTOR = 3.0
#: A saved tare whose rms lies outside these multiples of the model reference's rms is not a frame of
#: this sensor: voltages scale with the rubber's resistivity, 0.2..5 times nominal
#: (docs/physics.md#real-devices).
TARE_RMS_RATIO = (0.2, 5.0)
#: Why a pending tare ends when the board comes back after an outage (:meth:`FrameStream.reconnected`).
TARE_RECONNECTED = ("tare refused: the board reconnected during the tare (its frames would span an outage, "
                    "and the joint may be loaded when the board returns)")
#: Seconds over which lost and dropped frames are judged, and the fractions of the frames sent in
#: that time above which the status is WARN and ERROR.
LOSS_WINDOW = 5.0
LOSS_WARN = 0.01
LOSS_ERROR = 0.2
#: A repeated per-frame message (a dropped frame, a corrupt input) is logged at most once per this
#: many seconds, with the count of the ones left out.
LOG_EVERY = 5.0
#: A tare's deadline (:meth:`FrameStream.tare_deadline`): its frames at this many times the frame
#: period, plus ``stale_timeout`` and :data:`TARE_GRACE` s; the period is measured over the latest
#: :data:`PERIOD_FRAMES` frames (at least 3), else the nominal rate's, else
#: :data:`TARE_ASSUMED_PERIOD` s with no margin.
TARE_PERIOD_MARGIN = 1.5
TARE_GRACE = 2.0
TARE_ASSUMED_PERIOD = 0.1
PERIOD_FRAMES = 32


@dataclass(frozen=True)
class StreamConfig:
    """Every setting of the frame stream: the one source of their defaults (the node's parameters
    and the command line take theirs from here)."""

    tare_frames: int = 50
    tare_max_spread: float = TARE_MAX_SPREAD
    stress_field_every: int = 10  # attach the fields to every N-th processed frame (the first included); 0 never
    wrench_filter_hz: float = 20.0  # 0 = no filtered wrench
    stale_timeout: float = 0.5  # s: a frame older is late (dropped); a gap longer restarts the filter
    drift_tracking: bool = True  # follow the device's slow uniform change after the tare (force/drift.py)
    creep_per_decade: float = DEFAULT_CREEP  # the rubber's creep (force/creep.py) unless the calibration has it; 0 off
    noise_estimation: bool = True  # a reference without a measured noise: estimate it from the frames (force/noise.py)
    # N: a frame whose force's 1-sigma (sigma_n, force/sigma.py) exceeds it is said in the diagnostics
    # (above a 40 dB board's noise alone, ~1.9 N); 0 off
    max_sigma_n: float = 5.0

    def __post_init__(self) -> None:
        if isinstance(self.tare_frames, bool) or not self.tare_frames >= 1:
            raise ConfigError.bad_value("tare_frames", self.tare_frames, ">= 1")
        if not self.tare_max_spread > 0:
            raise ConfigError.bad_value("tare_max_spread", self.tare_max_spread, "> 0 (a fraction of the reference rms)")
        if not self.stress_field_every >= 0:
            raise ConfigError.bad_value("stress_field_every", self.stress_field_every, ">= 0 (0 = off)")
        if not (math.isfinite(self.wrench_filter_hz) and self.wrench_filter_hz >= 0):
            raise ConfigError.bad_value("wrench_filter_hz", self.wrench_filter_hz, ">= 0 Hz (0 = off)")
        if not self.stale_timeout > 0:
            raise ConfigError.bad_value("stale_timeout", self.stale_timeout, "> 0 s")
        if not (math.isfinite(self.max_sigma_n) and self.max_sigma_n >= 0):
            raise ConfigError.bad_value("max_sigma_n", self.max_sigma_n, ">= 0 N (0 = no check)")
        why = creep_problem(self.creep_per_decade)
        if why:
            raise ConfigError.bad_value("creep_per_decade", self.creep_per_decade, why)


def output_set(config: StreamConfig, scene_field: bool) -> tuple[str, ...]:
    """The outputs a stream with ``config`` produces (a subset of :data:`OUTPUTS`, in its order);
    ``scene_field``: the pipeline has the mechanics' field (a socket sensor)."""
    off = set()
    if not config.wrench_filter_hz:
        off.add("wrench_filtered")
    if not config.stress_field_every:
        off |= {"stress_field", "scene_stress_field"}
    if not scene_field:
        off.add("scene_stress_field")
    return tuple(n for n in OUTPUTS if n not in off)


def tare_problem(ref: np.ndarray, model_reference: np.ndarray) -> str:
    """Why the saved tare ``ref`` (n_meas,) is implausible for a model whose reference is
    ``model_reference``; '' if it is plausible."""
    if not np.all(np.isfinite(ref)):
        return "it holds non-finite values"
    if not np.any(ref):
        return "all its values are zero"
    ratio = float(np.sqrt(np.mean(ref**2)) / np.sqrt(np.mean(model_reference**2)))
    lo, hi = TARE_RMS_RATIO
    if not lo <= ratio <= hi:
        return (f"its rms is {ratio:.3g} times the model reference's, outside {lo:g}..{hi:g} (a rubber "
                "within the real-device ranges of docs/physics.md); a tare of another sensor or board?")
    return ""


@dataclass(frozen=True)
class Excluded:
    """Channels excluded from the reconstruction by the latest frame's status flags."""

    saturated: int = 0
    dead_electrodes: tuple[int, ...] = ()
    channels: int = 0


@dataclass(frozen=True)
class TareOutcome:
    """How a tare ended: ``reference`` (208,) if accepted, else None and ``reason`` says why.

    ``spread`` is the steadiness figure of :data:`TARE_MAX_SPREAD` (0.0 for a one-frame tare);
    ``noise`` (208,) volts the per-channel std of the frames (None for a one-frame tare); ``note``
    says why an accepted tare was not saved ('' when saved or when the stream has no file);
    ``check`` the load figures (:class:`~.tare.TareCheck`; None when the tare ended before them);
    ``forced`` a forced tare, and ``overridden`` what it overrode ('' when nothing).
    """

    reference: np.ndarray | None
    frames: int
    spread: float
    reason: str = ""
    noise: np.ndarray | None = None
    note: str = ""
    check: TareCheck | None = None
    forced: bool = False
    overridden: str = ""

    @property
    def ok(self) -> bool:
        return self.reference is not None


@dataclass
class Output:
    """What one processed frame emits: the result, the filtered force (None without the filter) and
    the frame's stamp (ns)."""

    result: FrameResult
    filtered: tuple[float, float, float] | None
    stamp_ns: int


class _Counts:
    """The stream's counters (guarded by the stream's ``counts_lock``); ``period_*`` are reset by
    :meth:`FrameStream.health`."""

    def __init__(self) -> None:
        self.frames = 0          # frames pushed (all time)
        self.period_frames = 0
        self.corrupt = 0         # input messages that were no frame (counted by the caller: drop(corrupt=True))
        self.rejected = 0        # frames dropped by the frame path, all causes
        self.all_excluded = 0    # ... of which every measurement was excluded by the board's flags
        self.errors = 0          # ... of which an unexpected exception (a bug) was the cause
        self.reject_reason = ""  # why the latest frame was dropped; '' once a frame goes through
        self.period_reason = ""
        self.late = 0            # frames older than stale_timeout (dropped)
        self.proc_sum = 0.0
        self.proc_max = 0.0
        self.proc_n = 0
        self.residual = math.nan
        self.consistency = math.nan
        self.foreign = 0
        self.period_foreign = 0
        self.sigma_n = math.nan      # the latest published frame's sigma_n
        self.sigma_over = 0          # frames whose sigma_n exceeded max_sigma_n (all time)
        self.period_sigma_over = 0
        self.period_sigma_max = 0.0
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


class FrameStream:
    """The frame stream of one sensor (module docstring).

    Parameters
    ----------
    pipe : Pipeline
        The per-frame core (its reference and mask are set here).
    config : StreamConfig
    on_tare : callable or None
        Called with the :class:`TareOutcome` when a tare ends, accepted or refused, outside the frame
        lock (an accepted tare with a ``tare_file``: once written, by the thread that writes it).
    tare_file : path or None
        Where an accepted tare is saved (frames file and its noise beside it, atomically, by a thread
        of its own: frames never wait for the disk), and read back by :meth:`init_reference`; None:
        not saved.
    tare_comment : str
        The first comment line of a saved tare (sensor, geometry digest).
    started : float or None
        ``time.monotonic()`` of the start the tare's log counts from (the node's; None: now).

    Tare semantics (the same everywhere): while a tare is pending (at start without a usable saved
    tare, ``tare_on_start``, :meth:`tare`, or replay without a reference), the next ``tare_frames``
    usable frames are averaged into the reference and give no output. A tare is refused (the old
    reference and the saved file stay) when its frames are not steady: the largest per-channel
    standard deviation over the channels not excluded during the tare, relative to the rms of the
    averaged reference, is above ``tare_max_spread`` (or :data:`TARE_NOISE_FACTOR` x the median
    channel's, when larger: a noisy board); when the average is not finite or not a frame of this
    sensor (:func:`tare_problem`); when it carries a load against the reference it replaces, or the
    load changed along its frames (a slow ramp: :mod:`.tare`, unless the tare is ``forced``); or when
    the board reconnected while it was pending (:meth:`reconnected`). Without any reference a tare is
    always pending: a refused or cancelled one starts over.
    """

    def __init__(self, pipe: Pipeline, config: StreamConfig = StreamConfig(),
                 on_tare: Callable[[TareOutcome], None] | None = None,
                 tare_file: str | Path | None = None, tare_comment: str = "", started: float | None = None) -> None:
        self.pipe = pipe
        self.config = config
        self.on_tare = on_tare
        self.tare_file = Path(tare_file) if tare_file else None
        self.tare_comment = tare_comment
        self.outputs = output_set(config, pipe.scene_field is not None)
        self.lock = threading.Lock()  # one frame at a time; a tare is started and ended under it
        self.counts_lock = threading.Lock()
        self.counts = _Counts()
        self.filter = LowPass(config.wrench_filter_hz, max_gap=config.stale_timeout) if config.wrench_filter_hz else None
        self.drift: DriftTracker | None = None  # made with each reference (drift_tracking)
        self.creep: CreepCompensator | None = None  # made with each reference (creep_per_decade)
        self._offset = np.zeros(pipe.n_meas)  # the drift's and the creep's offsets, summed
        self._gradients: np.ndarray | None = None  # the tracker's gradient directions (the model's)
        n_el = len(pipe.geometry.electrodes)
        pattern = MeasurementPattern(n_el, pipe.geometry.layers)
        self._electrode_rows = np.stack([pattern.electrode_rows(e) for e in range(n_el)])
        self._mask = pipe.bad_channels.copy()  # always the pipeline's own mask
        self._all_good = np.ones(n_el, bool)
        self.excluded = Excluded(channels=int(self._mask.sum()))
        self.processed = 0
        self.implausible = 0  # frames the plausibility gate rejected (all time)
        self.implausible_reason = ""
        self._implausible_run = 0
        self._tare_x0 = np.zeros(pipe.n_meas)   # first tare frame (sums are taken around it)
        self._tare_s1 = np.zeros(pipe.n_meas)
        self._tare_s2 = np.zeros(pipe.n_meas)
        self._tare_d = np.zeros(pipe.n_meas)
        self._tare_st = np.zeros(pipe.n_meas)  # sum of k * (frame k - first frame): the linear trend
        self._tare_forced = False
        self._tare_mask = np.zeros(pipe.n_meas, bool)
        self._tare_left = self._tare_n = 0
        self._tare_over = threading.Event()  # the transaction's tare ended (accepted or refused)
        self._tare_done = threading.Event()  # ... and was reported (an accepted one saved, or not)
        self._writers: list[threading.Thread] = []  # tare files being written (close() waits for them)
        self._tare_ended: TareOutcome | None = None
        self._ended: deque[tuple[TareOutcome, int]] = deque()  # ended, to save (the save's number) and report
        self._saves = 0  # accepted tares handed to a writer thread
        self._save_lock = threading.Lock()  # one write at a time
        self.tare_unsaved = ""  # why the latest accepted tare was not saved ('' when it was)
        self.reference_source = "none"
        self.tare_taken = ""    # when the reference in use was tared
        self.tare_refused = ""  # the latest refused tare: when and why
        self._created = self._last_health = time.monotonic()
        self._t_start = self._created if started is None else started
        self._loss_history: deque = deque()
        self._last_rejected = self._last_implausible = 0
        self._drop_log = _Throttle()
        self.noise = NoiseEstimate(pipe.n_meas) if config.noise_estimation else None  # None: not estimated
        self._noise_level: float | None = None  # the estimated level in use (volts)
        self._noise_from = ""  # ... and what it was estimated from
        self._noise_next = MIN_PAIRS  # the pair count at which the estimate is evaluated next
        self._noise_note = ""  # why no estimate is in use yet
        self._sigma: ForceSigma | None = None  # the force's uncertainty (force/sigma.py), for _sigma_for
        self._sigma_for: tuple = (None,) * 4  # ... made for this estimator, tracker, creep and calibration
        self.sigma_source = ""  # where the calibration residual of the sigma comes from
        self._joint: JointScale | None = None  # the joint fit of the scale (issue 26 item 2), for _joint_for
        self._joint_for: DriftTracker | None = None
        self._expected: tuple | None = None  # a controller's expected load (force, sigma, t): expect_load

    def with_config(self, **changes) -> None:
        """Change settings that may change while running (``stale_timeout``)."""
        self.config = replace(self.config, **changes)
        if self.filter is not None:
            self.filter.max_gap = self.config.stale_timeout

    # --- reference -------------------------------------------------------------------------------

    def use_reference(self, path: str | Path, what: str = "reference") -> str:
        """Use the reference file ``path`` (mean of its rows, or a saved tare with its noise and frame
        count): :meth:`set_reference` of what :func:`~.device.read_reference` reads."""
        return self.set_reference(*read_reference(path, self.pipe.n_meas), source=f"{what} {path}")

    def set_reference(self, ref: np.ndarray, noise: np.ndarray | None, n_frames: int, source: str,
                      age_s: float | None = None) -> str:
        """Use ``ref`` (n_meas,) volts, the mean of ``n_frames`` unloaded frames of per-channel ``noise``
        (None: assumed), if it is a plausible frame of this sensor (:func:`tare_problem`); returns the
        tare report's message. Raises :class:`ConfigError` naming ``source`` and what is wrong."""
        why = tare_problem(ref, self.pipe.model_reference)
        if why:
            raise ConfigError(f"{source} not used: {why}")
        report = self.pipe.set_reference(ref, noise, n_frames)
        self._keep_estimate()
        self._new_drift()
        if age_s is not None and self.drift is not None:  # issue 26: a restart from a saved tare of this age
            self.drift.widen(age_s)
        self.reference_source = source
        (log.warning if report.warn else log.info)("%s: mean of %d frame(s), noise %s; %s", source, n_frames,
                                                   self.noise_text, report.message)
        return report.message

    def init_reference(self, tare_on_start: bool) -> str:
        """The saved tare (``tare_file``) if usable, else a tare on the first frames (``tare_on_start``
        always tares): no force is ever computed against the model's own reference frame, which is
        not the device's (a phantom force of several newtons at zero load). Returns '' when the saved
        tare is used, else why a tare is pending."""
        self.tare_taken = self.tare_refused = ""
        path = self.tare_file
        why = "tare_on_start is true"
        if not tare_on_start:
            why = f"no saved tare of this device at {path}"
            if path is not None and path.is_file():
                try:
                    saved = read_reference(path, self.pipe.n_meas)
                except (CstomoError, OSError) as err:
                    why = f"saved tare {path} unusable ({err})"
                else:
                    try:
                        # the device moved since the tare was saved: its age (the file's time) widens the
                        # drift tracker's states (issue 26, force/drift.py DriftTracker.widen)
                        age = max(time.time() - path.stat().st_mtime, 0.0)
                        self.set_reference(*saved, source=f"saved tare {path}", age_s=age)
                        return ""
                    except ConfigError as err:
                        why = str(err)
        self.start_tare()
        self.reference_source = "tare pending"
        return why

    def start_tare(self, n_frames: int | None = None) -> None:
        """Average the next ``n_frames`` (default ``tare_frames``) frames into the reference."""
        n = self.config.tare_frames if n_frames is None else n_frames
        if isinstance(n, bool) or n < 1:
            raise ConfigError.bad_value("tare_frames", n, ">= 1")
        self._tare_left = self._tare_n = int(n)
        self._tare_forced = False
        if self.noise is not None:
            self.noise.restart()  # no frame pair across the tare

    def joint_free(self) -> bool:
        """A controller's hint that the joint is free now: re-zero at once, a tare on the next
        ``tare_frames`` frames with every rule of a tare (steady frames, no load against the reference
        it replaces, no ramp): refused under load like any tare. False (and nothing changes) while a
        tare is already pending."""
        with self.lock:
            if self._tare_left:
                return False
            self.start_tare()
        log.info("the joint is free (a controller's hint): re-zeroing on the next %d frames", self.config.tare_frames)
        return True

    def reconnected(self) -> None:
        """The board came back after an outage: the filtered wrench starts again from the next frame,
        and a pending tare ends, never completed on the returning frames (the joint may be loaded by
        then): refused with :data:`TARE_RECONNECTED` (a :meth:`tare` transaction returns that outcome;
        without any reference the tare starts over on the returning frames, all of them checked)."""
        with self.lock:
            if self.filter is not None:
                self.filter.reset()
            if self.noise is not None:
                self.noise.restart()  # no frame pair across the outage
            if self._tare_left:
                taken = self._tare_n - self._tare_left
                self._tare_left = 0
                self._end_tare(TareOutcome(None, taken, 0.0, TARE_RECONNECTED))
        self._finish_tares()

    def cancel_tare(self) -> int:
        """Drop a pending tare (the reference stays as it is); returns the frames it had taken.

        Without any reference the tare stays pending (see the class docstring)."""
        taken = self._tare_n - self._tare_left if self._tare_left else 0
        self._tare_left = 0 if self.pipe.reference is not None else self._tare_n
        self._tare_forced = False
        return taken

    @property
    def frame_period(self) -> float:
        """The frames' period (s) as they arrive, over the latest :data:`PERIOD_FRAMES` (an outage
        among them lengthens it); nan before 3 frames."""
        with self.counts_lock:
            t = self.counts.arrivals
            return (t[-1] - t[0]) / (len(t) - 1) if len(t) >= 3 else math.nan

    def tare_deadline(self, rate_hz: float = 0.0) -> float:
        """Seconds a tare of ``tare_frames`` frames may take (:data:`TARE_PERIOD_MARGIN`): from the
        measured :attr:`frame_period`, never shorter than the nominal ``rate_hz``'s (0: unknown)."""
        period = self.frame_period
        if rate_hz > 0:  # a backlog drained at once measures short: never shorter than the nominal rate's
            period = max(period, 1.0 / rate_hz) if period > 0 else 1.0 / rate_hz
        per_frame = TARE_PERIOD_MARGIN * period if period > 0 else TARE_ASSUMED_PERIOD
        return self.config.tare_frames * per_frame + self.config.stale_timeout + TARE_GRACE

    def tare(self, timeout: float, forced: bool = False) -> tuple[TareOutcome | None, int]:
        """A tare transaction: start a tare on the next frames and wait up to ``timeout`` s
        (:meth:`tare_deadline`) for it to end (accepted or refused); if it has not ended by then it is
        cancelled (decided under the frame lock: a tare cannot end while it is cancelled). An
        accepted tare is saved outside the frame lock (frames keep flowing): the transaction waits up
        to ``timeout`` s more for the save, and the outcome's ``note`` says when it is still under
        way. ``forced``: the load checks (:mod:`.tare`) do not refuse it; the outcome says what they
        would have refused (the steadiness and the other checks still apply). Returns (the outcome or
        None if cancelled, the frames it had taken)."""
        with self.lock:
            self._tare_over.clear()
            self._tare_done.clear()
            self._tare_ended = None
            self.start_tare()
            self._tare_forced = bool(forced)
        self._tare_over.wait(timeout)
        with self.lock:
            ended = self._tare_ended
            taken = self.cancel_tare() if ended is None else ended.frames
        if ended is None:
            return None, taken
        if not self._tare_done.wait(timeout):
            return replace(ended, note=f"tare in use, still being saved to {self.tare_file} (a slow disk?): "
                                       "the diagnostics' reference says when it is saved"), taken
        with self.lock:
            return self._tare_ended, taken

    @property
    def taring(self) -> bool:
        return self._tare_left > 0

    @property
    def ready(self) -> bool:
        """A reference is set and no tare is pending: frames give results."""
        return not self.taring and self.pipe.reference is not None

    def _add_tare_frame(self, v: np.ndarray, mask: np.ndarray) -> TareOutcome | None:
        if self._tare_left == self._tare_n:  # the first frame
            self._tare_x0[:] = v
            self._tare_s1[:] = 0.0
            self._tare_s2[:] = 0.0
            self._tare_st[:] = 0.0
            self._tare_mask[:] = mask
        self._tare_mask |= mask
        np.subtract(v, self._tare_x0, out=self._tare_d)
        self._tare_s1 += self._tare_d
        self._tare_st += (self._tare_n - self._tare_left) * self._tare_d
        self._tare_d **= 2
        self._tare_s2 += self._tare_d
        self._tare_left -= 1
        if self._tare_left:
            return None
        n = self._tare_n
        ref = self._tare_x0 + self._tare_s1 / n
        spread = 0.0
        noise = None
        used = ~self._tare_mask
        rms = float(np.sqrt(np.mean(ref[used] ** 2))) if used.any() else 0.0
        if n > 1 and rms > 0:
            var = np.maximum(self._tare_s2 - self._tare_s1**2 / n, 0.0) / (n - 1)
            spread = float(np.sqrt(var[used].max()) / rms)
            noise = np.sqrt(var)
            noise[~used | ~np.isfinite(noise)] = float(np.median(noise[used]))  # excluded: no data
        if not np.isfinite(ref).all() or not rms > 0 or not np.isfinite(spread):
            return TareOutcome(None, n, spread, "tare refused: the averaged frames hold NaN/Inf or no usable "
                                                "channel; check the board's contacts and cable")
        limit = self.config.tare_max_spread
        if noise is not None:
            limit = max(limit, TARE_NOISE_FACTOR * float(np.median(noise[used])) / rms)
        if spread > limit:
            worst = int(np.argmax(np.where(used, var, -1.0))) + 1
            return TareOutcome(None, n, spread, f"tare refused: frames not steady (spread {spread:.2%} of the "
                                                f"reference rms at measurement {worst}, limit "
                                                f"{limit:.2%}); keep the sensor still and unloaded "
                                                "during the tare")
        why = tare_problem(ref[used], self.pipe.model_reference[used])  # flagged channels hold no data
        if why:
            return TareOutcome(None, n, spread, f"tare refused: {why}")
        drift = None
        if n >= 3:  # the linear trend's change from the first frame to the last, per channel
            stt = n * (n * n - 1) / 12.0
            drift = (self._tare_st - 0.5 * (n - 1) * self._tare_s1) / stt * (n - 1)
        check = check_tare(self.pipe, ref, drift, noise, n, used)
        problems = check.problems()
        if problems and not self._tare_forced:
            return TareOutcome(None, n, spread, f"tare refused: {'; '.join(problems)}; tare with the joint "
                                                f"unloaded and still", noise=noise, check=check)
        return TareOutcome(ref.copy(), n, spread, noise=noise, check=check, forced=self._tare_forced,
                           overridden="; ".join(problems))

    def _end_tare(self, outcome: TareOutcome) -> None:
        """A tare ended (under the frame lock): an accepted one is the reference from the next frame.
        Saving it and reporting it (:meth:`_finish_tares`) wait until the lock is released."""
        when = time.strftime("%H:%M:%S")
        self._tare_forced = False
        if outcome.ok:
            report = self.pipe.set_reference(outcome.reference, outcome.noise, outcome.frames)
            self._keep_estimate()
            self._new_drift()
            self.tare_taken = f"{when}, {time.monotonic() - self._t_start:.1f} s after start, " \
                              f"{outcome.frames} frames, spread {outcome.spread:.2%}" + \
                              (", forced" if outcome.forced else "")
            log.info("tare taken at %s (noise %s; %s)", self.tare_taken, self.noise_text,
                     outcome.check.summary() if outcome.check is not None else "no load check")
            if outcome.forced:
                log.warning("forced tare: %s", f"overrode: {outcome.overridden}" if outcome.overridden else
                            "the load checks passed anyway")
            (log.warning if report.warn else log.info)("tare: %s", report.message)
            self.reference_source = "tare" if self.tare_file is None else f"tare, being saved to {self.tare_file}"
            if self.filter is not None:
                self.filter.reset()  # a new reference: the filtered wrench starts again from the next frame
        else:
            self.tare_refused = f"{when}: {outcome.reason}"
            if self.pipe.reference is None:
                log.warning("%s; no reference yet: taring again on the next %d frames", outcome.reason, self._tare_n)
                self.start_tare(self._tare_n)
            else:
                log.warning("%s; the previous reference stays", outcome.reason)
        if outcome.ok and self.tare_file is not None:
            self._saves += 1
        self._tare_ended = outcome
        self._tare_over.set()
        self._ended.append((outcome, self._saves if outcome.ok else 0))

    def _finish_tares(self) -> None:
        """Save and report the tares that ended, outside the frame lock (called by :meth:`process`,
        :meth:`push` and :meth:`reconnected` once they released it): an accepted tare is written by a
        thread of its own, so frames keep flowing while a slow or hung disk writes it."""
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
        """Wait up to ``timeout`` s for the tare files still being written (a node that stops or
        reconfigures keeps the tare it took); returns the files not written by then (a hung disk)."""
        self._finish_tares()
        deadline = time.monotonic() + timeout
        for w in self._writers:
            w.join(max(0.0, deadline - time.monotonic()))
        late = [str(self.tare_file) for w in self._writers if w.is_alive()]
        if late:
            log.error("tare not saved to %s within %.0f s (a hung disk?): the next start reads the older tare",
                      self.tare_file, timeout)
        return late

    def _report(self, outcome: TareOutcome, note: str = "") -> None:
        """The end of a tare, final (``note``: why an accepted one was not saved): to the :meth:`tare`
        transaction waiting for it and to ``on_tare``."""
        final = replace(outcome, note=note) if note else outcome
        with self.lock:
            if self._tare_ended is outcome:
                self._tare_ended = final
                self._tare_done.set()
        if self.on_tare is not None:
            self.on_tare(final)

    def _save(self, outcome: TareOutcome, seq: int) -> None:
        """Write an accepted tare to ``tare_file`` (atomically) with its noise beside it, then report it
        with '' or why it was not saved as its ``note`` (logged at ERROR and shown in the diagnostics
        until a tare is saved). The writer thread of :meth:`_finish_tares`; ``seq``: a later tare
        replaces an earlier one whose write has not started."""
        path, note = self.tare_file, ""
        with self._save_lock:
            if seq == self._saves:
                try:
                    path.parent.mkdir(parents=True, exist_ok=True)
                    write_reference(path, outcome.reference, outcome.noise, frames=outcome.frames,
                                    comment=f"{self.tare_comment}: mean of {outcome.frames} frames, "
                                            f"{time.strftime('%Y-%m-%dT%H:%M:%S%z')}")
                except OSError as err:
                    note = f"tare in use but not saved to {path} ({err}): fix tare_file and tare again"
                    log.error("%s", note)
                else:
                    log.info("tare saved to %s", path)
                if seq == self._saves:  # still the newest tare
                    self.tare_unsaved = note
                    self.reference_source = f"tare, not saved to {path}" if note else f"tare saved to {path}"
            else:
                note = f"tare in use, not saved: a later tare replaced it in {path}"
        self._report(outcome, note)

    def _new_drift(self) -> None:
        """A drift tracker (``drift_tracking``) and a creep compensator for the reference just set."""
        pipe = self.pipe
        self.drift = self.creep = None
        if pipe.reference is None:
            return
        if self.config.drift_tracking:
            est = pipe.estimator
            if self._gradients is None:  # the contacts' change, then the resistivity's gradient
                g = gradient_directions(pipe.model)
                c = pipe.model.contact
                self._gradients = g if c is None else np.vstack([c, g])
            self.drift = DriftTracker(pipe.reference / pipe._y_scale, self._gradients,
                                      change_noise(est.noise, pipe.reference_frames), ~pipe.bad_channels,
                                      self._force_map())
        c = self.creep_per_decade
        if c > 0:
            self.creep = CreepCompensator(c, pipe.n_meas)
        pipe.scale = 1.0
        self._apply_offsets()

    def _force_map(self) -> np.ndarray | None:
        """The estimator's linear map of a change to a force (the drift tracker's rest bound)."""
        est = self.pipe.estimator
        return getattr(getattr(est, "linear", est), "W", None)

    @property
    def creep_per_decade(self) -> float:
        """The creep compensated: the calibration's coefficient if it has one, else the setting's; a
        setting of 0 turns it off, over a calibration's too."""
        if not self.config.creep_per_decade:
            return 0.0
        cal = self.pipe.calibration
        fitted = getattr(cal, "creep_per_decade", None) if cal is not None else None
        return float(fitted) if fitted is not None else self.config.creep_per_decade

    def _apply_offsets(self) -> None:
        """The pipeline subtracts the drift's gradient and the creep from every change."""
        d = self.drift.offset if self.drift is not None else None
        c = self.creep.offset if self.creep is not None else None
        if c is None or d is None:
            self.pipe.offset = d if c is None else c
        else:
            self.pipe.offset = np.add(d, c, out=self._offset)

    # --- noise -----------------------------------------------------------------------------------

    @property
    def noise_text(self) -> str:
        """What noise the estimators use, in words: measured by the tare, estimated from N frame pairs
        (with its SNR), or assumed (and why no estimate is in use yet)."""
        pipe = self.pipe
        if pipe.noise_measured or self._noise_level is not None or self.noise is None:
            return pipe.noise_source
        return f"{pipe.noise_source} ({self._noise_note or f'estimating: {self.noise.count} of {MIN_PAIRS} frame pairs'})"

    def estimate_noise(self, frames: np.ndarray, source: str) -> str:
        """Estimate the noise from a whole file of consecutive frames ``frames`` (n, n_meas) before they
        are processed, by the running estimate's rules (force/noise.py), so every frame gets it; the
        estimate then stays (the file holds no more). Nothing changes when the reference's noise is
        measured or ``noise_estimation`` is off. Returns :attr:`noise_text`."""
        with self.lock:
            if self.noise is None or self.pipe.noise_measured or self.pipe.reference is None:
                return self.noise_text
            level, pairs, agree = noise_level(frames, ~self.pipe.bad_channels)
            if self._usable_noise(level, pairs, agree, f"of {source}"):
                self._use_noise(level, f"estimated from {pairs} frame pairs of {source}")
                self.noise = None
            return self.noise_text

    def _usable_noise(self, level: float, pairs: int, agree: float, where: str = "") -> bool:
        """Whether an estimate of ``level`` volts from ``pairs`` pairs, ``agree`` of them agreeing, may
        be used (force/noise.py); if not, :attr:`noise_text` says why."""
        if pairs < MIN_PAIRS:
            self._noise_note = f"not estimated: {pairs} frame pairs {where}, fewer than {MIN_PAIRS}".replace("  ", " ")
        elif not agree >= AGREE_FRACTION:
            self._noise_note = (f"not estimated: only {agree:.0%} of {pairs} consecutive frame pairs {where} "
                                f"differ by noise alone (at least {AGREE_FRACTION:.0%} needed): frames of "
                                "distinct loads, not a time series?").replace("  ", " ")
        else:
            return True
        return False

    def _observe_noise(self, values: np.ndarray) -> None:
        """A processed frame into the running noise estimate (every frame's pair until an estimate is
        in use, then one in :data:`~.noise.SAMPLE_EVERY`); the estimate is evaluated every
        :data:`~.noise.MIN_PAIRS` pairs until one is in use, then every :data:`~.noise.UPDATE_EVERY`,
        and replaces the one in use when it moved by more than :data:`~.noise.RETUNE`."""
        est = self.noise
        keep = ~self._mask if self.excluded.channels else None
        est.observe(values, keep, pair=self._noise_level is None or self.processed % SAMPLE_EVERY == 0)
        if est.pairs < self._noise_next:
            return
        self._noise_next = est.pairs + (UPDATE_EVERY if self._noise_level is not None else MIN_PAIRS)
        level, agree = est.level()
        if not self._usable_noise(level, est.count, agree):
            return
        if self._noise_level is None or abs(level / self._noise_level - 1.0) > RETUNE:
            self._use_noise(level, f"estimated from {est.count} frame pairs")

    def _use_noise(self, level: float, source: str) -> None:
        """The estimated noise ``level`` (volts, every channel) in the pipeline and the drift tracker
        (its state kept); ``source`` says from what. A level outside a board's range against the
        reference (device.NOISE_DB_RANGE) is not used: the noise in use stays."""
        pipe = self.pipe
        try:
            pipe.set_noise(np.full(pipe.n_meas, level), f"{source} ({snr_db(level, pipe.reference):.1f} dB)")
        except ConfigError as err:
            note = f"estimate not used: {err}"
            if note != self._noise_note:  # once per reason, not every evaluation
                log.warning("noise %s", note)
            self._noise_note = note
            self._noise_next = self.noise.pairs + UPDATE_EVERY if self.noise is not None else 0
            return
        self._noise_level, self._noise_from, self._noise_note = level, source, ""
        if self.drift is not None:
            self.drift = self.drift.with_noise(change_noise(pipe.estimator.noise, pipe.reference_frames),
                                               self._force_map())
            self._apply_offsets()
        log.info("noise %s: the estimators use it instead of the %s", pipe.noise_source, NOISE_ASSUMED)

    def _keep_estimate(self) -> None:
        """After a new reference without a measured noise: the board's estimated noise stays in use
        (the board's noise is constant over a session; docs/physics.md#real-devices)."""
        if not self.pipe.noise_measured and self._noise_level is not None:
            level, self._noise_level = self._noise_level, None
            self._use_noise(level, self._noise_from)

    # --- per frame -------------------------------------------------------------------------------

    def _mask_of(self, saturated: np.ndarray | None, contact_ok: np.ndarray | None):
        """(mask, saturated count, dead electrodes) of a frame's flags; raises
        :class:`NoUsableChannelsError` when they exclude every measurement."""
        contact = self._all_good if contact_ok is None else np.asarray(contact_ok, bool)
        dead = ~contact
        mask = self._electrode_rows[dead].any(axis=0) if dead.any() else np.zeros_like(self._mask)
        n_sat = 0
        if saturated is not None:
            saturated = np.asarray(saturated, bool)
            n_sat = int(np.count_nonzero(saturated))
            mask |= saturated
        if mask.all():
            raise NoUsableChannelsError(
                f"every measurement excluded ({n_sat} saturated values, {int(dead.sum())} of {dead.size} "
                "electrode contacts failed): frame dropped; check the sensor's cable, contacts and drive current")
        return mask, n_sat, dead

    def flagged(self, saturated: np.ndarray | None, contact_ok: np.ndarray | None) -> np.ndarray | None:
        """The measurements a frame's flags exclude (saturated, every row of a dead electrode), or None
        when nothing is flagged (the common case)."""
        if (saturated is None or not np.count_nonzero(saturated)) and (
                contact_ok is None or np.count_nonzero(contact_ok) == len(contact_ok)):
            return None
        try:
            return self._mask_of(saturated, contact_ok)[0]
        except NoUsableChannelsError:
            return np.ones(self.pipe.n_meas, bool)

    def update_mask(self, saturated: np.ndarray | None, contact_ok: np.ndarray | None) -> bool:
        """Exclude saturated values and every row of a dead electrode; True if the mask changed.

        Raises :class:`NoUsableChannelsError` (nothing changed) when the flags exclude every
        measurement: such a frame carries no data and must be dropped.
        """
        if not self.excluded.channels and (saturated is None or not np.count_nonzero(saturated)) and (
                contact_ok is None or np.count_nonzero(contact_ok) == len(contact_ok)):
            return False  # the common case, per frame: nothing flagged and nothing excluded
        mask, n_sat, dead = self._mask_of(saturated, contact_ok)
        if np.array_equal(mask, self._mask):
            return False
        self.pipe.set_bad_channels(mask.copy())  # raises before changing anything if refused
        self._mask = mask
        if self.drift is not None:
            self.drift = self.drift.with_mask(~mask, self._force_map())
            self._apply_offsets()
        self.excluded = Excluded(saturated=n_sat, dead_electrodes=tuple(int(e) for e in np.flatnonzero(dead)),
                                 channels=int(mask.sum()))
        if mask.any():
            log.warning("excluding %d measurements (saturated: %d, dead electrodes: %s)",
                        self.excluded.channels, self.excluded.saturated, self.excluded.dead_electrodes)
        return True

    def process(self, values: np.ndarray, saturated: np.ndarray | None = None,
                contact_ok: np.ndarray | None = None, t: float | None = None) -> FrameResult | None:
        """The :class:`FrameResult` of one frame, or None while the frame goes into a pending tare (or
        no reference exists yet). Raises :class:`FrameError` for a frame that must be dropped (it then
        counts for nothing, not even for a pending tare). An implausible result (``valid`` False) is
        counted in ``implausible``; a run of them is logged once when it starts and once when it ends.
        A valid frame updates the drift tracker (``t``: its time in seconds; None: 10 ms after the
        previous one). :meth:`push` is this with the accounting, the filter and the stamps."""
        try:
            with self.lock:
                return self._process(values, saturated, contact_ok, t)
        finally:
            self._finish_tares()

    def _process(self, values: np.ndarray, saturated: np.ndarray | None, contact_ok: np.ndarray | None,
                 t: float | None) -> FrameResult | None:
        """:meth:`process` under the frame lock (the tares it ends are saved and reported after it)."""
        if self._tare_left:
            mask = self._mask_of(saturated, contact_ok)[0]
            v = check_frame(values, self.pipe.n_meas, "tare frame", used=~mask)
            outcome = self._add_tare_frame(v, mask)
            if outcome is not None:
                self._end_tare(outcome)
            return None
        if self.pipe.reference is None:
            return None
        self.update_mask(saturated, contact_ok)
        every = self.config.stress_field_every
        with_field = every > 0 and self.processed % every == 0
        self.processed += 1
        result = self.pipe.process(values, with_field=with_field)
        if not result.valid:
            self.implausible += 1
            self.implausible_reason = result.reason
            if not self._implausible_run:
                log.warning("implausible frames (no force output): %s", result.reason)
            self._implausible_run += 1
        elif self._implausible_run:
            log.warning("plausible frames again after %d implausible ones", self._implausible_run)
            self._implausible_run = 0
        if self.noise is not None and not self.pipe.noise_measured:
            self._observe_noise(values)
        drift, creep = self.drift, self.creep
        sig = creep_f = None
        if result.valid:
            sig = self._sigma_model()
            if creep is not None:
                creep_f = sig.creep_force(creep.offset)  # the offset this frame was corrected by
        if self.pipe.change_plausible and (drift is not None or creep is not None):  # beyond max_force too
            y = self.pipe.last_y  # the change with the creep so far taken out: the load's and the drift's
            if drift is not None:
                # issue 26 items 2, 4: every frame measures the scale jointly with its force (force/drift.py
                # JointScale; a controller's expected load, expect_load, sharpens it); the force follows
                joint = self._joint_scale(t)
                drift.observe(y, t, joint)
                self.pipe.scale = drift.scale
                if drift.force_step is not None and result.valid:
                    result.force = result.force + drift.force_step
                    result.magnitude, result.elevation, result.azimuth = force_angles3(result.force)
            if creep is not None:
                creep.observe(y, t, self._mask if self.excluded.channels else None)
            self._apply_offsets()
        if sig is not None:  # the tracker's covariance after this frame's predict and update
            result.sigma, result.sigma_n = sig(result.force, drift.P if drift is not None else None, creep_f,
                                               drift.change if drift is not None else 0.0)
        return result

    def _joint_scale(self, t: float | None):
        """The latest frame's joint measurement of the scale (force/drift.py JointScale), None for an
        estimator without a joint fit (``linear``); with the controller's expected load (:meth:`expect_load`)
        when it is at most :data:`EXPECTED_HOLD` s older than the frame (or the frame has no time)."""
        est = self.pipe.estimator
        if getattr(est, "last_fit", None) is None:
            return None
        if self._joint is None or self._joint.est is not est or self._joint_for is not self.drift:
            self._joint, self._joint_for = JointScale(est, self.drift._D[0]), self.drift
        e = self._expected
        use = e is not None and (t is None or not e[2] or 0.0 <= t - e[2] <= EXPECTED_HOLD)
        return self._joint.measure(e[:2] if use else None)

    def expect_load(self, force, sigma: float, stamp_ns: int = 0) -> None:
        """A controller's expected load now (issue 26 item 4: its dynamics model, the link's weight):
        ``force`` (3,) N in the wrench frame, its 1-sigma ``sigma`` (N, per axis), at ``stamp_ns`` (the
        frames' clock; 0: the next frames). Used as a measurement of the force in the joint fit of the
        device's scale (force/drift.py JointScale) for frames up to :data:`EXPECTED_HOLD` s after it."""
        f = np.asarray(force, float).reshape(-1)
        if f.shape != (3,) or not np.isfinite(f).all():
            raise ConfigError.bad_value("expected load", force, "3 finite force components in newtons")
        if not (math.isfinite(sigma) and sigma > 0):
            raise ConfigError.bad_value("expected load sigma", sigma, "a 1-sigma > 0 in newtons")
        self._expected = (f, float(sigma), stamp_ns * 1e-9)

    def _sigma_model(self) -> ForceSigma:
        """The force's uncertainty for the estimator, tracker and creep in use (rebuilt when one changes)."""
        pipe, drift = self.pipe, self.drift
        f = self._sigma_for
        if (self._sigma is None or f[0] is not pipe.estimator or f[1] is not drift or f[2] is not self.creep
                or f[3] is not pipe.calibration):
            est = pipe.estimator
            k_rel, self.sigma_source = relative_error(pipe.calibration, est.name)
            fitted = getattr(pipe.calibration, "creep_per_decade", None) is not None
            creep_rel = 0.0 if self.creep is None else CREEP_REL_FITTED if fitted else CREEP_REL_ASSUMED
            self._sigma = ForceSigma(self._force_map(), change_noise(est.noise, pipe.reference_frames), ~pipe.bad_channels,
                                     None if drift is None else drift._D, k_rel, creep_rel)
            self._sigma_for = (pipe.estimator, drift, self.creep, pipe.calibration)
        return self._sigma

    def push(self, values: np.ndarray, saturated: np.ndarray | None = None, contact_ok: np.ndarray | None = None,
             stamp_ns: int = 0, age_ns: int = 0, process: bool = True) -> Output | None:
        """One frame measured ``age_ns`` ago (monotonic clock), stamped ``stamp_ns``: counted, dropped if
        late, then processed (``process`` False: only counted, e.g. an inactive node that is not
        taring). Returns the :class:`Output` of a result (an implausible one too: ``result.valid``
        False, no filtered force), else None (a tare frame, no reference, late, or dropped: counted,
        never raised)."""
        t0 = time.perf_counter()
        c = self.counts
        with self.counts_lock:
            c.frames += 1
            c.period_frames += 1
            c.last_frame = time.monotonic()
            c.arrivals.append(c.last_frame)
            late = age_ns > self.config.stale_timeout * 1e9
            c.late += late
        if late or not process:
            return None
        try:
            with self.lock:
                result = self._process(values, saturated, contact_ok, stamp_ns * 1e-9 if stamp_ns else None)
                filtered = None
                if result is not None and result.valid and self.filter is not None:
                    filtered = self.filter(result.force, stamp_ns * 1e-9)
        except Exception as err:  # noqa: BLE001 - the frame boundary: counted, logged, reported
            self.drop(err)
            return None
        finally:
            self._finish_tares()
        with self.counts_lock:
            c.reject_reason = ""  # frames go through again
            if result is None:
                return None
            if not result.valid:
                return Output(result, None, int(stamp_ns))
            dt = time.perf_counter() - t0
            c.proc_sum += dt
            c.proc_n += 1
            c.proc_max = max(c.proc_max, dt)
            if not math.isnan(result.residual):
                c.residual = result.residual
            c.consistency = result.consistency
            c.foreign += result.foreign_load
            c.period_foreign += result.foreign_load
            sn = result.sigma_n
            c.sigma_n = sn
            if sn > c.period_sigma_max:
                c.period_sigma_max = sn
            bound = self.config.max_sigma_n
            if bound and sn > bound:
                c.sigma_over += 1
                c.period_sigma_over += 1
        return Output(result, filtered, int(stamp_ns))

    def drop(self, err: BaseException, corrupt: bool = False) -> None:
        """Count and log (throttled) a frame that could not be used: ``corrupt`` for an input message
        that is no frame at all (the caller's decoding failed), else a frame the frame path dropped
        (a :class:`FrameError`, or an unexpected error: a bug, logged with its trace)."""
        c = self.counts
        if corrupt:
            with self.counts_lock:
                c.corrupt += 1
            self._drop_log(logging.WARNING, f"dropped input frame: {err}")
            return
        bug = not isinstance(err, FrameError)
        reason = f"{type(err).__name__}: {err}" if bug else str(err)
        with self.counts_lock:
            c.rejected += 1
            c.all_excluded += isinstance(err, NoUsableChannelsError)
            c.errors += bug
            c.reject_reason = c.period_reason = reason
        if bug:
            self._drop_log(logging.ERROR, "frame dropped on an unexpected error (a bug: please report it with "
                                          f"this trace):\n{''.join(traceback.format_exception(err))}")
        else:
            self._drop_log(logging.WARNING, f"dropped frame: {reason}")

    # --- health ----------------------------------------------------------------------------------

    def health(self, now: float, board_losses: dict[str, int] | None = None) -> tuple[int, list[str], dict]:
        """The stream's level (:data:`OK`, :data:`WARN`, :data:`ERROR`), problems and figures since the
        last call (resets the per-period figures). ``board_losses``: the board driver's running totals
        of lost frames by kind (corrupt, gaps, duplicates, reordered, overflow), None without a board."""
        c = self.counts
        period = max(now - self._last_health, 1e-9)
        self._last_health = now
        with self.counts_lock:
            rate = c.period_frames / period
            proc_mean = c.proc_sum / c.proc_n if c.proc_n else math.nan
            proc_max = c.proc_max if c.proc_n else math.nan
            c.period_frames, c.proc_sum, c.proc_max, c.proc_n = 0, 0.0, 0.0, 0
            period_reason, c.period_reason = c.period_reason, ""
            period_foreign, c.period_foreign = c.period_foreign, 0
            sigma_n, sigma_over = c.sigma_n, c.sigma_over
            period_sigma_over, period_sigma_max = c.period_sigma_over, c.period_sigma_max
            c.period_sigma_over, c.period_sigma_max = 0, 0.0
            frames, late, rejected, corrupt = c.frames, c.late, c.rejected, c.corrupt
            kv = {"frames": frames, "frame_rate_hz": f"{rate:.1f}", "late_dropped": late}
            kv_rejected = {"frames_rejected": rejected, "frames_all_excluded": c.all_excluded,
                           "frame_errors": c.errors, "reject_reason": c.reject_reason}
            consistency, foreign, residual = c.consistency, c.foreign, c.residual
        level, msgs = OK, []
        losses = {"corrupt": corrupt, "late": late}
        if board_losses is not None:
            losses.update(board_losses, corrupt=corrupt + board_losses.get("corrupt", 0))
        kv["corrupt"] = losses["corrupt"]
        loss_level, loss_msg = self._loss_level(now, frames, losses)
        if loss_msg:
            level = max(level, loss_level)
            msgs.append(loss_msg)
        kv.update(kv_rejected)
        if rejected > self._last_rejected:
            level = max(level, WARN)
            msgs.append(f"{rejected - self._last_rejected} frames rejected ({period_reason})")
        self._last_rejected = rejected
        ex = self.excluded
        kv.update(saturated_channels=ex.saturated, dead_electrodes=",".join(str(e + 1) for e in ex.dead_electrodes),
                  excluded_channels=ex.channels)
        if ex.channels:
            level = max(level, WARN)
            msgs.append(f"{ex.channels} channels excluded (saturated {ex.saturated}, dead electrodes "
                        f"{[e + 1 for e in ex.dead_electrodes]})")
        imp = self.implausible
        new_imp = imp - self._last_implausible if imp >= self._last_implausible else imp
        self._last_implausible = imp
        kv.update(implausible=imp, implausible_reason=self.implausible_reason)
        if new_imp:
            level = max(level, WARN)
            msgs.append(f"{new_imp} implausible frames not published ({self.implausible_reason})")
        kv.update(consistency=f"{consistency:.4g}", foreign_load_frames=foreign)
        if period_foreign:
            level = max(level, WARN)
            msgs.append(f"foreign load: {period_foreign} frames not explained by a load on the socket (consistency "
                        f"{consistency:.3g}, limit {self.pipe.consistency.threshold:g}); something else presses the "
                        "sensor or an electrode changed; forces still published")
        bound = self.config.max_sigma_n
        kv.update(sigma_n=f"{sigma_n:.4g}", sigma_n_period_max=f"{period_sigma_max:.4g}",
                  max_sigma_n=f"{bound:g}" if bound else "0 (no check)", sigma_over_frames=sigma_over,
                  sigma_calibration=self.sigma_source)
        if bound and period_sigma_over:
            level = max(level, WARN)
            msgs.append(f"uncertain forces: {period_sigma_over} frames with a 1-sigma above max_sigma_n {bound:g} N "
                        f"(largest {period_sigma_max:.3g} N): the noise, the device's untracked change (a long load "
                        "since the last rest) or the calibration; forces still published")
        kv.update(residual=f"{residual:.4g}", processing_time_mean_ms=f"{proc_mean * 1e3:.3f}",
                  processing_time_max_ms=f"{proc_max * 1e3:.3f}")
        kv.update(tare_taken=self.tare_taken, tare_refused=self.tare_refused, tare_unsaved=self.tare_unsaved)
        if self.tare_unsaved:
            level = max(level, WARN)
            msgs.append(self.tare_unsaved)
        pipe = self.pipe
        if self.taring and pipe.reference is None:
            level = max(level, WARN)
            msgs.append("no reference yet: taring on the first frames (the joint must be unloaded); no force "
                        "published until then" + (f"; last tare refused at {self.tare_refused}" if self.tare_refused else ""))
        report = pipe.scale_report
        if report is not None:
            kv.update(reference_scale=f"{report.factor:.4g}", reference_unexplained=f"{report.unexplained:.4f}",
                      noise=self.noise_text)
            if report.warn:
                level = max(level, WARN)
                msgs.append(report.message)
        cal = pipe.calibration
        kv.update(calibration=cal.path if cal else "none (nominal model)", calibration_accuracy=cal.accuracy if cal else "")
        drift = self.drift
        if drift is not None:
            d_level, d_msg = drift.status()
            kv.update(drift_change=f"{drift.change:+.3%}", drift_kelvin=drift.kelvin_text, drift_rest_frames=drift.rest_frames)
            if d_msg:
                level = max(level, d_level)
                msgs.append(d_msg)
        else:
            kv.update(drift_change="not tracked (drift_tracking false)" if not self.config.drift_tracking
                      else "not tracked yet: no reference (tracking starts with the tare)")
        kv.update(creep=self.creep_text)
        return level, msgs, kv

    @property
    def creep_text(self) -> str:
        """The creep compensated and where its coefficient comes from, for the diagnostics."""
        c = self.creep_per_decade
        if c <= 0:
            return "not compensated (creep_per_decade 0)"
        cal = self.pipe.calibration
        if cal is not None and getattr(cal, "creep_per_decade", None) is not None:
            return f"{c:.2%} per decade, from the calibration {cal.path}"
        return (f"{c:.2%} per decade, assumed (creep_per_decade; a rubber's is 2..6 %: fit it with "
                "cstomo calibrate from held loads, docs/calibration.md#the-creep)")

    def _loss_level(self, now: float, frames: int, losses: dict) -> tuple[int, str]:
        """The level and message of the frames lost or dropped over the last :data:`LOSS_WINDOW` s
        (``losses``: running totals by kind); WARN above :data:`LOSS_WARN`, ERROR above
        :data:`LOSS_ERROR` of the frames the board sent meanwhile."""
        hist = self._loss_history
        if not hist:
            hist.append((self._created, 0, {}))
        hist.append((now, frames, dict(losses)))
        while len(hist) > 2 and now - hist[1][0] >= LOSS_WINDOW:
            hist.popleft()
        t0, f0, old = hist[0]
        d = {k: v - old.get(k, 0) for k, v in losses.items()}
        lost = sum(d.values())
        sent = frames - f0 + lost - d["late"]  # late frames were received (and counted in frames)
        if lost <= 0 or sent <= 0 or lost <= LOSS_WARN * sent:
            return OK, ""
        level = ERROR if lost > LOSS_ERROR * sent else WARN
        parts = ", ".join(f"{k} {v}" for k, v in d.items() if v)
        return level, f"{lost} of {sent} frames lost or dropped in the last {now - t0:.0f} s ({parts})"
