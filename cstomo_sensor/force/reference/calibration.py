"""Device calibration on known loads: the model's physics as the prior, corrected by the data.

A real device (docs/physics.md#real-devices) answers a force F with ``y_dev(F)`` (normalised by its
own tare) that differs from the model's ``y_model(F)``: its rubber is stiffer or softer, more or less
piezoresistive, its electrodes sit elsewhere. The calibration models the device as::

    y_dev(F) = y_model(A F) + D F          A : (3, 3),  D : (n_meas, 3) in 1/N

``y_model`` is the model's own simulated calibration set (the estimators' training set), interpolated
at any force by the radial-basis surrogate the ``model`` estimator uses. ``A`` (the force as this
device's rubber feels it: a stiffer, softer or more sensitive batch scales it, an anisotropy tilts it)
is fitted first on every channel together (weighted by the channel noise, Gauss-Newton from the
identity): nine numbers, well determined by three loads in independent directions. ``D`` then takes
what each channel does besides (electrode placement, contact): a ridge fit per channel of the
residuals, shrunk toward zero with a prior std of :data:`PRIOR_REL` times the channel's own model
sensitivity. The estimators are rebuilt on the corrected training set (``A^-1 F``, ``y + D A^-1 F``):
the same estimators and per-frame cost, now fitted to this device.

It fixes what scales or tilts the response to force: the rubber's stiffness, Poisson ratio and
piezoresistive sensitivity (E, nu, phi0, tau), electrode placement and contact, a global gain. It
cannot fix what the model's shape of the response does not hold (a contact that behaves otherwise at
the rim, hysteresis, creep, temperature), loads off the socket, nor a device that changed after the
calibration (a new tare fixes only the reference and a global resistivity factor).

File (YAML, no pickle): format, sensor, model hash (:func:`model_hash`: the forward model the
normalisation and ``y_model`` come from), estimator, prior, the data it was fitted on, the
cross-validated accuracy before and after, ``A`` and ``D``; optionally the rubber's creep and the
device's own directions its recording's rests taught the drift tracker (``learned_directions``,
force/slow_states/learned.py: a stream of this calibration starts with them; a saved tare's own, newer,
take their place). Loading refuses a file of another format, a damaged one (a directions block too:
naming its value and the shape expected), or one fitted against another model (naming both hashes); a
file without directions (every one written before them) loads as before.
"""
from __future__ import annotations

import datetime
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol

import numpy as np
import yaml
from scipy.interpolate import RBFInterpolator

from ...angles import angle_between
from ...cache import input_hash
from ...errors import ConfigError, ModelMismatchError
from ...frames_io import atomic_write
from ..slow_states.creep import creep_problem
from ..slow_states.learned import CALIBRATION_KEY, Directions, directions_doc, directions_of_doc

FORMAT = "cstomo_sensor device calibration 1"
#: Prior std of each correction, relative to the channel's model sensitivity (rms over x, y, z).
PRIOR_REL = 0.2
#: Loads within this distance (N) are one load (its frames stay in one cross-validation fold).
SAME_LOAD_N = 0.5
#: Cross-validation: leave one load out up to this many loads, else this many folds.
MAX_FOLDS = 10


class Calibrated(Protocol):
    """What :func:`calibrate` reads of a pipeline (frame_path/pipeline.py ``Pipeline``; the force layer does not
    import the frame path): its sensor's geometry, the reconstruction model, the estimator in use (its noise
    and estimates) and its name, the estimator before any calibration, and the normalisation of frames by
    the reference in use. Read, never written."""

    geometry: Any
    model: Any
    estimator: Any
    estimator_name: str
    base_estimator: Any

    def normalise(self, frames: np.ndarray) -> np.ndarray: ...


def model_hash(model) -> str:
    """What a calibration depends on: the model's normalisation and its unloaded prediction, to 6
    significant digits (another mesh moves them by 1e-3 and more; a rebuild that differs only in
    rounding, e.g. after an upgrade, keeps the user's calibration)."""
    sig = lambda a: [f"{v:.6g}" for v in np.asarray(a, float)]  # noqa: E731
    return input_hash({"mesh_h": model.meta.get("mesh_h"), "v_scale": sig(model.v_scale),
                       "reference": sig(model.model_reference)})


def _surrogate(forces: np.ndarray, y: np.ndarray) -> RBFInterpolator:
    return RBFInterpolator(forces / 10.0, y, kernel="thin_plate_spline", degree=1)


