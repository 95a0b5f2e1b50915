"""The device's own directions (issue 34): what its rest frames say its change is, beyond the model's.

The drift tracker (:class:`~.drift.DriftTracker`) follows the device along the model's directions: a
uniform scale, the contacts' impedance (alike and linear along x, y, z), the resistivity's gradient along
x, y, z. A real device's change after its tare is not exactly these (one electrode's contact drifting
alone, a warming that is not linear across the block, a device whose response to a gradient is not the
nominal one's): the part they leave stays in every frame and reads as a force. :class:`DirectionLearner`
learns it from the device's own rest frames and the tracker follows each learned direction as one more
state, with the same Kalman machinery as the model's (measured at rest, followed under load by its
slope against the scale, widened at a restart).

How. Each rest frame's change, whitened by its noise, less its least-squares fit by every tracked
direction (its **residual**: what the tracked states cannot explain whatever their values), goes into
running sums (the residuals' sum and second moment, and their products with the tracked scale), as means
of :data:`AVG` rest frames (the device changes slowly: the mean keeps its change and a tenth of the noise),
a batch of :data:`EVERY` means at a time; every :data:`DECIDE` means (not per frame: a rest frame costs a
sum of its change, a tenth of a residual and a share of a batch's product) the residuals' covariance about their mean is decomposed (the
reference's own noise is constant over the frames: not learned). It is first normalised by its own
diagonal: each channel's noise as these frames measure it (a tare of 20 frames measures a channel's noise
to within a factor 0.6..1.6, and a channel whose noise it underestimated would otherwise lead). Its
leading component is learned when it exceeds :data:`LEARN_RATIO` times the noise's own edge, read from the
same covariance as its :data:`BULK`-th largest component (no direction, learned or to be learned, reaches
it). A device whose change is the model's leaves noise only: nothing is learned. At most
:data:`MAX_DIRECTIONS` are learned; after one, the sums are projected off it and the next is sought among
what is left.

A learned direction is kept in the tracker's units (the normalised change ``y``, scaled so that one unit of
its state is as large, whitened, as a uniform change of one), with its slope against the scale over the
rests that learned it (``per_scale``): a restart from an old tare (:meth:`~.drift.DriftTracker.widen`)
widens its state by that slope (at least :data:`~.drift.RESTART_GRADIENT`; :data:`UNKNOWN_PER_SCALE` when
the scale did not span :data:`~.rest.FOLLOW_SPAN` while it was learned) times the scale's restart 1-sigma.
The directions are saved beside the tare (:func:`write_directions`, ``<tare>.directions.csv``) each time
one is learned, and read back at a restart (the node's start, ``cstomo estimate --reference``, ``cstomo
replay --reference``): a restart starts with them. A tare file without one (older, or a device that
learned none) starts with the model's only.
docs/node.md, *The device's own directions*.
"""
from __future__ import annotations

import math
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.linalg import eigh

from ..errors import FrameError
from ..frames_io import read_frames, write_frames
from .rest import FOLLOW_SPAN

#: Rest frames averaged into one sample of the residuals (0.1 s at 100 frames/s): the device changes over
#: minutes, so the mean of AVG rest frames keeps all of its change and a tenth of their noise (a direction is
#: found sqrt(AVG) times smaller than from single frames: the covariance's spike threshold, sqrt(p / n)); the
#: residual is computed once per sample (its projection is linear), a rest frame costs a sum of 208 numbers.
AVG = 10
#: Samples per batch folded into the sums (one 208 x 50 product, 1-3 ms).
EVERY = 50
#: Samples per decomposition of the residuals' covariance, and before the first (2000 rest frames: 20 s of
#: rest at 100 frames/s): the BULK largest components of a 208 x 208 matrix take 15-25 ms on a loaded host;
#: the whole learner 28-32 us a rest frame amortized at host load 5.
DECIDE = 200
#: The leading component is learned when its variance exceeds this many times the noise's largest component
#: (module docstring), read as the BULK-th largest component of the same covariance: no learned direction
#: reaches it (at most MAX_DIRECTIONS, and the tracked ones are projected off), so it is the noise's own edge,
#: whatever the noise's correlations and however many frames. The noise alone: 1.05-1.10 (device_c's coarse
#: truth, 60 dB, 9000 rest frames, a uniform change or none); one electrode's contact +20 %: 1.47.
LEARN_RATIO = 1.3
BULK = 5
#: Directions learned at most (each one more state of the tracker).
MAX_DIRECTIONS = 2
#: The restart's 1-sigma per unit of the scale's of a direction learned while the scale did not move
#: (its slope unknown): the contacts' (force/drift.py RESTART_CONTACT).
UNKNOWN_PER_SCALE = 1.9
#: The side file of a tare that holds its learned directions, and its comment line of their slopes.
SUFFIX = ".directions.csv"
PER_SCALE_COMMENT = "restart per scale:"
_PER_SCALE = re.compile(r"#\s*" + re.escape(PER_SCALE_COMMENT) + r"(.*)$")


