"""The device's own directions (issue 34): what its rest frames say its change is, beyond the model's.

The drift tracker (:class:`~.drift.DriftTracker`) follows the device along the model's directions: a
uniform scale, the contacts' impedance (alike and linear along x, y, z), the resistivity's gradient along
x, y, z. A real device's change after its tare is not exactly these (one electrode's contact drifting
alone, a warming that is not linear across the block, a device whose response to a gradient is not the
nominal one's): the part they leave stays in every frame and reads as a force. :class:`DirectionLearner`
learns it from the device's own rest frames and the tracker follows each learned direction as one more
state, with the same Kalman machinery as the model's (measured at rest, followed under load by its
slope against the scale, widened at a restart).

How. Each clear frame's change (*Which frames*), whitened by its noise, less its least-squares fit by every
tracked direction (its **residual**: what the tracked states cannot explain whatever their values), goes into
running sums (the residuals' sum and second moment, and their products with the tracked scale), as means of
:data:`AVG` frames (the device changes slowly: the mean keeps its change and a tenth of the noise), a batch of
:data:`EVERY` means at a time. The residuals' covariance about their mean (the reference's own noise is
constant over the frames: not learned) is decomposed (*When*). It is first normalised by its own diagonal:
each channel's noise as these frames measure it (a tare of 20 frames measures a channel's noise to within a
factor 0.6..1.6, and a channel whose noise it underestimated would otherwise lead). A device whose change is
the model's leaves noise only: nothing is learned. At most :data:`MAX_DIRECTIONS` are learned; after one, the
sums are projected off it and the next is sought among what is left.

Which frames. Every frame the rest test counts as rest, and every frame it refuses while no load came since
the latest rest frame (:class:`Unloaded`: no step of the force, no controller's expected load beyond the
rest force): a change none of the tracked directions describe reads as a phantom force that keeps the frames
from counting as rest (a loose contact: 80 % of a session's frames), and it is what is to be learned; a load
comes in a step, and after it only a rest frame clears the frames again, so a held load is never learned.

When. After :data:`FIRST` samples, twice as many, up to :data:`DECIDE`, then every DECIDE more. The leading
component is learned when its ratio to the covariance's :data:`BULK`-th largest (the noise's own: no
direction, learned or to be learned, reaches it) exceeds the noise's edge for that many samples
(:func:`noise_edge`, derived, not tuned: few samples spread the noise's components further), and at least
:data:`LEARN_RATIO` (a real noise's own spread, which many samples do not shrink).

Off the frame's time. A decision takes a snapshot of the sums; the decomposition (:class:`_Lanczos`, the BULK
largest of a covariance of about 200 channels: 3-5 ms of CPU, 15-25 ms on a loaded host, in one frame before)
runs :data:`STEPS` Lanczos steps a frame (:meth:`DirectionLearner.tick`, every frame) and its decision is
applied at the frame it ends in: the same frame on every run of the same frames (the node, ``cstomo replay``,
``cstomo estimate``), no thread.

A learned direction is kept in the tracker's units (the normalised change ``y``, scaled so that one unit of
its state is as large, whitened, as a uniform change of one), with its slope against the scale over the
rests that learned it (``per_scale``): a restart from an old tare (:meth:`~.drift.DriftTracker.widen`)
widens its state by that slope (at least :data:`~.drift.RESTART_GRADIENT`; :data:`UNKNOWN_PER_SCALE` when
the scale did not span :data:`~.drift_parts.FOLLOW_SPAN` while it was learned) times the scale's restart 1-sigma.
The directions are saved beside the tare (:func:`write_directions`, ``<tare>.directions.csv``) each time
one is learned, and read back at a restart (the node's start, ``cstomo estimate --reference``, ``cstomo
replay --reference``): a restart starts with them. A calibration recording teaches them too: ``cstomo calibrate``
runs it through the calibration's stream, the frames its reference sensor says are unloaded feeding the learner
(tools/calibrate.py ``recording_directions``), and saves them in the calibration file (:func:`directions_doc`,
``learned_directions``); a stream of that calibration starts with them, and a saved tare's own, newer, take their
place. A tare file without one and a calibration without them (older, or a device that learned none) start with
the model's only.
docs/node.md, *The device's own directions*.
"""
from __future__ import annotations