def fit_correction(forces_cal: np.ndarray, y_cal: np.ndarray, forces: np.ndarray, y: np.ndarray,
                   noise: np.ndarray, prior_rel: float = PRIOR_REL,
                   counts: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(A (3, 3), D (n_meas, 3)) of the module docstring from known ``forces`` (n, 3) and their
    normalised frames ``y`` (n, n_meas), against the model's set (``forces_cal``, ``y_cal``);
    ``noise`` (n_meas,) in y units. With ``counts`` (n,), row i stands for ``counts[i]`` frames of
    force ``forces[i]`` whose mean is ``y[i]``: the same least-squares fit as those frames, row by row
    (the sum of squares over a load's frames is its count times that of their mean, plus a constant)."""
    F, y = np.atleast_2d(forces), np.atleast_2d(y)
    n = np.ones(len(F)) if counts is None else np.asarray(counts, float)
    sur = _surrogate(forces_cal, y_cal)
    w = 1.0 / noise
    rw = np.sqrt(n)[:, None] * w  # each row's weight: its frames' count and each channel's noise
    # 1. A: every channel together (weighted Gauss-Newton from A = I, a weak pull toward I)
    A, h = np.eye(3), 1e-4
    for _ in range(10):
        pred = sur(F @ A.T / 10.0)
        r = ((y - pred) * rw).reshape(-1)
        cols = []
        for k in range(9):
            dA = np.zeros(9)
            dA[k] = h
            cols.append(((sur(F @ (A + dA.reshape(3, 3)).T / 10.0) - pred) * rw).reshape(-1) / h)
        M = np.column_stack(cols)
        lam = 1e-6 * np.trace(M.T @ M) / 9
        step = np.linalg.solve(M.T @ M + lam * np.eye(9), M.T @ r - lam * (A - np.eye(3)).reshape(-1))
        A = A + step.reshape(3, 3)
        if np.abs(step).max() < 1e-7:
            break
    r = y - sur(F @ A.T / 10.0)
    # 2. what each channel does besides: a ridge fit shrunk toward zero (the model)
    J = np.linalg.lstsq(forces_cal, y_cal, rcond=None)[0].T  # (n_meas, 3) the model's sensitivity
    prior = np.maximum(prior_rel * np.sqrt(np.mean(J**2, axis=1)), 1e-300)
    G = ((F * n[:, None]).T @ F)[None] * w[:, None, None] ** 2 + np.eye(3)[None] / prior[:, None, None] ** 2
    b = (r.T @ (F * n[:, None])) * w[:, None] ** 2  # (n_meas, 3)
    return A, np.linalg.solve(G, b[..., None])[..., 0]


def load_groups(forces: np.ndarray) -> np.ndarray:
    """(n,) group index: frames of one load (same force within :data:`SAME_LOAD_N`) share it."""
    groups = np.full(len(forces), -1)
    reps = np.empty((0, 3))
    for i, f in enumerate(np.asarray(forces, float)):
        near = np.flatnonzero(np.linalg.norm(reps - f, axis=1) <= SAME_LOAD_N)
        if len(near):
            groups[i] = near[0]
        else:
            groups[i] = len(reps)
            reps = np.vstack([reps, f])
    return groups


def errors(est: np.ndarray, true: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(angle error deg, magnitude error % of the true magnitude) per frame."""
    ang = np.degrees(angle_between(est, true))
    mag = 100 * np.abs(np.linalg.norm(est, axis=1) / np.linalg.norm(true, axis=1) - 1)
    return ang, mag


def summary(est: np.ndarray, true: np.ndarray) -> dict:
    a, m = errors(est, true)
    q = lambda v, p: round(float(np.quantile(v, p)), 3)  # noqa: E731
    return {"angle_deg_median": q(a, 0.5), "angle_deg_p90": q(a, 0.9),
            "magnitude_pct_median": q(m, 0.5), "magnitude_pct_p90": q(m, 0.9)}


def reference_path_of(calibration_path: str | Path) -> Path:
    """Where the unloaded reference of the calibration ``calibration_path`` is kept: ``<stem>.reference.csv``
    beside it (its noise beside that, force/reference/files.py noise_path)."""
    p = Path(calibration_path)
    return p.with_name(p.stem + ".reference.csv")


@dataclass(frozen=True)
class DeviceCalibration:
    """A fitted correction D for one model (module docstring); ``cv`` the cross-validated table."""

    sensor: str
    model_hash: str
    estimator: str
    force_map: np.ndarray  # A (3, 3)
    correction: np.ndarray  # D (n_meas, 3), 1/N
    prior_rel: float = PRIOR_REL
    fitted_on: dict = field(default_factory=dict)
    cv: dict = field(default_factory=dict)
    path: str = ""
    creep_per_decade: float | None = None  # the rubber's creep (force/slow_states/creep.py); None: the stream's setting
    # the device's own directions learned from the calibration's recording (force/slow_states/learned.py); None: none
    directions: Directions | None = None
    directions_note: str = ""  # how they were learned (the file's note)

    def corrected_set(self, forces: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The model's training set (``forces`` (n, 3), ``y`` (n, n_meas)) corrected to this device:
        the device reads ``y + D F'`` under ``F' = A^-1 F``."""
        f = np.linalg.solve(self.force_map, np.asarray(forces, float).T).T
        return f, y + f @ self.correction.T

    @property
    def accuracy(self) -> str:
        """One line: the cross-validated accuracy after (and before) calibration."""
        if not self.cv or not self.cv.get("after"):
            return "not cross-validated (needs 4 loads or more)"
        a, b = self.cv["after"], self.cv["before"]
        return (f"{self.cv['method']}: angle {a['angle_deg_median']:.2f}/{a['angle_deg_p90']:.2f} deg, magnitude "
                f"{a['magnitude_pct_median']:.2f}/{a['magnitude_pct_p90']:.2f} % (median/p90; uncalibrated "
                f"{b['angle_deg_median']:.2f} deg, {b['magnitude_pct_median']:.2f} %)")

    @property
    def reference_path(self) -> Path | None:
        """The device's unloaded reference of the calibration's recording, beside its file
        (``DEVICE.reference.csv``, written by ``cstomo calibrate``, the time it was recorded in its
        comment): a start without a saved tare starts from it, as from a saved tare of its age
        (:meth:`~cstomo_sensor.frame_path.stream.FrameStream.init_reference`). None when the calibration has no file."""
        return reference_path_of(self.path) if self.path else None

    def check_model(self, model) -> None:
        """Refuse a model other than the one this calibration was fitted against."""
        h = model_hash(model)
        if h != self.model_hash:
            raise ModelMismatchError(
                f"calibration {self.path or ''} was fitted against model {self.model_hash}, but the model in use is "
                f"{h} (another sensor file, mesh size or mesh): calibrate again with this model")

    def save(self, path: str | Path) -> None:
        doc = {"format": FORMAT, "sensor": self.sensor, "model_hash": self.model_hash, "estimator": self.estimator,
               "prior_rel": self.prior_rel, "fitted_on": self.fitted_on, "cross_validation": self.cv,
               **({} if self.creep_per_decade is None else {"creep_per_decade": float(self.creep_per_decade)}),
               **({CALIBRATION_KEY: directions_doc(self.directions, self.directions_note)} if self.directions else {}),
               "force_map": [[float(f"{v:.12g}") for v in row] for row in self.force_map],
               "correction_per_newton": [[float(f"{v:.9g}") for v in row] for row in self.correction]}
        text = "# cstomo_sensor device calibration: y_device(F) = y_model(force_map F) + correction F (README)\n"
        text += yaml.safe_dump(doc, sort_keys=False, default_flow_style=None, width=200)
        with atomic_write(path) as f:
            f.write(text.encode())

    @classmethod
    def load(cls, path: str | Path, n_meas: int = 208) -> DeviceCalibration:
        """Read and validate a calibration file; :class:`ConfigError` names the file and the problem."""
        where = f"calibration file {path}"
        try:
            doc = yaml.safe_load(Path(path).read_text(encoding="utf-8"))
        except OSError as err:
            raise ConfigError(f"{where}: cannot be read ({err.strerror or err})") from None
        except (yaml.YAMLError, UnicodeDecodeError) as err:
            raise ConfigError(f"{where}: not valid YAML ({str(err).splitlines()[0]}); truncated or damaged? "
                              "calibrate again") from None
        if not isinstance(doc, dict) or doc.get("format") != FORMAT:
            found = doc.get("format") if isinstance(doc, dict) else type(doc).__name__
            raise ConfigError(f"{where}: format {found!r}, expected {FORMAT!r} (a file written by cstomo calibrate)")
        missing = [k for k in ("sensor", "model_hash", "estimator", "force_map", "correction_per_newton") if k not in doc]
        if missing:
            raise ConfigError(f"{where}: lacks {missing}; truncated? calibrate again")
        tables = {}
        for key, shape in (("force_map", (3, 3)), ("correction_per_newton", (n_meas, 3))):
            try:
                t = np.array(doc[key], dtype=float)
            except (TypeError, ValueError) as err:
                raise ConfigError(f"{where}: {key} is not a table of numbers ({err}); damaged? calibrate again") from None
            if t.shape != shape or not np.isfinite(t).all():
                raise ConfigError(f"{where}: {key} of shape {t.shape} (all finite: {bool(np.isfinite(t).all())}), "
                                  f"expected {shape[0]} rows of {shape[1]} finite numbers; truncated? calibrate again")
            tables[key] = t
        A, D = tables["force_map"], tables["correction_per_newton"]
        if not 0.2 < abs(np.linalg.det(A)) ** (1 / 3) < 5:
            raise ConfigError.bad_value(f"{where}: force_map", A.round(3).tolist(), "a map near the identity "
                                        "(a device within docs/physics.md#real-devices)")
        creep = doc.get("creep_per_decade")
        why = creep_problem(creep) if creep is not None else ""
        if why:
            raise ConfigError.bad_value(f"{where}: creep_per_decade", creep, why)
        # the device's own directions (force/slow_states/learned.py): optional (a file written before them, or of a
        # device whose recording learned none, has none); a block present is checked whole
        block = doc.get(CALIBRATION_KEY)
        directions = None if block is None else directions_of_doc(block, n_meas, where)
        note = str(block.get("note", "")) if isinstance(block, dict) else ""
        return cls(str(doc["sensor"]), str(doc["model_hash"]), str(doc["estimator"]), A, D,
                   float(doc.get("prior_rel", PRIOR_REL)), doc.get("fitted_on") or {}, doc.get("cross_validation") or {},
                   str(path), None if creep is None else float(creep), directions, note)


def calibrate(pipe: Calibrated, frames: np.ndarray, forces: np.ndarray, fitted_on: dict | None = None,
              prior_rel: float = PRIOR_REL) -> DeviceCalibration:
    """Fit a :class:`DeviceCalibration` for ``pipe`` (built, uncalibrated, its reference the device's
    tare) from frames (n, n_meas) volts under known ``forces`` (n, 3) N, with a cross-validated table
    (leave one load out, or :data:`MAX_FOLDS` folds of whole loads) before and after, for the
    pipeline's estimator; a fold whose other loads cannot determine a calibration (fewer than three,
    or not spanning three directions) is not judged (``after`` None when none is)."""
    frames, forces = np.atleast_2d(np.asarray(frames, float)), np.atleast_2d(np.asarray(forces, float))
    if len(frames) != len(forces):
        raise ConfigError(f"{len(frames)} frames but {len(forces)} forces: expected one force per frame")
    if (np.linalg.norm(forces, axis=1) <= 0).any():
        raise ConfigError("a calibration load of 0 N: unloaded frames belong in the reference, not the loads")
    groups = load_groups(forces)
    n_loads = int(groups.max()) + 1
    if n_loads < 3 or np.linalg.matrix_rank(forces) < 3:
        span = {1: "all along one line", 2: "all in one plane"}.get(int(np.linalg.matrix_rank(forces)), "")
        raise ConfigError(f"{n_loads} loads{', ' + span if span and n_loads >= 2 else ''}: expected at least 3 "
                          "loads in independent directions (forces not all in one plane through the origin)")
    base = pipe.base_estimator
    y = pipe.normalise(frames)
    noise = pipe.estimator.noise

    # the fit runs on each load's mean frame and force, weighted by its count (fit_correction): one
    # row per load, not per frame (a 20 000-frame recording fits in seconds); the same fit up to the
    # spread of the reference force within a load (SAME_LOAD_N), to second order
    counts = np.bincount(groups).astype(float)
    f_mean = np.array([np.bincount(groups, forces[:, k]) for k in range(3)]).T / counts[:, None]
    y_mean = np.zeros((n_loads, y.shape[1]))
    np.add.at(y_mean, groups, y)
    y_mean /= counts[:, None]

    def fitted(idx):
        g = np.unique(groups[idx])
        A, D = fit_correction(base.forces, base.y, f_mean[g], y_mean[g], noise, prior_rel, counts[g])
        cal = DeviceCalibration("", "", "", A, D)
        return pipe.estimator.with_set(*cal.corrected_set(base.forces, base.y)), cal

    est_before = np.array([pipe.estimator.estimate(v) for v in y])
    est_after = np.full_like(est_before, np.nan)
    n_folds = n_loads if n_loads <= 20 else MAX_FOLDS
    fold = groups % n_folds if n_loads > 20 else groups
    for k in range(n_folds):
        test = fold == k
        if np.linalg.matrix_rank(forces[~test]) < 3 or len(np.unique(groups[~test])) < 3:
            continue  # the rest cannot determine a calibration: this fold is not judged
        e, _ = fitted(~test)
        est_after[test] = [e.estimate(v) for v in y[test]]
    judged = np.isfinite(est_after[:, 0])
    method = "leave one load out" if n_loads <= 20 else f"{n_folds}-fold by load"
    cv = {"method": method, "loads": n_loads, "frames": len(frames), "judged_loads": len(np.unique(groups[judged])),
          "before": summary(est_before, forces),
          "after": summary(est_after[judged], forces[judged]) if judged.any() else None}
    _, cal = fitted(np.ones(len(forces), bool))
    info = {"loads": n_loads, "frames": len(frames), "date": datetime.datetime.now().isoformat(timespec="seconds"),
            **(fitted_on or {})}
    return DeviceCalibration(pipe.geometry.name, model_hash(pipe.model), pipe.estimator_name, cal.force_map,
                             cal.correction, prior_rel, info, cv)
