"""The rules of a tare and their constants (the transaction that applies them: force/reference/tare_transaction.py). No
ROS, no serial.

A tare is never taken under load (issue 20). A tare's frames must be steady (:data:`TARE_MAX_SPREAD`,
:data:`TARE_NOISE_FACTOR`), their mean a frame of this sensor (:func:`tare_problem`); it must end
within its deadline (:func:`tare_deadline`, from the measured frame period). One that passed the
steadiness check is then judged by two figures,
both forces in newtons estimated by the pipeline's own estimator (its calibration, noise and mask):

- **load**: the change from the reference it replaces, ``new / s - old`` in the old reference's
  normalisation, with the uniform-scaling component removed first. A device that warmed (its
  resistivity rose alike everywhere) or a drive current that drifted scales every voltage by the same
  factor (docs/physics.md#device-changes); through the force estimator a 1 % uniform change reads as
  an 18 N "load", so it is taken out: ``s`` is the best global factor between the two references,
  and what is left is projected off the uniform direction (the old reference, normalised) and
  estimated by the estimator retrained on its calibration set projected the same way. The retrained
  estimator is blind to a uniform change and still sees every socket load at its full size: a load
  pressing straight down shares a large part of its change with a uniform one, and the plain
  estimator reads 5 N straight down as 1.3 N once the global factor is divided out (4.1 N once the
  change is projected too). Refused above :data:`TARE_MAX_LOAD` (or above :data:`TARE_NOISE_SIGMAS`
  x the figure's noise, when that is larger).
- **drift**: the linear trend of the tare's own frames, the change from its first frame to its last
  (least-squares slope x (n - 1) frames, per channel), in the new reference's normalisation, through
  the plain estimator: a slow ramp, which the spread check does not see. Refused above
  :data:`TARE_MAX_DRIFT` (or the noise figure). Temperature moves over minutes, not within a tare, so
  no scale is removed here (removing it would make the vertical force about 4 x noisier).

Without a reference to replace (the first tare of a device, no saved tare) there is no load figure:
only the steadiness, the drift and the rms plausibility (:func:`tare_problem`) are checked;
the comparison with the model's predicted frame refuses nothing (a real device's own mismatch with the
model reads as a "load" of several newtons through the estimator: about 12 N for the test bag's
device on the coarse test model) and is only
reported (:class:`~.files.ScaleReport`). With one tare frame there is no drift figure.

Measured (the honestly simulated device of the test bag, seed 7, linear estimator of the coarse test
model, noise-free unless stated): a 1 % uniform resistivity change 0.03 N (15 %: 0.45 N; 15 K warmer
with the contacts' -1 %/K: 0.98 N); 5 N held 5.1-5.3 N at every elevation (2 N: 2.1 N); contact
impedance drift of +-20 % per electrode 0.1-1.1 N; 60 dB noise alone, 50-frame tares: load 0.26 N rms.
A 2 N/s ramp over the default 50 frames at 100 frames/s: drift figure 1.0 N on average, at least 0.76 N
in 100 tares, against a noise of 0.13 N rms. What the check cannot tell from a load: a temperature
rise that varies across the block (docs/physics.md#device-changes: by up to 30 % of its mean) looks
like a lateral load, 0.7-0.8 N per K of mean warming at that largest gradient; such a tare is
refused, and a forced tare takes it. The full table: docs/node.md#tare.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np

from .files import ScaleReport

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
#: Why a pending tare ends when the board comes back after an outage (force/reference/tare_transaction.py).
TARE_RECONNECTED = ("tare refused: the board reconnected during the tare (its frames would span an outage, "
                    "and the joint may be loaded when the board returns)")
#: A tare's deadline (:func:`tare_deadline`): its frames at this many times the frame period, plus
#: ``stale_timeout`` and :data:`TARE_GRACE` s; the period is the measured one (frame_path/health.py), else
#: the nominal rate's, else :data:`TARE_ASSUMED_PERIOD` s with no margin.
TARE_PERIOD_MARGIN = 1.5
TARE_GRACE = 2.0
TARE_ASSUMED_PERIOD = 0.1
#: Largest load (N) a new reference may carry against the one it replaces, uniform scale removed.
#: A 5 N load reads 5.1-5.3 N; a 1 % uniform resistivity change 0.03 N; 60 dB noise 0.26 N rms
#: (module docstring).
TARE_MAX_LOAD = 2.0
#: Largest change of load (N) along the tare's own frames (linear trend, first to last frame). A 2 N/s
#: ramp over the default 50 frames at 100 frames/s reads about 1.0 N; 60 dB noise 0.13 N rms (so
#: the noise's limit, 0.56-0.60 N, applies there with the linear estimator).
TARE_MAX_DRIFT = 0.5
#: Each limit is at least this many times the rms of its figure under the noise alone (measured by the
#: tare, else the estimators' assumed 60 dB): a 40 dB board or a one-frame tare cannot judge a
#: small load, and the limit says so rather than refusing noise.
TARE_NOISE_SIGMAS = 4.0
#: Noise draws of that rms (a fixed seed: the same tare gives the same decision).
NOISE_DRAWS = 64


@dataclass(frozen=True)
class TareCheck:
    """The load figures of a tare (module docstring); NaN where a figure could not be formed.

    ``load`` and ``drift`` in N, with their limits; ``scale`` the global factor new / old reference.
    """

    load: float = math.nan
    load_limit: float = math.nan
    scale: float = math.nan
    drift: float = math.nan
    drift_limit: float = math.nan
    frames: int = 0

    def problems(self) -> list[str]:
        """What refuses the tare ([] when it may be taken)."""
        out = []
        if self.load > self.load_limit:
            out.append(f"it carries a load of {self.load:.2f} N against the reference it replaces (limit "
                       f"{self.load_limit:.2f} N, after removing a uniform scale of {self.scale:.4f})")
        if self.drift > self.drift_limit:
            out.append(f"the load changed by {self.drift:.2f} N along its {self.frames} frames (limit "
                       f"{self.drift_limit:.2f} N: a slow ramp)")
        return out

    def summary(self) -> str:
        """One line of the figures, for the log and the service's answer."""
        parts = []
        if math.isfinite(self.load):
            parts.append(f"load {self.load:.2f} N (limit {self.load_limit:.2f} N, uniform scale {self.scale:.4f} "
                         "removed)")
        else:
            parts.append("no load check (no reference to compare with)")
        if math.isfinite(self.drift):
            parts.append(f"drift {self.drift:.2f} N (limit {self.drift_limit:.2f} N)")
        else:
            parts.append("no drift check (fewer than 3 frames)")
        return ", ".join(parts)


