"""A tare is never taken under load: the load checks of a new reference (issue 20). No ROS, no serial.

A tare that passed the steadiness check (:data:`~.stream.TARE_MAX_SPREAD`) is judged by two figures,
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
only the steadiness, the drift and the rms plausibility (:func:`~.stream.tare_problem`) are checked;
the comparison with the model's predicted frame refuses nothing (a real device's own mismatch with the
model reads as a "load" of several newtons through the estimator: about 12 N for the test bag's
device on the coarse test model) and is only
reported (:class:`~.device.ScaleReport`). With one tare frame there is no drift figure.

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

import numpy as np

from .device import ScaleReport

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


def y_scale(pipe, reference: np.ndarray) -> np.ndarray:
    """``c * v_scale`` of ``reference``: the normalisation :meth:`~.pipeline.Pipeline.set_reference`
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


def check_tare(pipe, reference: np.ndarray, drift: np.ndarray | None, noise: np.ndarray | None, frames: int,
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
