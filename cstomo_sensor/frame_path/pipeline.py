"""The per-frame path: tared difference -> plausibility gate -> image -> stress field -> force.
No ROS, no serial. Per frame: one normalisation, the plausibility gate (force/checks/gate.py: a norm, one
per-channel comparison), one float32 matrix-vector product for the image (only when the field is asked
for), the estimator, into preallocated buffers. Its settings: frame_path/config.py; the state that lives
from frame to frame (tare, masks, filter, counts) is the frame stream's (frame_path/stream.py), which the
node, ``cstomo replay`` and the command line share, so they give the same numbers.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, NamedTuple

import numpy as np

from ..angles import force_angles3
from ..errors import ConfigError, FrameError
from ..force.checks.consistency import Consistency, SceneField, change_noise, mismatch_allowance, noise_expectation
from ..force.checks.gate import PlausibilityGate
from ..force.estimators.estimate import build_estimator
from ..force.reference.calibration import DeviceCalibration
from ..force.reference.files import DEFAULT_NOISE_DB, ScaleReport, check_noise
from ..frames_io import check_frame
from ..inverse.landweber import LandweberSVD
from ..inverse.reconstruction import ReconstructionModel, build_model
from ..model.geometry import SensorGeometry, load_sensor
from ..model.material import StressField
from ..settings import check_value, default
from .config import PipelineConfig

#: :attr:`Pipeline.noise_source` of the assumed noise, and of a noise measured by a tare of several frames.
NOISE_ASSUMED = f"assumed {DEFAULT_NOISE_DB:g} dB"
NOISE_MEASURED = "measured by the tare"


@dataclass(slots=True)
class FrameResult:
    """One frame's outputs. ``force`` in newtons in the wrench frame; angles in radians.

    ``valid`` is False when the plausibility gate rejected the frame (force/checks/gate.py): then
    ``reason`` says why, and force, angles and residual are NaN and there is no field.
    ``scene_field`` is the mechanics' field of the estimated force (socket sensors, with the
    field); ``consistency`` the frame's statistic against the socket load model and
    ``foreign_load`` whether it trips (force/checks/consistency.py); ``sigma`` and ``sigma_n`` the force's
    1-sigma uncertainty, set by the frame stream (force/slow_states/sigma.py; None and NaN without it).
    """

    force: np.ndarray
    magnitude: float
    elevation: float
    azimuth: float
    residual: float
    field: StressField | None
    valid: bool = True
    reason: str = ""
    scene_field: StressField | None = None
    consistency: float = float("nan")
    foreign_load: bool = False
    sigma: tuple[float, float, float] | None = None  # 1-sigma of fx, fy, fz (N): the stream's (force/slow_states/sigma.py)
    sigma_n: float = float("nan")  # the rms of the force error's norm, sqrt(trace(cov)) (N)

    @classmethod
    def implausible(cls, reason: str) -> FrameResult:
        nan = float("nan")
        return cls(np.full(3, nan), nan, nan, nan, nan, None, False, reason)


@dataclass(frozen=True)
class InUse:
    """What a pipeline makes its frames with, as one value: replaced, never changed, whenever a reference,
    a noise, a mask or a calibration changes any of it (:attr:`Pipeline.in_use`). The stages after the
    pipeline read these from a frame's :class:`FrameRecord` (the slow states: the force's 1-sigma,
    the joint fit of force and scale, force/slow_states/coordinator.py), not from the pipeline."""

    estimator: Any  # the force estimator (force/estimators/estimate.py), with the noise and the mask in use
    calibration: DeviceCalibration | None
    keep: np.ndarray  # (n_meas,) the channels used (True); not to be written
    reference_frames: int  # frames averaged into the reference
    consistency: Consistency  # the foreign-load statistic (force/checks/consistency.py)


class FrameRecord(NamedTuple):
    """One frame through the pipeline (:meth:`Pipeline.step`): its result and what the stages after it
    need of the frame (the slow states, force/slow_states/coordinator.py; the first tare's watch)."""

    result: FrameResult
    change: np.ndarray  # (n_meas,) the normalised change, zero on excluded channels: the pipeline's buffer, valid until its next frame
    plausible: bool  # the change passed the gate's change bounds (a load, or a uniform drift, can cause it; beyond max_force too)
    fit: Any  # the estimator's fit of this change (ModelFit, force/estimators/estimate.py; None: not plausible, or a linear estimator)
    in_use: InUse  # what the frame was made with


class Pipeline:
    """Reference, mask, reconstruction model and force estimator of one sensor.

    Ready when constructed; :meth:`build` loads everything from the cache (or builds it).
    ``image_dtype`` is the precision of the per-frame image product (float32, or float64 to
    measure what float32 costs). ``max_force`` (N) sets the plausibility gate (force/checks/gate.py).
    """

    def __init__(self, geometry: SensorGeometry, model: ReconstructionModel, estimator,
                 image_dtype: type = np.float32, max_force: float = default("max_force"),
                 scene_field: SceneField | None = None) -> None:
        self.geometry = geometry
        self.model = model
        self.estimator = estimator
        self.scene_field = scene_field
        self._allowance = mismatch_allowance(model)
        # frames averaged into the reference (set_reference); True: the estimators use the tare's noise (of those frames)
        self.reference_frames, self.noise_measured = 1, False
        self.n_meas = model.n_meas
        self.centers = (model.centers - geometry.socket_center).astype(np.float32)  # wrench frame
        self.reference: np.ndarray | None = None
        self._svd: LandweberSVD | None = None
        self._dtype = np.dtype(image_dtype)
        self._R = model.R.astype(self._dtype, copy=False)
        self._fit = model.fit.astype(self._dtype, copy=False)  # y -> the part the image explains
        self._keep = np.ones(self.n_meas, dtype=bool)
        self._dropped: np.ndarray | None = None  # indices of the excluded channels (None: none)
        self.calibration: DeviceCalibration | None = None
        self._update_consistency()  # and in_use
        self._y = np.empty(self.n_meas, dtype=np.float64)  # the latest frame's change (FrameRecord.change)
        self._y32 = np.empty(self.n_meas, dtype=self._dtype)
        self._x = np.empty(model.n_cells, dtype=self._dtype)
        check_value("max_force", max_force)
        self.max_force = float(max_force)
        self.gate = PlausibilityGate(estimator.forces, estimator.y, model, self.max_force)
        self._y_scale = model.v_scale  # c * v_scale, c the device's global factor (set_reference)
        self._default_noise = np.asarray(estimator.noise)  # y units, DEFAULT_NOISE_DB
        self.scale_report: ScaleReport | None = None
        self._base_set = (np.asarray(estimator.forces), np.asarray(estimator.y))  # the model's own
        self.noise_source = NOISE_ASSUMED  # what noise the estimators use, in words (set_reference, set_noise)

    @classmethod
    def build(cls, config: PipelineConfig, progress=None) -> Pipeline:
        geometry = load_sensor(config.sensor)
        model = build_model(geometry, config.recon_spec, config.cache_dir or None, progress)
        calibration = DeviceCalibration.load(config.calibration_file, model.n_meas) if config.calibration_file else None
        estimator = build_estimator(config.estimator, geometry, model, config.cache_dir or None, progress)
        scene_field = SceneField.build(geometry, model, cache_dir=config.cache_dir or None)
        pipe = cls(geometry, model, estimator, max_force=config.max_force, scene_field=scene_field)
        pipe._svd = model.svd()  # now (0.1 s), not at the first masked channel in the frame path
        if calibration is not None:
            pipe.set_calibration(calibration)
        return pipe

    def set_calibration(self, calibration: DeviceCalibration | None) -> None:
        """Use a device calibration (None: the nominal model): the estimator is rebuilt on the model's
        training set corrected to the device. Refuses one fitted against another model."""
        forces, y = self._base_set
        if calibration is None:
            self.estimator = self.estimator.with_set(forces, y)
        else:
            calibration.check_model(self.model)
            self.estimator = self.estimator.with_set(*calibration.corrected_set(forces, y))
        self.calibration = calibration
        self._update_consistency()

    @property
    def base_estimator(self):
        """The estimator without the device calibration (same noise and mask)."""
        return self.estimator if self.calibration is None else self.estimator.with_set(*self._base_set)

    @property
    def estimator_name(self) -> str:
        return self.estimator.name

    def normalise(self, frames: np.ndarray, scale: float = 1.0, offset: np.ndarray | None = None) -> np.ndarray:
        """``(V / s - V_ref) / (c v_scale) - offset`` of (n_meas,) or (n, n_meas) frames, as :meth:`process`
        forms it (``scale`` and ``offset``: the device's slow change since the tare, force/slow_states/coordinator.py)."""
        if self.reference is None:
            raise FrameError("no reference: tare the sensor (set_reference) before processing frames")
        y = (check_frame(frames, self.n_meas, "frame", batch=True) / scale - self.reference) / self._y_scale
        return y if offset is None else y - offset

    @property
    def y_scale(self) -> float:
        """``c * v_scale``: what a change is divided by (:meth:`set_reference`)."""
        return self._y_scale

    @property
    def model_reference(self) -> np.ndarray:
        return self.model.model_reference

    @property
    def bad_channels(self) -> np.ndarray:
        return ~self._keep

    def set_reference(self, frame: np.ndarray, noise: np.ndarray | None = None, n_frames: int = 1) -> ScaleReport:
        """Use the device's own unloaded frame (tare) as the difference reference; returns how it
        compares with the model (:class:`~cstomo_sensor.force.reference.files.ScaleReport`).

        The change is normalised by ``c * v_scale``, ``c`` the reference's global factor against the
        model's, so a device whose voltages are all scaled alike gives the same forces. ``noise``
        (n_meas,) volts, the per-channel std of one frame (of the tare frames), sets the estimators'
        noise; None assumes :data:`~cstomo_sensor.force.reference.files.DEFAULT_NOISE_DB` relative to the reference.
        ``n_frames`` (>= 1) is how many frames were averaged into ``frame``: the reference carries
        noise of std ``noise / sqrt(n_frames)`` on every change, so the consistency statistic whitens
        by ``noise * sqrt(1 + 1 / n_frames)`` (force/checks/consistency.py); the estimators keep ``noise``.
        """
        if isinstance(n_frames, bool) or not isinstance(n_frames, (int, np.integer)) or n_frames < 1:
            raise ConfigError.bad_value("n_frames", n_frames, "the count of frames averaged into the reference (>= 1)")
        ref = check_frame(frame, self.n_meas, "reference").copy()
        report = ScaleReport.of(ref, self.model_reference)
        c = report.factor if np.isfinite(report.factor) and report.factor > 0 else 1.0
        y_scale = c * self.model.v_scale
        noise_y = self._default_noise if noise is None else self._noise_y(noise, y_scale)
        estimator = self.estimator.with_noise(noise_y)
        self.reference, self._y_scale, self.estimator = ref, y_scale, estimator
        self.scale_report, self.noise_measured = report, noise is not None
        self.noise_source = NOISE_MEASURED if noise is not None else NOISE_ASSUMED
        self.reference_frames = int(n_frames)
        self._update_gate()
        self._update_consistency()
        return report

    def drop_reference(self) -> None:
        """No reference in use any more (a first tare that carried a load, force/reference/first_tare.py): no frame
        is processed until :meth:`set_reference` sets the next; the noise, the mask and the calibration stay."""
        self.reference = None

    def _noise_y(self, noise: np.ndarray, y_scale: float) -> np.ndarray:
        """Per-channel noise (n_meas,) volts in y units, floored at a tenth of the median channel's (a
        channel that happened to read steady)."""
        noise_v = check_frame(noise, self.n_meas, "noise")
        floor = 0.1 * float(np.median(noise_v))
        return np.maximum(noise_v, floor if floor > 0 else 1e-300) / y_scale

    def set_noise(self, noise: np.ndarray, source: str) -> None:
        """Use ``noise`` (n_meas,) volts, the per-channel std of one frame, for the reference in use
        (its frames, scale and drift stay): the estimators and the consistency statistic are rebuilt
        on it (milliseconds). ``source`` says where it comes from (:attr:`noise_source`), e.g. an
        estimate from the frames (force/reference/noise_estimate.py); :attr:`noise_measured` stays False."""
        if self.reference is None:
            raise FrameError("no reference: set_reference before set_noise")
        noise_y = self._noise_y(check_noise(noise, self.reference), self._y_scale)
        self.estimator = self.estimator.with_noise(noise_y)
        self.noise_measured, self.noise_source = False, str(source)
        self._update_consistency()

    def after_noise(self, record: FrameRecord) -> FrameRecord:
        """The record of this pipeline's latest frame as the stages after it see it once :meth:`set_noise` has
        changed the noise since it was made: with what the pipeline makes frames with now (:attr:`in_use`: the
        estimator of the new noise, its consistency) and no fit (that estimator has fitted no frame; the old
        one's fit whitens the change by the old noise). Its result and change stay."""
        return record._replace(fit=None, in_use=self.in_use)

    def _update_consistency(self) -> None:
        """The foreign-load statistic on the estimator's training set and noise (both follow the
        device: measured noise at a tare, corrected set with a calibration) and the current mask. Its
        noise is the change's: the frame's plus the reference's (the mean of ``reference_frames``: if measured, of their spread)."""
        noise, measured = change_noise(self.estimator.noise, self.reference_frames), self.reference_frames if self.noise_measured else None
        self.consistency = Consistency(np.asarray(self.estimator.y), noise, self._allowance, self._keep, noise_expectation(measured))
        self._update_in_use()

    def _update_in_use(self) -> None:
        """:attr:`in_use` anew (after anything of it changed)."""
        self.in_use = InUse(self.estimator, self.calibration, self._keep, self.reference_frames, self.consistency)

    def _update_gate(self) -> None:
        ref = self.reference if self.reference is not None else self.model_reference
        self.gate.follow(ref, self._y_scale, self._keep)

    def set_bad_channels(self, bad: np.ndarray) -> None:
        """Exclude measurements (saturated channel, dead electrode): R and the estimator get the mask.

        Re-SVDs the 208 x n_basis sensitivity (tens of milliseconds); the forward model is not rebuilt.
        """
        keep = ~np.asarray(bad, dtype=bool)
        if keep.shape != (self.n_meas,):
            raise ConfigError(f"bad channel mask of shape {keep.shape}, expected ({self.n_meas},)")
        if np.array_equal(keep, self._keep):
            return
        # everything is computed before anything is assigned: a refused mask changes nothing
        if keep.all():
            R, fit = (a.astype(self._dtype, copy=False) for a in (self.model.R, self.model.fit))
        else:
            if self._svd is None:
                self._svd = self.model.svd()
            lam = self.model.damping * self._svd.s_max**2
            R, fit = self.model.matrices(self._svd.masked(keep), self.model.iterations, self.model.step, lam,
                                         dtype=self._dtype)
        estimator = self.estimator.masked(keep)
        consistency = self.consistency.masked(keep)
        self._keep, self._R, self._fit, self.estimator, self.consistency = keep, R, fit, estimator, consistency
        self._dropped = None if keep.all() else np.flatnonzero(~keep)
        self._update_gate()
        self._update_in_use()

    def process(self, frame: np.ndarray, with_field: bool = True, gate: bool = True, scale: float = 1.0,
                offset: np.ndarray | None = None, gradient=None) -> FrameResult:
        """The :class:`FrameResult` of :meth:`step` (a study of the pipeline alone: the frame stream takes the record)."""
        return self.step(frame, with_field, gate, scale, offset, gradient).result

    def step(self, frame: np.ndarray, with_field: bool = True, gate: bool = True, scale: float = 1.0,
             offset: np.ndarray | None = None, gradient=None) -> FrameRecord:
        """The :class:`FrameRecord` of one frame of (n_meas,) volts: its force (and field), its change,
        whether the change is plausible and the estimator's fit. ``scale`` and ``offset``:
        the device's slow change since the tare (the uniform scale of the voltages and the change along
        other directions in y units: the frame stream's, force/slow_states/coordinator.py; 1 and None: none); ``gradient``:
        the states of its resistivity gradients (3 floats, force/estimators/scale_fit.py; None: none), which the ``model``
        estimator's response follows (force/estimators/estimate.py, force/estimators/training.py).

        ``gate=False`` skips the plausibility gate (studies of what the estimator does with any
        input, e.g. the benchmark's stability table); the node, replay and the command line keep it.
        Raises :class:`FrameError` for a frame of the wrong length or with NaN/Inf in a used channel.
        """
        if self.reference is None:
            raise FrameError("no reference: tare the sensor (set_reference) before processing frames")
        y = self._y
        with np.errstate(over="ignore", invalid="ignore"):  # huge finite values: the gate rejects them
            v = frame  # a finite float64 frame as is (one product; np.isfinite takes 2 us more), else checked
            if not (type(v) is np.ndarray and v.dtype == np.float64 and v.shape == y.shape and math.isfinite(v.dot(v))):
                v = check_frame(frame, self.n_meas, used=self._keep)
            np.multiply(v, 1.0 / scale, out=y)  # the device's slow change (force/slow_states/drift.py)
            y -= self.reference
            y /= self._y_scale
            if offset is not None:
                y -= offset
            if self._dropped is not None:
                y[self._dropped] = 0.0
            why = self.gate.change_quiet(y) if gate else ""
        if why:  # no change a load (or a uniform drift) can cause
            return FrameRecord(FrameResult.implausible(why), y, False, None, self.in_use)
        est = self.estimator
        force = est.estimate(y, gradient)
        fit = getattr(est, "last_fit", None)
        mag, el, az = force_angles3(force)
        why = self.gate.force(mag) if gate else ""
        if why:
            return FrameRecord(FrameResult.implausible(why), y, True, fit, self.in_use)
        c = self.consistency(y)
        field = scene = None
        residual = math.nan
        if with_field and self.scene_field is not None:
            scene = self.scene_field.field(force)
        if with_field:
            self._y32[:] = y
            np.matmul(self._R, self._y32, out=self._x)
            dsigma = self._x.astype(np.float64) * self.model.sigma0
            field = StressField.from_conductivity_change(dsigma, self.geometry.material)
            r = (y - self._fit @ self._y32) * self._keep
            residual = float(np.linalg.norm(r) / max(np.linalg.norm(y), 1e-300))
        result = FrameResult(force, mag, el, az, residual, field, scene_field=scene, consistency=c,
                             foreign_load=c > self.consistency.threshold)
        return FrameRecord(result, y, True, fit, self.in_use)