class Pipe(Protocol):
    """What a tare's rules read of a pipeline (frame_path/pipeline.py ``Pipeline``; the force layer does not import
    the frame path): the reference in use (volts; None: none) and the frames averaged into it, the model's
    unloaded frame and the reconstruction model (its ``v_scale``), the force estimator (its noise, mask and
    training set) and the channels excluded. Read, never written."""

    reference: np.ndarray | None
    reference_frames: int
    model_reference: np.ndarray
    model: Any
    estimator: Any
    bad_channels: np.ndarray


def y_scale(pipe: Pipe, reference: np.ndarray) -> np.ndarray:
    """``c * v_scale`` of ``reference``: the normalisation :meth:`~cstomo_sensor.frame_path.pipeline.Pipeline.set_reference`
    gives it (``c`` its global factor against the model's reference)."""
    c = ScaleReport.of(reference, pipe.model_reference).factor
    return (c if np.isfinite(c) and c > 0 else 1.0) * pipe.model.v_scale


def noise_force(estimator, sigma: np.ndarray, project=None) -> float:
    """rms |F| (N) that ``estimator`` gives to a change of per-channel noise ``sigma`` (y units) alone,
    projected by ``project`` first when given (:data:`NOISE_DRAWS` seeded draws)."""
    z = np.random.default_rng(20).standard_normal((NOISE_DRAWS, len(sigma))) * sigma
    if project is not None:
        z = project(z)
    f = np.array([estimator.estimate(row) for row in z])
    return float(np.sqrt(np.mean(np.sum(f**2, axis=1))))


def check_tare(pipe: Pipe, reference: np.ndarray, drift: np.ndarray | None, noise: np.ndarray | None, frames: int,
               used: np.ndarray) -> TareCheck:
    """The figures of a tare whose ``frames`` frames average to ``reference`` (n_meas,) volts, changed
    by ``drift`` (n_meas,) volts from the first to the last along their linear trend (None: not
    formed) with per-channel ``noise`` (volts, None: the estimators' assumed noise), over the channels
    ``used`` (not excluded during the tare), against ``pipe``'s reference if it has one."""
    est = pipe.estimator
    keep = used & ~pipe.bad_channels
    if not np.array_equal(keep, est.keep):
        est = est.masked(keep)
    old = pipe.reference
    ys_new = y_scale(pipe, reference)

    def sigma_y(ys: np.ndarray) -> np.ndarray:
        s = np.asarray(est.noise, float).copy() if noise is None else np.asarray(noise, float) / ys
        floor = 0.1 * float(np.median(s[keep]))
        return np.where(keep, np.maximum(s, floor if floor > 0 else 1e-300), 0.0)

    out = {}
    if old is not None:
        ys_old = y_scale(pipe, old)
        s = float(reference[keep] @ old[keep] / (old[keep] @ old[keep]))
        u = np.where(keep, old / ys_old, 0.0)
        uu = float(u @ u)

        def project(y: np.ndarray) -> np.ndarray:
            return y - np.multiply.outer(y @ u, u) / uu

        blind = est.with_set(est.forces, project(np.asarray(est.y)))  # the estimator blind to a uniform change
        y = np.where(keep, (reference / s - old) / ys_old, 0.0)
        load = float(np.linalg.norm(blind.estimate(project(y))))
        sigma = sigma_y(ys_old) * math.sqrt(1.0 / frames + 1.0 / pipe.reference_frames)
        limit = max(TARE_MAX_LOAD, TARE_NOISE_SIGMAS * noise_force(blind, sigma, project))
        out.update(load=load, load_limit=limit, scale=s)
    if drift is not None and frames >= 3:
        yd = np.where(keep, drift / ys_new, 0.0)
        n = frames
        sigma = sigma_y(ys_new) * (n - 1) * math.sqrt(12.0 / (n * (n * n - 1.0)))
        limit = max(TARE_MAX_DRIFT, TARE_NOISE_SIGMAS * noise_force(est, sigma))
        out.update(drift=float(np.linalg.norm(est.estimate(yd))), drift_limit=limit)
    return TareCheck(frames=frames, **out)