import math
import re
from collections import deque
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.linalg import eigh_tridiagonal, eigvalsh_tridiagonal

from ...errors import ConfigError, CstomoError, FrameError
from ...frames_io import read_frames, write_frames
from .drift_parts import FOLLOW_SPAN

#: Rest frames averaged into one sample of the residuals (0.1 s at 100 frames/s): the device changes over
#: minutes, so the mean of AVG rest frames keeps all of its change and a tenth of their noise (a direction is
#: found sqrt(AVG) times smaller than from single frames: the covariance's spike threshold, sqrt(p / n)); the
#: residual is computed once per sample (its projection is linear), a rest frame costs a sum of 208 numbers.
AVG = 10
#: Samples per batch folded into the sums (one 208 x 50 product, 1-3 ms).
EVERY = 50
#: Samples at the first decision (500 clear frames: 5 s at 100 frames/s), then at twice as many up to DECIDE,
#: then every DECIDE more: early, so that a device whose change keeps most of its frames from counting as rest
#: learns from the few it has, each decision against the noise's edge for its own sample count (noise_edge).
FIRST, DECIDE = 50, 200
#: The noise's edge (noise_edge): its largest component's Tracy-Widom quantile. 4.0: exceeded by noise alone
#: with a probability of about 1e-4 per decision (the law's upper tail); checked against white noise in
#: test_learned (200 channels: the edge over the 99th percentile of 300 draws 1.03-1.11 for 900..30 samples).
EDGE_TW = 4.0
#: ... and at least LEARN_RATIO: the white noise's edge falls toward 1 as the samples grow (1.135 at 900, 1.05
#: at 10000), but a real noise is not white: its own components spread (device_c's coarse truth, 60 dB, a
#: uniform change or none: 1.05-1.10 at 900 samples, 1.10 at 800 where the white edge is 1.14), and that spread
#: stays however many samples. One electrode's contact +20 %: 1.47 at 900 samples.
LEARN_RATIO = 1.3
#: The leading component is sought beside the noise's BULK largest: the BULK-th largest is the noise's own
#: (at most MAX_DIRECTIONS are learned, the tracked ones are projected off), the ratio of the largest to it
#: the decision's statistic.
BULK = 5
#: Lanczos steps per frame of a decomposition under way (DirectionLearner.tick): 20-60 us each on a loaded
#: host; a decomposition of the 200 channels in use takes at most 200 steps (fewer while the samples are
#: fewer than the channels: the covariance's rank), 1-2 s of frames at 100 frames/s, never one frame's 15-25 ms.
STEPS = 1
#: A frame the rest test refuses feeds the learner while no load came since the latest rest frame (Unloaded):
#: a load comes within tenths of a second, so a step of the force, its mean over STEP_FAST s against its mean
#: over STEP_SLOW s apart by more than STEP_SIGMAS times their difference's noise (at least STEP_N newtons),
#: ends the chain (60 dB: 0.19 N; a 0.5 N load put on in 0.1 s is seen within 0.3 s). A device's change moves
#: the two means apart by its rate times 0.8 s: a phantom growing 1.5 N in 30 s (a loose contact) by 0.04 N,
#: the noise's 3-D excursions the rest (clear for 30 s on 8 noise seeds of 8; test_learned checks one). A load put on more
#: slowly than about 0.1 N/s is taken for the device (docs/node.md).
STEP_FAST, STEP_SLOW = 0.2, 1.0
#: ... and a load's first frames come before its step is seen: a sample counts HOLD_S after its last frame, and
#: the samples still held when the chain ends are dropped (DirectionLearner.discard).
HOLD_S = 0.5
STEP_SIGMAS, STEP_N = 6.0, 0.12
#: Directions learned at most (each one more state of the tracker).
MAX_DIRECTIONS = 2
#: The restart's 1-sigma per unit of the scale's of a direction learned while the scale did not move
#: (its slope unknown): the contacts' (force/slow_states/drift.py RESTART_CONTACT).
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

    @classmethod
    def checked(cls, rows: object, per_scale: object, n_meas: int, where: str, error: type[CstomoError] = ConfigError,
                names: tuple[str, str] = (".rows", ".restart_per_scale"), hint: str = "") -> Directions:
        """``rows`` and their slopes ``per_scale`` as read (numbers in lists or arrays; None: none found) checked:
        1 to :data:`MAX_DIRECTIONS` rows of ``n_meas`` finite numbers, not all zero, and one finite slope >= 0 per
        row; else ``error``, one line naming the part (``where`` + ``names``' rows' or slopes'), the value found
        and what was expected, then ``hint`` (what to do). Both readers' check: a saved tare's directions file
        (:func:`read_directions`) and a calibration file's block (:func:`directions_of_doc`)."""
        rows_at, slopes_at = (where + name for name in names)
        want = f"1 to {MAX_DIRECTIONS} rows of {n_meas} finite numbers, not all zero"
        try:
            r = np.array(rows, dtype=float)
        except (TypeError, ValueError):
            r = None
        if r is None or r.ndim != 2 or not 1 <= len(r) <= MAX_DIRECTIONS or r.shape[1] != n_meas:
            shape = "not a table of numbers" if r is None else f"of shape {r.shape}"
            raise error(f"{rows_at} {shape}: expected {want}{hint}")
        bad = ~np.isfinite(r).all(axis=1) | ~(np.abs(r).max(axis=1) > 0)
        if bad.any():
            raise error(f"{rows_at}: row {int(np.flatnonzero(bad)[0]) + 1} is not finite or all zero: expected {want}"
                        f"{hint}")
        try:
            ks = None if per_scale is None else np.array(per_scale, dtype=float).reshape(-1)
        except (TypeError, ValueError):
            ks = None
        if ks is None or len(ks) != len(r) or not (np.isfinite(ks).all() and (ks >= 0).all()):
            expected = f"{len(r)} finite number(s) >= 0, one per row"
            if issubclass(error, ConfigError):
                raise error.bad_value(slopes_at, per_scale, expected + hint)
            found = " missing" if per_scale is None else f"={per_scale!r}"
            raise error(f"{slopes_at}{found}: expected {expected}{hint}")
        return cls(r, ks)

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
    a device that learned none); :class:`~cstomo_sensor.errors.FrameError` naming the file if malformed
    (:meth:`Directions.checked`)."""
    path = directions_path(reference_path)
    if not path.is_file():
        return None
    rows = read_frames(path, n_meas)
    ks = None  # the slopes as written: the words of the comment '# restart per scale: k1 ... kN'
    with open(path, encoding="utf-8", errors="replace") as f:
        for line in f:
            m = _PER_SCALE.match(line.strip())
            if m:
                ks = m.group(1).split()
                break
    return Directions.checked(rows, ks, n_meas, str(path), FrameError,
                              names=(": rows", f": {PER_SCALE_COMMENT.rstrip(':')}"))


#: The calibration file's key of the directions learned from its recording (force/reference/calibration.py).
CALIBRATION_KEY = "learned_directions"


def directions_doc(directions: Directions, note: str = "") -> dict:
    """``directions`` as the calibration file's block (:data:`CALIBRATION_KEY`, docs/formats.md#calibration-file):
    ``restart_per_scale`` (k numbers), ``rows`` (k rows of n_meas numbers) and ``note`` (how they were learned)."""
    return {**({"note": note} if note else {}),
            "restart_per_scale": [float(f"{k:.6g}") for k in directions.per_scale],
            "rows": [[float(f"{v:.9g}") for v in row] for row in directions.rows]}


def directions_of_doc(block: object, n_meas: int, where: str) -> Directions:
    """The calibration file's block (:func:`directions_doc`) read back and checked (:meth:`Directions.checked`):
    1 to :data:`MAX_DIRECTIONS` rows of ``n_meas`` finite numbers, not all zero, and one slope >= 0 each; else
    :class:`~cstomo_sensor.errors.ConfigError` naming ``where``, the value and what was expected."""
    key = f"{where}: {CALIBRATION_KEY}"
    if not isinstance(block, dict) or "rows" not in block or "restart_per_scale" not in block:
        found = sorted(block) if isinstance(block, dict) else type(block).__name__
        raise ConfigError(f"{key}: {found!r}, expected a mapping with 'rows' and 'restart_per_scale' "
                          "(written by cstomo calibrate); damaged? calibrate again, or delete the block")
    return Directions.checked(block["rows"], block["restart_per_scale"], n_meas, key, ConfigError,
                              hint="; damaged? calibrate again, or delete the block")


def empty(n_meas: int) -> Directions:
    return Directions(np.zeros((0, n_meas)), np.zeros(0))


class Unloaded:
    """Whether a frame the rest test refuses may still feed the learner (module docstring, *Which frames*): no
    load came since the latest rest frame. A load comes in tenths of a second, the device's change over
    minutes: a step of the frame's force (its mean over :data:`STEP_FAST` s against its mean over
    :data:`STEP_SLOW` s, beyond :data:`STEP_SIGMAS` times their difference's noise, at least :data:`STEP_N`)
    or a controller's expected load beyond the rest force ends the chain of clear frames; only a rest frame
    begins it again."""

    def __init__(self) -> None:
        self.fast = self.slow = None
        self.clear = False  # no load since the latest rest frame
        self.broke = False  # the latest frame ended the chain (a step, a known load, a refused frame)
        self._dt, self._k = None, None

    def step(self, force: np.ndarray | None, rest: bool, sigma: float, dt: float, known: bool) -> bool:
        """A frame's estimated ``force`` (3,) N (None: refused, not finite), whether the rest test counted it
        (``rest``), the force's per-frame noise ``sigma`` (N, per axis), the time since the previous frame
        ``dt`` (s) and whether a load is known (``known``: a controller's expected load): whether the frame
        feeds the learner: a rest frame, or a clear one."""
        f = None if force is None else force.tolist() if isinstance(force, np.ndarray) else list(force)
        if f is None or not (math.isfinite(f[0]) and math.isfinite(f[1]) and math.isfinite(f[2])):
            self.clear, self.broke = False, True
            return rest
        if dt != self._dt:  # frames come at one rate: the factors once
            if dt > 0:
                a, b = 1.0 - math.exp(-dt / STEP_FAST), 1.0 - math.exp(-dt / STEP_SLOW)
                # the per-axis variance of the two means' difference for white noise of unit variance
                var = a / (2.0 - a) + b / (2.0 - b) - 2.0 * a * b / (1.0 - (1.0 - a) * (1.0 - b))
                self._k = (a, b, math.sqrt(max(var, 0.0)))
            else:  # a frame on its predecessor's stamp (a coarse or simulated clock): no time for the means to move
                self._k = (0.0, 0.0, self._k[2] if self._k is not None else 0.0)
            self._dt = dt
        a, b, sd = self._k
        if self.fast is None:  # the means on 3 Python floats each (2 us, where numpy's small-array calls took 10)
            self.fast, self.slow = f, list(f)
        else:  # (unrolled: a comprehension's generator costs more than the arithmetic)
            (p0, p1, p2), (q0, q1, q2), (v0, v1, v2) = self.fast, self.slow, f
            self.fast = [p0 + a * (v0 - p0), p1 + a * (v1 - p1), p2 + a * (v2 - p2)]
            self.slow = [q0 + b * (v0 - q0), q1 + b * (v1 - q1), q2 + b * (v2 - q2)]
        (p0, p1, p2), (q0, q1, q2) = self.fast, self.slow
        d0, d1, d2 = p0 - q0, p1 - q1, p2 - q2
        bound = max(STEP_N, STEP_SIGMAS * sd * sigma)
        moved = d0 * d0 + d1 * d1 + d2 * d2 > bound * bound
        self.broke = moved or known
        self.clear = (self.clear or rest) and not self.broke
        return self.clear or rest  # a rest frame feeds it as ever (the rest test's own verdict)


def noise_edge(n: int, p: int) -> float:
    """The noise's largest over its :data:`BULK`-th largest component of a covariance of ``n`` samples of ``p``
    independent channels (about their mean, normalised by its diagonal) that noise alone exceeds with a
    probability of about 1e-4 (module docstring, *When*): the Tracy-Widom law of the largest eigenvalue
    (Johnstone 2001, real Wishart: centre ``mu``, scale ``sigma``) at :data:`EDGE_TW`, over the BULK-th's
    typical place at the edge (the Airy density's ``(3 pi (k - 1/2) / 2)^(2/3)`` scales below it)."""
    n1 = max(n - 1, 2)
    a, b = math.sqrt(n1), math.sqrt(max(p, 2))
    mu = (a + b) ** 2 / n1
    sigma = (a + b) * (1.0 / a + 1.0 / b) ** (1.0 / 3.0) / n1
    low = mu - (1.5 * math.pi * (BULK - 0.5)) ** (2.0 / 3.0) * sigma
    return (mu + EDGE_TW * sigma) / low if low > 0 else math.inf


class _Lanczos:
    """The :data:`BULK` largest components of the normalised covariance of a snapshot of the sums, a few
    :data:`STEPS` at a time (module docstring, *Off the frame's time*): Lanczos with full
    re-orthogonalisation from a fixed start, exact after as many steps as the covariance's rank (at most
    its size); then its tridiagonal's BULK largest."""

    def __init__(self, S2: np.ndarray, S1: np.ndarray, n: int, keep: np.ndarray, extra: tuple) -> None:
        self.snap = (S2.copy(), S1.copy(), n, keep)
        self.extra = extra  # the slope's sums at the snapshot (decide)
        self.C = self.Q = None
        self.j = 0
        self.done = False

    def _start(self) -> None:
        """The covariance about the mean over the channels in use (one frame), then normalised (the next)."""
        S2, S1, n, keep = self.snap
        if self.C is None:
            k = np.flatnonzero(keep)
            C = S2[k][:, k]
            C /= n
            self.mu = mu = S1 / n
            C -= np.multiply.outer(mu[k], mu[k])
            self.C, self.n = C, n
            return
        # against the noise's own second moment, channel by channel (module docstring)
        C = self.C
        self.d = d = np.sqrt(np.maximum(C.diagonal(), 1e-300))
        C /= np.multiply.outer(d, d)
        k = len(C)
        self.Q = np.zeros((k + 1, k))
        q = np.random.default_rng(0).standard_normal(k)  # a fixed start: the same steps on every replay
        self.Q[0] = q / np.linalg.norm(q)
        self.alpha, self.beta = [], []
        self.tol = 1e-10 * max(float(np.trace(C)), 1e-300)

    def step(self, steps: int) -> bool:
        """``steps`` more Lanczos steps (the first two calls form the normalised covariance): True when done."""
        if self.Q is None:
            self._start()
            return False
        C, Q, k = self.C, self.Q, len(self.C)
        for _ in range(steps):
            j = self.j
            w = np.dot(C, Q[j])
            a = float(np.dot(Q[j], w))
            Qj = Q[:j + 1]
            for _ in range(2):  # full re-orthogonalisation, twice: the Ritz values of the bulk stay exact
                w -= np.dot(np.dot(Qj, w), Qj)
            b = float(np.linalg.norm(w))
            self.alpha.append(a)
            self.j = j + 1
            if b <= self.tol or self.j >= k:  # the Krylov space is invariant: every component it holds is exact
                self.done = True
                return True
            self.beta.append(b)
            Q[j + 1] = w / b
        return False

    def values(self) -> np.ndarray | None:
        """The BULK largest components' variances (ascending), None if too few."""
        K = len(self.alpha)
        if K <= BULK:
            return None
        return eigvalsh_tridiagonal(np.array(self.alpha), np.array(self.beta[:K - 1]), select="i",
                                    select_range=(K - BULK, K - 1))

    def leading(self) -> np.ndarray:
        """The leading component's unit vector (over the channels in use)."""
        K = len(self.alpha)
        _, s = eigh_tridiagonal(np.array(self.alpha), np.array(self.beta[:K - 1]), select="i",
                                select_range=(K - 1, K - 1))
        return np.dot(s[:, -1], self.Q[:K])

    def result(self) -> tuple[np.ndarray, np.ndarray] | None:
        """(the BULK largest components' variances, ascending; the leading one's unit vector) or None (too few)."""
        lam = self.values()
        return None if lam is None else (lam, self.leading())


class DirectionLearner:
    """The running sums of the rest residuals and the decision (module docstring) for a tracker's
    directions. :meth:`add` a clear frame's change ``y`` (the tracker's; :class:`Unloaded`), :meth:`tick`
    every frame: it returns a newly learned (row, per_scale) every so often, else None."""

    def __init__(self, n_meas: int, learned: int = 0) -> None:
        self.p = n_meas
        self.learned = learned  # directions learned so far (the tracker's, saved ones included)
        self.unloaded = Unloaded()
        self._batch = np.zeros((EVERY, n_meas))
        self._s = np.zeros(EVERY)
        self._k = 0
        self._ysum, self._ssum, self._j = np.zeros(n_meas), 0.0, 0  # the sample being averaged (AVG)
        self.n = 0  # samples (AVG rest frames each) in the sums
        self._S1 = np.zeros(n_meas)
        self._S2 = np.zeros((n_meas, n_meas))
        self._Ss = np.zeros(2)  # sums of s and of s^2
        self._Sxs = np.zeros(n_meas)
        self._for = None  # the tracker the projection is for
        self._proj = None
        self._next = FIRST  # the samples at the next decision
        self._run: _Lanczos | None = None  # the decomposition under way (tick)
        self.decisions = 0
        self.fed = 0  # frames added (diagnostics, tests)
        self.frames = 0  # frames ticked
        self._pending: deque = deque()  # samples held (release frame, residual, scale)
        self._hold_dt, self._hold = None, max(1, math.ceil(HOLD_S / 0.01))
        self.last_ratio = 0.0  # the latest decomposition's leading variance over the noise's (diagnostics, tests)
        self.max_ratio = 0.0  # ... and the largest so far
        self.last_edge = math.inf  # ... the noise's edge for its samples (noise_edge)
        self.max_excess = 0.0  # ... and the largest ratio over its edge so far (> 1: learned)
        self.history: list[tuple[int, float, float]] = []  # every decision's (samples, ratio, edge)

    def _projection(self, tracker) -> None:
        """The least-squares residual's operator for ``tracker``'s directions (whitened)."""
        Dw = tracker.whitened_directions
        N = Dw @ Dw.T
        self._A = np.linalg.solve(N + 1e-12 * np.trace(N) * np.eye(len(N)), Dw)  # (m, p): coefficients of yw
        self._Dw, self._w, self._keep = Dw, tracker.weights, tracker.weights > 0
        self._rho = float(np.linalg.norm(Dw[0]))
        self._m = len(Dw)
        self._for = tracker

    def add(self, tracker, y: np.ndarray) -> None:
        """A clear frame's change ``y`` (n_meas,) as ``tracker`` took it, at its scale now."""
        if self.learned >= MAX_DIRECTIONS:  # all learned: nothing more to look for
            return
        self.fed += 1
        self._ysum += y
        self._ssum += tracker.scale - 1.0
        self._j += 1
        if self._j < AVG:
            return
        if self._for is not tracker:
            self._projection(tracker)
        yw = self._ysum * (self._w / AVG)
        s_mean = self._ssum / AVG
        self._ysum[:], self._ssum, self._j = 0.0, 0.0, 0
        res = yw - self._A.dot(yw).dot(self._Dw)
        if not np.isfinite(res).all():
            return
        # held HOLD_S before it counts: a load's first frames feed it before its step is seen (discard)
        self._pending.append((self.frames + self._hold, res, s_mean))

    def discard(self) -> None:
        """The chain of clear frames ended (:class:`Unloaded`): the samples not yet counted, and the one being
        averaged, may hold a load's first frames: dropped."""
        self._pending.clear()
        self._ysum.fill(0.0)
        self._ssum, self._j = 0.0, 0

    def _commit(self, res: np.ndarray, s_mean: float) -> None:
        self._batch[self._k] = res
        self._s[self._k] = s_mean
        self._k += 1
        if self._k < EVERY:
            return
        B, s = self._batch, self._s
        self._S2 += B.T @ B
        self._S1 += B.sum(axis=0)
        self._Sxs += s @ B
        self._Ss[0] += s.sum()
        self._Ss[1] += s.dot(s)
        self.n += EVERY
        self._k = 0
        if self.n >= self._next and self._run is None and self._for is not None:
            # a decision: the sums now, decomposed STEPS at a time over the next frames (tick)
            self._next = self.n * 2 if self.n < DECIDE else self.n + DECIDE
            self._run = _Lanczos(self._S2, self._S1, self.n, self._keep,
                                 (self._Ss.copy(), self._Sxs.copy(), self._m))

    def tick(self, tracker, dt: float | None = None) -> tuple[np.ndarray, float] | None:
        """A frame (every one, clear or not; ``dt`` s after the previous): the samples held HOLD_S counted, the
        decomposition under way a few steps on; when it is done, its decision: a newly learned (row, per_scale),
        else None."""
        self.frames += 1
        if dt is not None and dt > 0 and dt != self._hold_dt:
            self._hold_dt, self._hold = dt, max(1, math.ceil(HOLD_S / dt))
        while self._pending and self._pending[0][0] <= self.frames:
            self._commit(*self._pending.popleft()[1:])
        run = self._run
        if run is None or not run.step(STEPS):
            return None
        self._run = None
        if self.learned >= MAX_DIRECTIONS:
            return None
        return self._decide(run)

    def _decide(self, run: _Lanczos) -> tuple[np.ndarray, float] | None:
        self.decisions += 1
        lam = run.values()
        if lam is None:
            return None
        n, mu, d, keep = run.n, run.mu, run.d, run.snap[3]
        Ss, Sxs, m = run.extra
        # the noise's own largest components: the bulk's edge, read where no direction can reach (BULK-th largest)
        bulk = float(lam[-BULK])
        self.last_ratio = float(lam[-1] / bulk) if bulk > 0 else 0.0
        self.max_ratio = max(self.max_ratio, self.last_ratio)
        # the channels the residual spans: those in use less the tracked directions projected off
        self.last_edge = max(LEARN_RATIO, noise_edge(n, int(np.count_nonzero(keep)) - m))
        self.max_excess = max(self.max_excess, self.last_ratio / self.last_edge)
        self.history.append((n, self.last_ratio, self.last_edge))
        if not self.last_ratio > self.last_edge:
            return None
        # the direction, whitened again: the leading component of the covariance over the normalised one's channels
        v = run.leading() * d
        v /= max(float(np.linalg.norm(v)), 1e-300)
        u = np.zeros(self.p)
        u[keep] = v
        ms, vs = Ss[0] / n, Ss[1] / n - (Ss[0] / n) ** 2
        cov = Sxs / n - mu * ms
        slope = float(u.dot(cov)) / vs / self._rho if vs > FOLLOW_SPAN ** 2 else math.nan
        if math.isfinite(slope) and slope < 0:
            u, slope = -u, -slope
        per_scale = slope if math.isfinite(slope) else UNKNOWN_PER_SCALE
        row = np.where(keep, u * self._rho / np.where(keep, self._w, 1.0), 0.0)  # y units, a uniform change's size
        # what is left is sought off it: the sums (all of them, the samples since the snapshot too) projected
        # (whitened, u is a unit vector)
        # (I - u u^T) S2 (I - u u^T) as rank-one updates: O(p^2), not two products of O(p^3)
        S2u = np.dot(self._S2, u)
        uS2u = float(u.dot(S2u))
        self._S2 -= np.multiply.outer(u, S2u) + np.multiply.outer(S2u, u) - uS2u * np.multiply.outer(u, u)
        self._S1 -= u * float(u.dot(self._S1))
        self._Sxs -= u * float(u.dot(self._Sxs))
        self.learned += 1
        return row, per_scale
