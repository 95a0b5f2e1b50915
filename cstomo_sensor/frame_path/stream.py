"""The frame stream of one sensor: everything that happens to its frames between the board and the
outputs and needs state from frame to frame. No ROS, no serial. The node, ``cstomo replay`` and
``cstomo estimate`` push their frames through a :class:`FrameStream`, so they cannot disagree.

It coordinates stages that own their state and rules and hand their results on as arguments: the
tare transaction (force/reference/tare_transaction.py, force/reference/tare_rules.py), the channel mask (frame_path/mask.py), the per-frame
core (frame_path/pipeline.py), the device's slow states and the force's 1-sigma (force/slow_states/coordinator.py), the noise
in use (frame_path/noise_in_use.py), the filtered wrench (frame_path/filter.py: reset on a tare, a reconnect and
gaps) and health (frame_path/health.py). Its settings: frame_path/config.py; its outputs: frame_path/outputs.py.

A frame comes with a stamp (ns on the caller's clock: the filter runs on it) and an age (ns on the
monotonic clock: older than ``stale_timeout`` is late). A frame the stream cannot use (wrong length,
NaN in a used channel, every channel excluded, an unexpected error) is dropped, counted and logged
(throttled), never raised.
"""
from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path

import numpy as np

from ..angles import force_angles3
from ..errors import ConfigError, CstomoError
from ..force.reference.files import read_reference, tare_age
from ..force.reference.first_tare import FirstTareWatch
from ..force.reference.tare_rules import TareOutcome, tare_deadline, tare_problem
from ..force.reference.tare_transaction import Taring
from ..force.slow_states.coordinator import SlowStates
from ..force.slow_states.learned import Directions, read_directions, write_directions
from ..frames_io import check_frame
from .config import StreamConfig
from .filter import LowPass
from .health import Health
from .mask import ChannelMask
from .noise_in_use import NoiseState
from .outputs import FrameOutput, output_set
from .pipeline import FrameResult, Pipeline

log = logging.getLogger(__name__)