def tare_deadline(frames: int, period: float, rate_hz: float, stale_timeout: float) -> float:
    """Seconds a tare of ``frames`` frames may take (:data:`TARE_PERIOD_MARGIN`): from the measured
    frame ``period`` (s; nan: unknown), never shorter than the nominal ``rate_hz``'s (0: unknown)."""
    if rate_hz > 0:  # a backlog drained at once measures short: never shorter than the nominal rate's
        period = max(period, 1.0 / rate_hz) if period > 0 else 1.0 / rate_hz
    per_frame = TARE_PERIOD_MARGIN * period if period > 0 else TARE_ASSUMED_PERIOD
    return frames * per_frame + stale_timeout + TARE_GRACE


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
class TareOutcome:
    """How a tare ended: ``reference`` (208,) if accepted, else None and ``reason`` says why.

    ``spread`` is the steadiness figure of :data:`TARE_MAX_SPREAD` (0.0 for a one-frame tare);
    ``noise`` (208,) volts the per-channel std of the frames (None for a one-frame tare); ``note``
    says why an accepted tare was not saved ('' when saved or when the stream has no file);
    ``check`` the load figures (:class:`TareCheck`; None when the tare ended before them);
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


def judge_tare(pipe: Pipe, n: int, x0: np.ndarray, s1: np.ndarray, s2: np.ndarray, st: np.ndarray, used: np.ndarray,
               max_spread: float, forced: bool) -> TareOutcome:
    """The outcome of a tare of ``n`` frames by every rule above: their sums taken around the first
    frame ``x0`` (``s1`` of the differences, ``s2`` of their squares, ``st`` of k x the k-th's), over
    the channels ``used`` (none excluded during the tare); ``max_spread`` the setting
    (:data:`TARE_MAX_SPREAD`); ``forced``: the load checks do not refuse it."""
    ref = x0 + s1 / n
    spread = 0.0
    noise = None
    rms = float(np.sqrt(np.mean(ref[used] ** 2))) if used.any() else 0.0
    if n > 1 and rms > 0:
        var = np.maximum(s2 - s1**2 / n, 0.0) / (n - 1)
        spread = float(np.sqrt(var[used].max()) / rms)
        noise = np.sqrt(var)
        noise[~used | ~np.isfinite(noise)] = float(np.median(noise[used]))  # excluded: no data
    if not np.isfinite(ref).all() or not rms > 0 or not np.isfinite(spread):
        return TareOutcome(None, n, spread, "tare refused: the averaged frames hold NaN/Inf or no usable "
                                            "channel; check the board's contacts and cable")
    limit = max_spread
    if noise is not None:
        limit = max(limit, TARE_NOISE_FACTOR * float(np.median(noise[used])) / rms)
    if spread > limit:
        worst = int(np.argmax(np.where(used, var, -1.0))) + 1
        return TareOutcome(None, n, spread, f"tare refused: frames not steady (spread {spread:.2%} of the "
                                            f"reference rms at measurement {worst}, limit {limit:.2%}); keep "
                                            "the sensor still and unloaded during the tare")
    why = tare_problem(ref[used], pipe.model_reference[used])  # flagged channels hold no data
    if why:
        return TareOutcome(None, n, spread, f"tare refused: {why}")
    drift = None
    if n >= 3:  # the linear trend's change from the first frame to the last, per channel
        stt = n * (n * n - 1) / 12.0
        drift = (st - 0.5 * (n - 1) * s1) / stt * (n - 1)
    check = check_tare(pipe, ref, drift, noise, n, used)
    problems = check.problems()
    if problems and not forced:
        return TareOutcome(None, n, spread, f"tare refused: {'; '.join(problems)}; tare with the joint unloaded "
                                            "and still", noise=noise, check=check)
    return TareOutcome(ref.copy(), n, spread, noise=noise, check=check, forced=forced, overridden="; ".join(problems))