@dataclass(frozen=True)
class Directions:
    """Learned directions: ``rows`` (k, n_meas) in the tracker's units (module docstring), ``per_scale`` (k,)
    each one's restart 1-sigma per unit of the scale's."""

    rows: np.ndarray
    per_scale: np.ndarray

    def __len__(self) -> int:
        return len(self.rows)

    def plus(self, row: np.ndarray, per_scale: float) -> Directions:
        return Directions(np.vstack([self.rows, row[None]]), np.append(self.per_scale, per_scale))


def directions_path(reference_path: str | Path) -> Path:
    """Where a saved tare's learned directions are kept: ``<name>.directions.csv`` beside it."""
    p = Path(reference_path)
    return p.with_name(p.stem + SUFFIX)


def write_directions(reference_path: str | Path, directions: Directions, comment: str = "") -> None:
    """Save ``directions`` beside the tare ``reference_path`` (atomically; none: the file removed)."""
    path = directions_path(reference_path)
    if not len(directions):
        path.unlink(missing_ok=True)
        return
    ks = " ".join(f"{k:.6g}" for k in directions.per_scale)
    write_frames(path, directions.rows, comment=(f"{comment}\n" if comment else "")
                 + f"learned directions of the device of the tare {Path(reference_path).name} "
                 f"(docs/formats.md#reference-and-noise-files)\n{PER_SCALE_COMMENT} {ks}")


def read_directions(reference_path: str | Path, n_meas: int = 208) -> Directions | None:
    """The learned directions saved beside the tare ``reference_path``, None without a file (an older tare,
    a device that learned none); :class:`~cstomo_sensor.errors.FrameError` naming the file if malformed."""
    path = directions_path(reference_path)
    if not path.is_file():
        return None
    rows = read_frames(path, n_meas)
    ks = None
    with open(path, encoding="utf-8", errors="replace") as f:
        for line in f:
            m = _PER_SCALE.match(line.strip())
            if m:
                try:
                    ks = np.array([float(x) for x in m.group(1).split()], float)
                except ValueError:
                    ks = None
                break
    if ks is None or len(ks) != len(rows) or not (np.isfinite(ks).all() and (ks >= 0).all()):
        raise FrameError(f"{path}: expected a comment '# {PER_SCALE_COMMENT} k1 ... k{len(rows)}', one slope >= 0 "
                         "per row of learned directions")
    if not np.isfinite(rows).all():
        raise FrameError(f"{path}: a learned direction is not finite")
    return Directions(rows, ks)


def empty(n_meas: int) -> Directions:
    return Directions(np.zeros((0, n_meas)), np.zeros(0))