class FrameStream:
    """The frame stream of one sensor over the pipeline ``pipe``. The tare's ``on_tare``, ``tare_file``,
    ``tare_comment`` and ``started``: :class:`~cstomo_sensor.force.reference.tare_transaction.Taring`. A tare pending (at start without a
    usable saved tare, :meth:`tare`, replay without a reference) averages the next ``tare_frames``
    frames into the reference (no output); force/reference/tare_rules.py's rules or a reconnect refuse it. Without any
    reference a tare is always pending: a refused or cancelled one starts over."""

    def __init__(self, pipe: Pipeline, config: StreamConfig = StreamConfig(),
                 on_tare: Callable[[TareOutcome], None] | None = None,
                 tare_file: str | Path | None = None, tare_comment: str = "", started: float | None = None) -> None:
        self.pipe, self.config = pipe, config
        self.outputs = output_set(config, pipe.scene_field is not None)
        self.lock = threading.Lock()  # one frame at a time; a tare is started and ended under it
        self.filter = LowPass(config.wrench_filter_hz, max_gap=config.stale_timeout) if config.wrench_filter_hz else None
        self.tares = Taring(pipe.n_meas, tare_file, tare_comment, on_tare, started)
        self.channels = ChannelMask(pipe.geometry, pipe.bad_channels)
        # the device's own directions (force/slow_states/learned.py) start as its calibration's (learned from its
        # recording); a saved tare's, newer, take their place (init_reference)
        self.slow = SlowStates(pipe.n_meas, config, pipe.max_force, getattr(pipe.calibration, "directions", None))
        self.noise_state = NoiseState(pipe.n_meas, config.noise_estimation)
        self.counter = Health(config.max_sigma_n)
        self.processed = 0  # frames processed (their count picks the stress fields')
        self.fields_wanted = True  # False: the fields are not computed (nobody subscribes to them: want_fields)
        self.first_tare: FirstTareWatch | None = None  # the frames after a first tare (force/reference/first_tare.py)

    def with_config(self, **changes) -> None:
        """Change settings that may change while running (``stale_timeout``)."""
        self.config = replace(self.config, **changes)
        if self.filter is not None:
            self.filter.max_gap = self.config.stale_timeout

    def want_fields(self, wanted: bool) -> None:
        """Whether the stress fields are wanted (a sink's subscribers, :class:`~cstomo_sensor.ros.sinks.Publishers`):
        False, they are not computed (``stress_field_every`` still counts the frames)."""
        self.fields_wanted = bool(wanted)

    @property
    def ready(self) -> bool:
        """Frames give results: no tare pending and a reference in use."""
        return not self.tares.pending and self.pipe.reference is not None

    @property
    def noise_text(self) -> str:
        """What noise the estimators use, in words (frame_path/noise_in_use.py)."""
        return self.noise_state.text(self.pipe.noise_measured, self.pipe.noise_source)

    # --- reference and tare ----------------------------------------------------------------------

    def set_reference(self, ref: np.ndarray, noise: np.ndarray | None, n_frames: int, source: str,
                      age_s: float | None = None, directions: Directions | None = None) -> str:
        """Use ``ref`` (n_meas,) volts, the mean of ``n_frames`` unloaded frames of per-channel ``noise``
        (None: assumed) if plausible (:func:`~cstomo_sensor.force.reference.tare_rules.tare_problem`, else :class:`ConfigError` naming
        ``source``); returns the tare report's message. ``age_s``: a saved tare this old (a restart);
        ``directions``: the device's own directions saved with it (force/slow_states/learned.py
        :func:`~cstomo_sensor.force.slow_states.learned.read_directions`)."""
        why = tare_problem(ref, self.pipe.model_reference)
        if why:
            raise ConfigError(f"{source} not used: {why}")
        report = self._new_reference(ref, noise, n_frames, age_s, directions)
        self.tares.reference_from(source)
        (log.warning if report.warn else log.info)("%s: mean of %d frame(s), noise %s; %s", source, n_frames,
                                                   self.noise_text, report.message)
        return report.message

    def _new_reference(self, ref: np.ndarray, noise: np.ndarray | None, n_frames: int, age_s: float | None = None,
                       directions: Directions | None = None):
        report = self.pipe.set_reference(ref, noise, n_frames)
        self.first_tare = None  # a first tare's watch is set by _end_tare (force/reference/first_tare.py)
        self._use_noise(self.noise_state.kept(self.pipe.noise_measured))  # an estimated noise stays in use
        self.slow.reset(self.pipe, age_s, directions)
        return report

    def init_reference(self, tare_on_start: bool) -> str:
        """The saved tare if usable, else a tare on the first frames (``tare_on_start``: always, judged
        against the saved tare or the calibration's reference where one is usable, so a tare at start
        under a load is refused): never a force against the model's own reference (a phantom force of
        newtons at zero load). Returns '' when a saved reference is in use, else why a tare is pending."""
        saved, why = self.tares.saved(self.pipe.n_meas)
        path = self.tares.tare_file
        if saved is None:
            # no saved tare of this device: its calibration's own unloaded reference, if it has one (a
            # first start under a load is then read as a restart, not taken as the zero)
            cal = self.pipe.calibration
            ref = cal.reference_path if cal is not None else None
            if ref is not None and ref.is_file():
                try:
                    saved, path = read_reference(ref, self.pipe.n_meas), ref
                except (CstomoError, OSError) as err:
                    log.warning("the calibration's reference %s is unusable (%s): a tare on the first frames", ref, err)
        if saved is not None:
            try:
                # the device moved since the tare was saved: its age (force/reference/files.py tare_age) widens the slow states;
                # the device's own directions saved beside a saved tare (force/slow_states/learned.py) are tracked from the first frame
                kind = "saved tare" if path == self.tares.tare_file else "the calibration's unloaded reference"
                self.set_reference(*saved, source=f"{kind} {path}", age_s=tare_age(path, time.time()) or 0.0,
                                   directions=self._saved_directions() if path == self.tares.tare_file else None)
                if tare_on_start:  # a tare at start is checked against it: not taken under a load
                    self.start_tare()
                return ""
            except ConfigError as err:
                why = str(err)
        self.start_tare()
        self.tares.reference_from("tare pending")
        return why

    def _saved_directions(self) -> Directions | None:
        """The learned directions saved beside the tare file (None: none, or unreadable: said once; the stream keeps
        those it has, its calibration's or none: the model's only)."""
        try:
            return read_directions(self.tares.tare_file, self.pipe.n_meas)
        except (CstomoError, OSError) as err:
            n = len(self.slow.directions)
            log.warning("the device's learned directions not used (%s): %s", err,
                        f"the calibration's {n} direction(s) and the model's" if n else "the model's directions only")
            return None

    def _save_directions(self) -> None:
        """A direction learned (force/slow_states/learned.py): the device's directions saved beside its tare file, by a
        thread of its own (frames keep flowing while a slow disk writes it)."""
        self.slow.learned_new = False
        path, directions = self.tares.tare_file, self.slow.directions
        if path is None:
            return

        def write():
            try:
                write_directions(path, directions, comment=self.tares.comment)
                log.info("the device's %d learned direction(s) saved beside %s", len(directions), path)
            except OSError as err:
                log.error("the device's learned directions not saved beside %s (%s)", path, err)

        threading.Thread(target=write, name="cstomo_directions_save", daemon=True).start()

    def start_tare(self, n_frames: int | None = None) -> None:
        """Average the next ``n_frames`` (default ``tare_frames``) frames into the reference."""
        self.tares.start(self.config.tare_frames if n_frames is None else n_frames)
        self.noise_state.restart()  # no frame pair across the tare

    def joint_free(self) -> bool:
        """A controller's hint that the joint is free: a tare now, with every rule of a tare; False (and
        nothing changes) while one is pending."""
        with self.lock:
            if self.tares.pending:
                return False
            self.start_tare()
        log.info("the joint is free (a controller's hint): re-zeroing on the next %d frames", self.config.tare_frames)
        return True

    def reconnected(self) -> None:
        """The board came back after an outage: the filter starts again, a pending tare is refused
        (:data:`~cstomo_sensor.force.reference.tare_rules.TARE_RECONNECTED`: the joint may be loaded by then)."""
        with self.lock:
            if self.filter is not None:
                self.filter.reset()
            self.noise_state.restart()  # no frame pair across the outage
            outcome = self.tares.interrupt()
            if outcome is not None:
                self._end_tare(outcome)
        self.tares.finish()

    def corrupt(self, err: Exception) -> None:
        """An input that is no frame (the source could not decode it): counted as corrupt and logged (throttled)."""
        self.counter.drop(err, corrupt=True)

    def cancel_tare(self) -> int:
        """Drop a pending tare (it stays pending without any reference); returns the frames it had taken."""
        return self.tares.cancel(keep_pending=self.pipe.reference is None)

    def tare_deadline(self, rate_hz: float = 0.0) -> float:
        """Seconds a tare of ``tare_frames`` frames may take (:func:`~cstomo_sensor.force.reference.tare_rules.tare_deadline`): from the
        measured frame period (:attr:`~.health.Health.frame_period`), never shorter than the nominal ``rate_hz``'s (0: unknown)."""
        return tare_deadline(self.config.tare_frames, self.counter.frame_period, rate_hz, self.config.stale_timeout)

    def tare(self, timeout: float, forced: bool = False) -> tuple[TareOutcome | None, int]:
        """A tare transaction: a tare awaited up to ``timeout`` s (:meth:`tare_deadline`), else cancelled
        (under the frame lock), then its save up to ``timeout`` s more (else its ``note`` says so);
        ``forced``: the load checks do not refuse it. Returns (the outcome, None if cancelled; its frames)."""
        with self.lock:
            self.tares.begin(self.config.tare_frames, forced)
            self.noise_state.restart()
        self.tares.wait(timeout)
        with self.lock:
            ended, taken = self.tares.settle(keep_pending=self.pipe.reference is None)
        return (None, taken) if ended is None else (self.tares.wait_saved(ended, timeout), taken)

    def _end_tare(self, outcome: TareOutcome) -> None:
        """Under the frame lock: an accepted tare is the reference from the next frame (saved and
        reported once the lock is released: :meth:`~cstomo_sensor.force.reference.tare_transaction.Taring.finish`)."""
        report = None
        if outcome.ok:
            first = self.pipe.reference is None and not outcome.forced  # nothing to judge it against: watched
            report = self._new_reference(outcome.reference, outcome.noise, outcome.frames)
            if self.filter is not None:
                self.filter.reset()  # a new reference: the filtered wrench starts again from the next frame
            self.first_tare = FirstTareWatch.of(self.pipe.in_use) if first else None
        self.tares.end(outcome, self.pipe.reference is not None, self.noise_text, report)
        if self.tares.pending:  # refused without a reference: it starts over
            self.noise_state.restart()

    def close(self, timeout: float = 5.0) -> list[str]:
        """Wait up to ``timeout`` s for the tare files being written; returns those still unwritten."""
        return self.tares.close(timeout)

    # --- noise -----------------------------------------------------------------------------------

    def estimate_noise(self, frames: np.ndarray, source: str) -> str:
        """The noise from a file of consecutive ``frames`` (n, n_meas) before they are processed, unless
        measured or not estimated (frame_path/noise_in_use.py); returns :attr:`noise_text`."""
        with self.lock:
            if self.noise_state.estimate is not None and not self.pipe.noise_measured and self.pipe.reference is not None:
                self._use_noise(self.noise_state.from_frames(frames, ~self.pipe.bad_channels, source))
            return self.noise_text

    def _use_noise(self, found: tuple[float, str] | None) -> bool:
        """An estimated (level, source) into the pipeline and, if it took it, the drift tracker; the noise
        stage is told which (frame_path/noise_in_use.py). True if the pipeline took it."""
        if found is None:
            return False
        pipe, noise, (level, source) = self.pipe, self.noise_state, found
        try:
            pipe.set_noise(np.full(pipe.n_meas, level), noise.named(level, source, pipe.reference))
        except ConfigError as err:
            noise.refused(err)
            return False
        noise.took(level, source, pipe.noise_source)
        self.slow.renoised(pipe.in_use)
        return True

    # --- per frame -------------------------------------------------------------------------------

    def update_mask(self, saturated: np.ndarray | None, contact_ok: np.ndarray | None) -> bool:
        """Exclude saturated values and every row of a dead electrode; True if the mask changed. Raises
        :class:`NoUsableChannelsError` (nothing changed) when the flags exclude every measurement."""
        if saturated is None and contact_ok is None and self.channels.frozen is None:
            return False  # the common case, per frame: nothing flagged and nothing excluded
        new = self.channels.change(saturated, contact_ok)
        if new is None:
            return False
        self.pipe.set_bad_channels(new[0].copy())  # raises before changing anything if refused
        self.channels.use(*new)
        self.slow.masked(self.pipe.in_use)
        if new[1].channels:
            log.warning("excluding %d measurements (saturated: %d, dead electrodes: %s)",
                        new[1].channels, new[1].saturated, new[1].dead_electrodes)
        return True

    def _process(self, values: np.ndarray, saturated: np.ndarray | None, contact_ok: np.ndarray | None,
                 t: float | None) -> FrameResult | None:
        tares, pipe, slow = self.tares, self.pipe, self.slow
        if tares.left:
            mask = self.channels.of(saturated, contact_ok)[0]
            v = check_frame(values, pipe.n_meas, "tare frame", used=~mask)
            outcome = tares.add(v, mask, pipe, self.config.tare_max_spread)
            if outcome is not None:
                self._end_tare(outcome)
            return None
        if pipe.reference is None:
            return None
        self.update_mask(saturated, contact_ok)
        every, k = self.config.stress_field_every, self.processed
        self.processed += 1
        frame = pipe.step(values, every > 0 and k % every == 0 and self.fields_wanted, True, slow.scale, slow.offset,
                          slow.gradient)
        result = frame.result
        if not result.valid or self.counter.implausible_run:
            self.counter.plausible(result)
        if (self.noise_state.estimate is not None and not pipe.noise_measured
                and self._use_noise(self.noise_state.observe(values, self.channels.kept, self.processed))):
            # the noise now in use (a new estimator, its consistency) is the one the slow states see this frame with
            frame = pipe.after_noise(frame)
        fix = slow.observe(frame, t, self.channels.frozen)  # the device's slow states: the force corrected, its 1-sigma
        if fix.force is not None:
            result.force = fix.force
            result.magnitude, result.elevation, result.azimuth = force_angles3(fix.force)
        if fix.sigma is not None:
            result.sigma, result.sigma_n = fix.sigma, fix.sigma_n
        if slow.learned_new:
            self._save_directions()
        if (self.first_tare is not None and result.valid and not result.foreign_load  # a press elsewhere: no pull
                and self.first_tare.observe(frame.change)):
            # the first tare carried a load (force/reference/first_tare.py): dropped, nothing published until a tare
            self.tares.discard(self.first_tare.message(self.config.tare_frames, self.tares.tare_file))
            self.first_tare = None
            pipe.drop_reference()
            slow.reset(pipe)
            self.start_tare()
            return None  # measured against the dropped reference
        return result

    def expect_load(self, force, sigma: float, stamp_ns: int | None = None, frame_id: str | None = None, source=None) -> str:
        """A controller's expected load now (its dynamics model: the link's weight): checked, then a measurement
        of the device's states; '' or why refused (:meth:`cstomo_sensor.force.slow_states.coordinator.SlowStates.expect_load`,
        force/checks/expected.py)."""
        return self.slow.expect_load(force, sigma, stamp_ns, frame_id, source)

    def push(self, values: np.ndarray, saturated: np.ndarray | None = None, contact_ok: np.ndarray | None = None,
             stamp_ns: int = 0, age_ns: int = 0, process: bool = True) -> FrameOutput | None:
        """One frame measured ``age_ns`` ago, stamped ``stamp_ns`` (its time for the filter and the slow
        states; 0: none, 10 ms after the previous): counted, dropped if late, processed unless ``process``
        is False. Its :class:`~cstomo_sensor.frame_path.outputs.FrameOutput` (an implausible one too: no
        filtered force), else None (a tare frame, no reference, late, dropped: counted, never raised). The
        one entry of a frame (the frame loop's, frame_path/loop.py)."""
        t0 = time.perf_counter()
        if self.counter.arrived(age_ns > self.config.stale_timeout * 1e9) or not process:
            return None
        try:
            with self.lock:
                result = self._process(values, saturated, contact_ok, stamp_ns * 1e-9 if stamp_ns else None)
                filtered = None
                if result is not None and result.valid and self.filter is not None:
                    filtered = self.filter(result.force, stamp_ns * 1e-9)
        except Exception as err:  # noqa: BLE001 - the frame boundary: counted, logged, reported
            self.counter.drop(err)  # counted and logged (throttled)
            return None
        finally:
            self.tares.finish()
        self.counter.passed(result, time.perf_counter() - t0)
        return None if result is None else FrameOutput(result, filtered, int(stamp_ns))

    # --- health ----------------------------------------------------------------------------------

    def health(self, now: float, board_losses: dict[str, int] | None = None) -> tuple[int, list[str], dict]:
        """The level (:data:`~.health.OK`, ``WARN``, ``ERROR``), problems and figures of the period so far:
        a snapshot (:meth:`end_period` starts the next). ``board_losses``: :meth:`~.health.Health.status`."""
        pipe = self.pipe
        return self.counter.status(now, board_losses, pipe, self.channels.status(), self.slow.sigma_source,
                                   self.tares.status(pipe.reference is not None), self.slow.status(pipe.calibration),
                                   self.noise_text)

    def end_period(self, now: float, board_losses: dict[str, int] | None = None) -> tuple[int, list[str], dict]:
        """:meth:`health` of the period that ends ``now``; the next period starts."""
        out = self.health(now, board_losses)
        self.counter.end_period(now, board_losses)
        self.slow.expected.end_period()
        return out
