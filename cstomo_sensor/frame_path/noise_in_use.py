"""Which noise the estimators use when the reference measured none, and the running estimate it
comes from. No ROS, no serial.

A stage of the frame stream (frame_path/stream.py). A one-frame reference measures no noise: the
estimators then assume :data:`~.pipeline.NOISE_ASSUMED` until the running estimate
(:class:`~cstomo_sensor.force.reference.noise_estimate.NoiseEstimate`, ``noise_estimation``) of consecutive frames gives a usable level,
or a whole frames file does first (:meth:`NoiseState.from_frames`). The stage returns the level to
use; the stream hands it to the pipeline (``Pipeline.set_noise``, named by :meth:`NoiseState.named`) and
the drift tracker, and tells the stage whether it was taken (:meth:`NoiseState.took`, :meth:`NoiseState.refused`).
It never reads nor writes the pipeline: what it needs of it comes as values.
"""
from __future__ import annotations

import logging

import numpy as np

from ..errors import ConfigError
from ..force.reference.noise_estimate import (
    AGREE_FRACTION,
    MIN_PAIRS,
    RETUNE,
    SAMPLE_EVERY,
    UPDATE_EVERY,
    NoiseEstimate,
    is_time_series,
    noise_level,
    snr_db,
)
from .pipeline import NOISE_ASSUMED

log = logging.getLogger(__name__)


class NoiseState:
    """The estimated noise in use (``level`` volts, every channel; None: none) and the running estimate
    over ``n_meas`` channels (``estimating`` False: none, the assumed noise stays)."""

    def __init__(self, n_meas: int, estimating: bool) -> None:
        self.estimate = NoiseEstimate(n_meas) if estimating else None  # None: not estimated
        self.level: float | None = None  # the estimated level in use (volts)
        self._from = ""  # ... and what it was estimated from
        self._next = MIN_PAIRS  # the pair count at which the estimate is evaluated next
        self._note = ""  # why no estimate is in use yet

    def restart(self) -> None:
        """No frame pair across this point (a tare, an outage)."""
        if self.estimate is not None:
            self.estimate.restart()

    def text(self, noise_measured: bool, noise_source: str) -> str:
        """What noise the estimators use, in words (the pipeline's ``noise_source``; ``noise_measured``: by the
        tare): measured by the tare, estimated from N frame pairs (with its SNR), or assumed (and why no
        estimate is in use yet)."""
        if noise_measured or self.level is not None or self.estimate is None:
            return noise_source
        return f"{noise_source} ({self._note or f'estimating: {self.estimate.count} of {MIN_PAIRS} frame pairs'})"

    def _usable(self, level: float, pairs: int, agree: float, where: str = "") -> bool:
        """Whether an estimate of ``level`` volts from ``pairs`` pairs, ``agree`` of them agreeing, may
        be used (force/reference/noise_estimate.py); if not, :meth:`text` says why."""
        if is_time_series(pairs, agree):
            return True
        if pairs < MIN_PAIRS:
            self._note = f"not estimated: {pairs} frame pairs {where}, fewer than {MIN_PAIRS}".replace("  ", " ")
        else:
            self._note = (f"not estimated: only {agree:.0%} of {pairs} consecutive frame pairs {where} "
                          f"differ by noise alone (at least {AGREE_FRACTION:.0%} needed): frames of "
                          "distinct loads, not a time series?").replace("  ", " ")
        return False

    def from_frames(self, frames: np.ndarray, keep: np.ndarray, source: str) -> tuple[float, str] | None:
        """The (level, source) of a whole file of consecutive ``frames`` (n, n_meas) over the channels
        ``keep``, by the running estimate's rules; None when not usable (:meth:`text` says why). The
        running estimate ends (the file holds no more)."""
        level, pairs, agree = noise_level(frames, keep)
        if not self._usable(level, pairs, agree, f"of {source}"):
            return None
        self.estimate = None
        return level, f"estimated from {pairs} frame pairs of {source}"

    def observe(self, values: np.ndarray, keep: np.ndarray | None, processed: int) -> tuple[float, str] | None:
        """A processed frame (the ``processed``-th; ``keep`` its channels, None: all) into the running
        estimate (every frame's pair until an estimate is in use, then one in
        :data:`~cstomo_sensor.force.reference.noise_estimate.SAMPLE_EVERY`). The estimate is evaluated every
        :data:`~cstomo_sensor.force.reference.noise_estimate.MIN_PAIRS` pairs
        until one is in use, then every :data:`~cstomo_sensor.force.reference.noise_estimate.UPDATE_EVERY`: returns the (level, source) to
        use when none is or it moved by more than :data:`~cstomo_sensor.force.reference.noise_estimate.RETUNE`, else None."""
        est = self.estimate
        est.observe(values, keep, pair=self.level is None or processed % SAMPLE_EVERY == 0)
        if est.pairs < self._next:
            return None
        self._next = est.pairs + (UPDATE_EVERY if self.level is not None else MIN_PAIRS)
        level, agree = est.level()
        if not self._usable(level, est.count, agree):
            return None
        if self.level is None or abs(level / self.level - 1.0) > RETUNE:
            return level, f"estimated from {est.count} frame pairs"
        return None

    def kept(self, noise_measured: bool) -> tuple[float, str] | None:
        """After a new reference (``noise_measured``: its noise measured by the tare): the (level, source) in
        use, to use again unless measured (the board's noise is constant over a session; docs/physics.md#real-devices)."""
        if noise_measured or self.level is None:
            return None
        found, self.level = (self.level, self._from), None
        return found

    @staticmethod
    def named(level: float, source: str, reference: np.ndarray) -> str:
        """The pipeline's ``noise_source`` of an estimated ``level`` (volts) from ``source``: with its SNR
        against ``reference``."""
        return f"{source} ({snr_db(level, reference):.1f} dB)"

    def refused(self, err: ConfigError) -> None:
        """The pipeline refused the level offered (outside a board's range against the reference,
        device.NOISE_DB_RANGE): the noise in use stays; said once per reason, evaluated again later."""
        note = f"estimate not used: {err}"
        if note != self._note:  # once per reason, not every evaluation
            log.warning("noise %s", note)
        self._note = note
        self._next = self.estimate.pairs + UPDATE_EVERY if self.estimate is not None else 0

    def took(self, level: float, source: str, in_use: str) -> None:
        """The pipeline took the estimated ``level`` (volts, every channel) from ``source``; ``in_use``: its
        ``noise_source`` now."""
        self.level, self._from, self._note = level, source, ""
        log.info("noise %s: the estimators use it instead of the %s", in_use, NOISE_ASSUMED)