class DirectionLearner:
    """The running sums of the rest residuals and the decision (module docstring) for a tracker's
    directions. :meth:`add` a rest frame's change ``y`` (the tracker's) and its scale; it returns a newly
    learned (row, per_scale) every so often, else None."""

    def __init__(self, n_meas: int, learned: int = 0) -> None:
        self.p = n_meas
        self.learned = learned  # directions learned so far (the tracker's, saved ones included)
        self._batch = np.zeros((EVERY, n_meas))
        self._s = np.zeros(EVERY)
        self._k = 0
        self._ysum, self._ssum, self._j = np.zeros(n_meas), 0.0, 0  # the sample being averaged (AVG)
        self.n = 0  # samples (AVG rest frames each) in the sums
        self._S1 = np.zeros(n_meas)
        self._S2 = np.zeros((n_meas, n_meas))
        self._Ss = np.zeros(3)  # sum of s, s^2 (and unused)
        self._Sxs = np.zeros(n_meas)
        self._for = None  # the tracker the projection is for
        self._proj = None
        self.last_ratio = 0.0  # the latest decomposition's leading variance over the noise's (diagnostics, tests)
        self.max_ratio = 0.0  # ... and the largest so far

    def _projection(self, tracker) -> None:
        """The least-squares residual's operator for ``tracker``'s directions (whitened)."""
        Dw = tracker._Dw
        N = Dw @ Dw.T
        self._A = np.linalg.solve(N + 1e-12 * np.trace(N) * np.eye(len(N)), Dw)  # (m, p): coefficients of yw
        self._Dw, self._w, self._keep = Dw, tracker._w, tracker._w > 0
        self._rho = float(np.linalg.norm(Dw[0]))
        self._for = tracker

    def add(self, tracker, y: np.ndarray) -> tuple[np.ndarray, float] | None:
        """A rest frame's change ``y`` (n_meas,) as ``tracker`` took it, at its scale now."""
        if self.learned >= MAX_DIRECTIONS:  # all learned: nothing more to look for
            return None
        self._ysum += y
        self._ssum += tracker.scale - 1.0
        self._j += 1
        if self._j < AVG:
            return None
        if self._for is not tracker:
            self._projection(tracker)
        yw = self._ysum * (self._w / AVG)
        s_mean = self._ssum / AVG
        self._ysum[:], self._ssum, self._j = 0.0, 0.0, 0
        res = yw - np.dot(np.dot(self._A, yw), self._Dw)
        if not np.isfinite(res).all():
            return None
        self._batch[self._k] = res
        self._s[self._k] = s_mean
        self._k += 1
        if self._k < EVERY:
            return None
        B, s = self._batch, self._s
        self._S2 += B.T @ B
        self._S1 += B.sum(axis=0)
        self._Sxs += s @ B
        self._Ss[0] += s.sum()
        self._Ss[1] += s.dot(s)
        self.n += EVERY
        self._k = 0
        if self.n % DECIDE:
            return None
        return self._decide(tracker)

    def _decide(self, tracker) -> tuple[np.ndarray, float] | None:
        n = self.n
        mu = self._S1 / n
        keep = self._keep
        C = (self._S2 / n - np.outer(mu, mu))[np.ix_(keep, keep)]
        # against the noise's own second moment, channel by channel: the covariance's diagonal (a tare's noise is
        # measured from a few frames, so the whitened channels' variances spread 0.4..2.4 about 1 and a channel whose
        # noise the tare underestimated would lead); a signal shared by channels stands out of it
        d = np.sqrt(np.maximum(C.diagonal(), 1e-300))
        Cn = C / np.outer(d, d)
        k = len(Cn)
        if k <= BULK:
            return None
        lam, vec = eigh(Cn, subset_by_index=[k - BULK, k - 1])  # the BULK largest only: half a full one's time
        # the noise's own largest components: the bulk's edge, read where no direction can reach (BULK-th largest)
        bulk = float(lam[-BULK])
        self.last_ratio = float(lam[-1] / bulk) if bulk > 0 else 0.0
        self.max_ratio = max(self.max_ratio, self.last_ratio)
        if not self.last_ratio > LEARN_RATIO:
            return None
        # the direction, whitened again: the leading component of the covariance over the normalised one's channels
        v = vec[:, -1] * d
        v /= max(float(np.linalg.norm(v)), 1e-300)
        u = np.zeros(self.p)
        u[keep] = v
        ms, vs = self._Ss[0] / n, self._Ss[1] / n - (self._Ss[0] / n) ** 2
        cov = self._Sxs / n - mu * ms
        slope = float(u.dot(cov)) / vs / self._rho if vs > FOLLOW_SPAN ** 2 else math.nan
        if math.isfinite(slope) and slope < 0:
            u, slope = -u, -slope
        per_scale = slope if math.isfinite(slope) else UNKNOWN_PER_SCALE
        row = np.where(keep, u * self._rho / np.where(keep, self._w, 1.0), 0.0)  # y units, a uniform change's size
        # what is left is sought off it: the sums projected (whitened, u is a unit vector)
        Pu = np.eye(self.p) - np.outer(u, u)
        self._S2 = Pu @ self._S2 @ Pu
        self._S1 = Pu @ self._S1
        self._Sxs = Pu @ self._Sxs
        self.learned += 1
        return row, per_scale
