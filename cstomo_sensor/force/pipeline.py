"""The per-frame path: tared difference -> plausibility gate -> image -> stress field -> force.
No ROS, no serial.

Everything the node does with a frame is here, so the node, ``cstomo replay`` and the command line
give the same numbers. Per frame: one normalisation, the plausibility gate (a norm, one per-channel
comparison), one float32 matrix-vector product for the image (only when the field is asked for),
the estimator, into preallocated buffers.

Plausibility gate
-----------------
A frame whose change from the reference lies far outside what any load in the sensor's rated range
can cause is not a force (all-zero or scaled frames from a failing board, huge values, a bit-flipped
text line). Its :class:`FrameResult` has ``valid=False``, a short ``reason`` and NaN force, angles
and field. The gate works on the change relative to the device's *own* reference,
``g = (V - V_ref) / max(|V_ref|, 0.05 rms(V_ref))`` per used channel, so a device whose rubber is
0.2..5 times as resistive as the model (REFERENCE_SENSOR.md section 8) is judged alike. A frame is
rejected when any of these holds:

1. ``||g|| > DEVICE_MARGIN * k * max_force + NOISE_NORM_FACTOR * ||n40||``: ``k`` is the largest
   ``||y|| / |F|`` of the estimator's calibration set (simulated socket loads 5..40 N; nearly
   linear in |F|), ``||n40||`` the norm of the per-channel noise of a 40 dB board (section 5, the
   poorest board of section 8), doubled to cover a single-frame reference.
2. any channel's ``|g_i| > DEVICE_MARGIN * e_i * max_force + CHANNEL_NOISE_SIGMAS * n40_i``: ``e_i``
   is channel i's largest ``|y_i| / |F|`` over the calibration set.
3. the estimated force exceeds ``max_force`` (default 1.5 x the rated 40 N).

``DEVICE_MARGIN`` = 3.5 covers a device at the ends of section 8 (E 0.7 MPa: 1.43 x the strain;
d ln(rho) / d theta -19 instead of -12: 1.58 x; nu 0.43: more compressible) loaded to ``max_force``.
Figures for the cuboid_joint (h = 4 mm model): k = 0.0209 /N, ||n40|| = 0.76, so the bound on
``||g||`` is 5.9 at max_force = 60 N; honest simulation (independent mesh, mismatched electrodes)
of 40 N at any direction at 40 dB with a single-frame reference gives ``||g||`` <= 1.6 and every
channel under 0.84 of its bound *before* the margin; an all-zero frame gives ||g|| = 14.4, a frame
scaled by 10 gives 130.
"""
from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from ..angles import force_angles3
from ..errors import ConfigError, FrameError, NoUsableChannelsError
from ..frames_io import check_frame
from ..inverse.landweber import LandweberSVD
from ..inverse.reconstruction import ReconSpec, ReconstructionModel, build_model
from ..model.geometry import SensorGeometry, load_sensor
from ..model.material import StressField
from ..model.pattern import MeasurementPattern
from .calibration import DeviceCalibration
from .device import ScaleReport
from .estimate import ESTIMATORS, CalibrationSpec, build_estimator
from .scene_field import Consistency, SceneField, change_noise, mismatch_allowance

log = logging.getLogger(__name__)

#: The rated force range of the socket (REFERENCE_SENSOR.md section 4): the calibration's largest load.
RATED_FORCE = max(CalibrationSpec.magnitudes)  # N
#: Plausibility gate (module docstring): device spread of section 8, the poorest board's SNR,
#: the noise allowances of the norm and of one channel.
DEVICE_MARGIN = 3.5
GATE_SNR_DB = 40.0
NOISE_NORM_FACTOR = 2.0
CHANNEL_NOISE_SIGMAS = 6.0 * np.sqrt(2.0)  # 6 sigma of the difference of two noisy frames

@dataclass(frozen=True)
class PipelineConfig:
    """Every setting of the per-frame path: the one source of their defaults and choices (the
    node's parameters, the parameter file and the command line take theirs from here)."""

    sensor: str = "cuboid_joint"
    cache_dir: str = ""  # '' = default_cache_dir()
    estimator: str = ESTIMATORS[0]
    mesh_size: float = ReconSpec.mesh_size  # m
    grid: tuple[int, int, int] = ReconSpec.grid
    iterations: int = 0  # 0 = chosen by the discrepancy rule
    damping: float = ReconSpec.damping
    max_force: float = 1.5 * RATED_FORCE  # N; larger estimates (and frames no such load explains) are implausible
    calibration_file: str = ""  # a device calibration (cstomo calibrate); '' = the nominal model

    def __post_init__(self) -> None:
        if self.estimator not in ESTIMATORS:
            raise ConfigError.bad_value("estimator", self.estimator, f"one of {list(ESTIMATORS)}")
        if not self.max_force > 0:
            raise ConfigError.bad_value("max_force", self.max_force, "a force > 0 in newtons")
        if self.iterations < 0:
            raise ConfigError.bad_value("iterations", self.iterations, "0 (automatic) or a positive count")
        object.__setattr__(self, "grid", self.recon_spec.grid)  # validates mesh_size, grid, damping

    @property
    def recon_spec(self) -> ReconSpec:
        return ReconSpec(mesh_size=self.mesh_size, grid=tuple(self.grid),
                         iterations=self.iterations or None, damping=self.damping)


@dataclass
class FrameResult:
    """One frame's outputs. ``force`` in newtons in the wrench frame; angles in radians.

    ``valid`` is False when the plausibility gate rejected the frame (module docstring): then
    ``reason`` says why, and force, angles and residual are NaN and there is no field.
    ``scene_field`` is the mechanics' field of the estimated force (socket sensors, with the
    field); ``consistency`` the frame's statistic against the socket load model and
    ``foreign_load`` whether it trips (force/scene_field.py).
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

    @classmethod
    def implausible(cls, reason: str) -> FrameResult:
        nan = float("nan")
        return cls(np.full(3, nan), nan, nan, nan, nan, None, False, reason)


class Pipeline:
    """Reference, mask, reconstruction model and force estimator of one sensor.

    Ready when constructed; :meth:`build` loads everything from the cache (or builds it).
    ``image_dtype`` is the precision of the per-frame image product (float32, or float64 to
    measure what float32 costs). ``max_force`` (N) sets the plausibility gate (module docstring).
    """

    def __init__(self, geometry: SensorGeometry, model: ReconstructionModel, estimator,
                 image_dtype: type = np.float32, max_force: float = PipelineConfig.max_force,
                 scene_field: SceneField | None = None) -> None:
        self.geometry = geometry
        self.model = model
        self.estimator = estimator
        self.scene_field = scene_field
        self._allowance = mismatch_allowance(model)
        self.reference_frames = 1  # frames averaged into the reference (set_reference)
        self.n_meas = model.n_meas
        self.centers = (model.centers - geometry.socket_center).astype(np.float32)  # wrench frame
        self.reference: np.ndarray | None = None
        self._svd: LandweberSVD | None = None
        self._dtype = np.dtype(image_dtype)
        self._R = model.R.astype(self._dtype, copy=False)
        self._fit = model.fit.astype(self._dtype, copy=False)  # y -> the part the image explains
        self._keep = np.ones(self.n_meas, dtype=bool)
        self._update_consistency()
        self._y = np.empty(self.n_meas, dtype=np.float64)
        self._y32 = np.empty(self.n_meas, dtype=self._dtype)
        self._x = np.empty(model.n_cells, dtype=self._dtype)
        # plausibility gate: calibration envelopes (per newton) and the 40 dB noise, in y units
        if not max_force > 0:
            raise ConfigError.bad_value("max_force", max_force, "a force > 0 in newtons")
        self.max_force = float(max_force)
        F, Y = np.asarray(estimator.forces), np.asarray(estimator.y)
        mag = np.linalg.norm(F, axis=1)
        loaded = mag > 0
        per_n = np.abs(Y[loaded]) / mag[loaded, None]
        self.gate_k = float(np.max(np.linalg.norm(Y[loaded], axis=1) / mag[loaded]))  # ||y|| per N
        ref = model.model_reference
        noise = np.sqrt(np.mean(ref**2)) * 10 ** (-GATE_SNR_DB / 20) / model.v_scale
        self.gate_norm_bound = DEVICE_MARGIN * self.gate_k * self.max_force + NOISE_NORM_FACTOR * float(np.linalg.norm(noise))
        self.gate_channel_bound = DEVICE_MARGIN * per_n.max(axis=0) * self.max_force + CHANNEL_NOISE_SIGMAS * noise
        self._gate_w = np.ones(self.n_meas)  # y -> g: keep * y_scale / (device's reference scale)
        self._y_scale = model.v_scale  # c * v_scale, c the device's global factor (set_reference)
        self._default_noise = np.asarray(estimator.noise)  # y units, DEFAULT_NOISE_DB
        self.scale_report: ScaleReport | None = None
        self.calibration: DeviceCalibration | None = None
        self._base_set = (np.asarray(estimator.forces), np.asarray(estimator.y))  # the model's own
        self.noise_measured = False  # True: the estimators use the tare's noise
        self._g = np.empty(self.n_meas)
        self._over = np.empty(self.n_meas, dtype=bool)

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

    def normalise(self, frames: np.ndarray) -> np.ndarray:
        """``(V - V_ref) / (c v_scale)`` of (n_meas,) or (n, n_meas) frames, as :meth:`process` forms it."""
        if self.reference is None:
            raise FrameError("no reference: tare the sensor (set_reference) before processing frames")
        return (check_frame(frames, self.n_meas, "frame", batch=True) - self.reference) / self._y_scale

    @property
    def model_reference(self) -> np.ndarray:
        return self.model.model_reference

    @property
    def bad_channels(self) -> np.ndarray:
        return ~self._keep

    def set_reference(self, frame: np.ndarray, noise: np.ndarray | None = None, n_frames: int = 1) -> ScaleReport:
        """Use the device's own unloaded frame (tare) as the difference reference; returns how it
        compares with the model (:class:`~.device.ScaleReport`).

        The change is normalised by ``c * v_scale``, ``c`` the reference's global factor against the
        model's, so a device whose voltages are all scaled alike gives the same forces. ``noise``
        (n_meas,) volts, the per-channel std of one frame (of the tare frames), sets the estimators'
        noise; None assumes :data:`~.device.DEFAULT_NOISE_DB` relative to the reference.
        ``n_frames`` (>= 1) is how many frames were averaged into ``frame``: the reference carries
        noise of std ``noise / sqrt(n_frames)`` on every change, so the consistency statistic whitens
        by ``noise * sqrt(1 + 1 / n_frames)`` (force/scene_field.py); the estimators keep ``noise``.
        """
        if isinstance(n_frames, bool) or not isinstance(n_frames, (int, np.integer)) or n_frames < 1:
            raise ConfigError.bad_value("n_frames", n_frames, "the count of frames averaged into the reference (>= 1)")
        ref = check_frame(frame, self.n_meas, "reference").copy()
        report = ScaleReport.of(ref, self.model_reference)
        c = report.factor if np.isfinite(report.factor) and report.factor > 0 else 1.0
        y_scale = c * self.model.v_scale
        if noise is None:
            noise_y = self._default_noise
        else:
            noise_v = check_frame(noise, self.n_meas, "noise")
            floor = 0.1 * float(np.median(noise_v))  # a channel that happened to read steady
            noise_y = np.maximum(noise_v, floor if floor > 0 else 1e-300) / y_scale
        estimator = self.estimator.with_noise(noise_y)
        self.reference, self._y_scale, self.estimator = ref, y_scale, estimator
        self.scale_report, self.noise_measured = report, noise is not None
        self.reference_frames = int(n_frames)
        self._update_gate()
        self._update_consistency()
        return report

    def _update_consistency(self) -> None:
        """The foreign-load statistic on the estimator's training set and noise (both follow the
        device: measured noise at a tare, corrected set with a calibration) and the current mask. Its
        noise is the change's: the frame's plus the reference's (the mean of ``reference_frames``)."""
        noise = change_noise(self.estimator.noise, self.reference_frames)
        self.consistency = Consistency(np.asarray(self.estimator.y), noise, self._allowance, self._keep)

    def _update_gate(self) -> None:
        """The gate's per-channel weight: the change relative to the device's own reference."""
        ref = self.reference if self.reference is not None else self.model_reference
        scale = np.maximum(np.abs(ref), 0.05 * np.sqrt(np.mean(ref**2)))
        with np.errstate(divide="ignore"):
            w = np.where(scale > 0, self._y_scale / scale, np.inf)  # an all-zero reference: nothing passes
        self._gate_w = np.where(self._keep, w, 0.0)

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
        self._update_gate()

    def process(self, frame: np.ndarray, with_field: bool = True, gate: bool = True) -> FrameResult:
        """Estimate the force (and the field) from one frame of (n_meas,) volts.

        ``gate=False`` skips the plausibility gate (studies of what the estimator does with any
        input, e.g. the benchmark's stability table); the node, replay and the command line keep it.

        Raises :class:`FrameError` for a frame of the wrong length or with NaN/Inf in a used channel.
        """
        if self.reference is None:
            raise FrameError("no reference: tare the sensor (set_reference) before processing frames")
        v = check_frame(frame, self.n_meas, used=self._keep)
        y = self._y
        with np.errstate(over="ignore", invalid="ignore"):  # huge finite values: the gate rejects them
            np.subtract(v, self.reference, out=y)
            y /= self._y_scale
            y[~self._keep] = 0.0
            g = np.multiply(y, self._gate_w, out=self._g)
            g2 = float(np.dot(g, g)) if gate else 0.0
            if not g2 <= self.gate_norm_bound**2:  # NaN/inf too
                return FrameResult.implausible(
                    f"relative change of norm {np.sqrt(g2):.3g}, beyond {self.gate_norm_bound:.3g} (the largest a "
                    f"load up to max_force {self.max_force:g} N can cause)")
            np.abs(g, out=g)
            if gate and np.greater(g, self.gate_channel_bound, out=self._over).any():
                i = int(np.argmax(g / self.gate_channel_bound))
                return FrameResult.implausible(
                    f"channel {i} changed by {g[i]:.3g} of its reference, beyond {self.gate_channel_bound[i]:.3g}")
        force = self.estimator.estimate(y)
        mag, el, az = force_angles3(force)
        if gate and not mag <= self.max_force:
            return FrameResult.implausible(f"force {mag:.4g} N beyond max_force {self.max_force:g} N")
        c = self.consistency(y)
        field = scene = None
        residual = float("nan")
        if with_field and self.scene_field is not None:
            scene = self.scene_field.field(force)
        if with_field:
            self._y32[:] = y
            np.matmul(self._R, self._y32, out=self._x)
            dsigma = self._x.astype(np.float64) * self.model.sigma0
            field = StressField.from_conductivity_change(dsigma, self.geometry.material)
            r = (y - self._fit @ self._y32) * self._keep
            residual = float(np.linalg.norm(r) / max(np.linalg.norm(y), 1e-300))
        return FrameResult(force, mag, el, az, residual, field, scene_field=scene, consistency=c,
                           foreign_load=c > self.consistency.threshold)


@dataclass(frozen=True)
class Excluded:
    """Channels excluded from the reconstruction by the latest frame's status flags."""

    saturated: int = 0
    dead_electrodes: tuple[int, ...] = ()
    channels: int = 0


#: Largest tare spread accepted: max over the used channels of std / rms(reference) of the tare
#: frames. 60 dB noise (std 0.1 % of rms) gives 0.15..0.35 % over 208 channels (2..50 frames); a
#: 20 N socket load moves a channel by up to 5.7 % of rms, so one arriving in the middle 80 % of
#: a tare gives 1.7 % or more.
TARE_MAX_SPREAD = 0.01
#: On a noisy board the limit is this many times the median channel's spread instead, when larger: a
#: 40 dB board (REFERENCE_SENSOR.md s.8) has a std of 1 % of rms on every channel, and a load arriving
#: during the tare still shows as channels far noisier than the typical one (use >= 10 tare frames there).
TARE_NOISE_FACTOR = 3.0


@dataclass(frozen=True)
class TareOutcome:
    """How a tare ended: ``reference`` (208,) if accepted, else None and ``reason`` says why.

    ``spread`` is the steadiness figure of :data:`TARE_MAX_SPREAD` (0.0 for a one-frame tare);
    ``noise`` (208,) volts the per-channel std of the frames (None for a one-frame tare).
    """

    reference: np.ndarray | None
    frames: int
    spread: float
    reason: str = ""
    noise: np.ndarray | None = None

    @property
    def ok(self) -> bool:
        return self.reference is not None


class FrameProcessor:
    """Tare, bad-channel mask and per-frame processing around a Pipeline (node and replay share it).

    Tare semantics (the same everywhere): when a tare is pending (``tare_on_start`` in the node, or
    no ``--reference`` given to replay), the next ``tare_frames`` usable frames of the input are
    averaged into the reference and give no output; every later frame is processed against that
    reference. A tare is refused (the old reference stays) when its frames are not steady: the
    largest per-channel standard deviation over the channels not excluded during the tare, relative
    to the rms of the averaged reference, is above ``tare_max_spread`` (or :data:`TARE_NOISE_FACTOR` x
    the median channel's, when larger: a noisy board); or when the average is not
    finite. Without any reference a tare is always pending: a refused or cancelled one starts over.

    Parameters
    ----------
    pipe : Pipeline
        The per-frame core (its reference is set here by a tare or by the caller).
    stress_field_every : int
        Attach the stress field to every N-th processed frame (the first one included); 0 never.
    on_tare : callable or None
        Called with the :class:`TareOutcome` when a tare ends, accepted or refused (e.g. to save it).
    tare_max_spread : float
        The steadiness limit of a tare (see :data:`TARE_MAX_SPREAD`).
    """

    def __init__(self, pipe: Pipeline, stress_field_every: int = 0,
                 on_tare: Callable[[TareOutcome], None] | None = None,
                 tare_max_spread: float = TARE_MAX_SPREAD) -> None:
        if stress_field_every < 0:
            raise ConfigError(f"{stress_field_every=}: expected >= 0 (0 = off)")
        if not tare_max_spread > 0:
            raise ConfigError(f"{tare_max_spread=}: expected > 0 (a fraction of the reference rms)")
        self.pipe = pipe
        self.stress_field_every = int(stress_field_every)
        self.on_tare = on_tare
        self.tare_max_spread = float(tare_max_spread)
        n_el = len(pipe.geometry.electrodes)
        pattern = MeasurementPattern(n_el, pipe.geometry.layers)
        self._electrode_rows = np.stack([pattern.electrode_rows(e) for e in range(n_el)])
        self._mask = pipe.bad_channels.copy()  # always the pipeline's own mask
        self._all_good = np.ones(n_el, bool)
        self.excluded = Excluded(channels=int(self._mask.sum()))
        self.processed = 0
        self._tare_x0 = np.zeros(pipe.n_meas)   # first tare frame (sums are taken around it)
        self._tare_s1 = np.zeros(pipe.n_meas)
        self._tare_s2 = np.zeros(pipe.n_meas)
        self._tare_d = np.zeros(pipe.n_meas)
        self._tare_mask = np.zeros(pipe.n_meas, bool)  # channels excluded by any tare frame
        self.implausible = 0  # frames the plausibility gate rejected (all time)
        self.implausible_reason = ""  # the latest one's reason
        self._implausible_run = 0  # consecutive rejected frames (logged at the start and the end)
        self._tare_left = self._tare_n = 0

    # --- tare ------------------------------------------------------------------------------------

    def start_tare(self, n_frames: int) -> None:
        """Average the next ``n_frames`` frames into the reference (they give no output)."""
        if n_frames < 1:
            raise ConfigError(f"tare_frames={n_frames!r}: expected >= 1")
        self._tare_left = self._tare_n = int(n_frames)

    def cancel_tare(self) -> int:
        """Drop a pending tare (the reference stays as it is); returns the frames it had taken.

        Without any reference the tare stays pending (see the class docstring)."""
        taken = self._tare_n - self._tare_left if self._tare_left else 0
        if self.pipe.reference is not None:
            self._tare_left = 0
        else:
            self._tare_left = self._tare_n
        return taken

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
            self._tare_mask[:] = mask
        self._tare_mask |= mask
        np.subtract(v, self._tare_x0, out=self._tare_d)
        self._tare_s1 += self._tare_d
        self._tare_s2 += self._tare_d**2
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
        limit = self.tare_max_spread
        if noise is not None:
            limit = max(limit, TARE_NOISE_FACTOR * float(np.median(noise[used])) / rms)
        if spread > limit:
            worst = int(np.argmax(np.where(used, var, -1.0))) + 1
            return TareOutcome(None, n, spread, f"tare refused: frames not steady (spread {spread:.2%} of the "
                                                f"reference rms at measurement {worst}, limit "
                                                f"{limit:.2%}); keep the sensor still and unloaded "
                                                "during the tare")
        return TareOutcome(ref.copy(), n, spread, noise=noise)

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

    def update_mask(self, saturated: np.ndarray | None, contact_ok: np.ndarray | None) -> bool:
        """Exclude saturated values and every row of a dead electrode; True if the mask changed
        (only then is ``pipe.set_bad_channels`` called).

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
        self.excluded = Excluded(
            saturated=n_sat,
            dead_electrodes=tuple(int(e) for e in np.flatnonzero(dead)),
            channels=int(mask.sum()),
        )
        if mask.any():
            log.warning("excluding %d measurements (saturated: %d, dead electrodes: %s)",
                        self.excluded.channels, self.excluded.saturated, self.excluded.dead_electrodes)
        return True

    def process(self, values: np.ndarray, saturated: np.ndarray | None = None,
                contact_ok: np.ndarray | None = None) -> FrameResult | None:
        """The FrameResult of one frame, or None while the frame goes into a pending tare (or no
        reference exists yet). Raises :class:`FrameError` for a frame that must be dropped (it then
        counts for nothing, not even for a pending tare). A result the plausibility gate rejected
        (``valid`` False) is counted in ``implausible``; a run of them is logged once when it starts
        and once when it ends."""
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
        every = self.stress_field_every
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
        return result

    def _end_tare(self, outcome: TareOutcome) -> None:
        if outcome.ok:
            report = self.pipe.set_reference(outcome.reference, outcome.noise, outcome.frames)
            log.info("tare: new reference from %d frames (spread %.2f%% of its rms; noise %s)", outcome.frames,
                     100 * outcome.spread, "measured" if outcome.noise is not None else "assumed 60 dB")
            (log.warning if report.warn else log.info)("tare: %s", report.message)
        elif self.pipe.reference is None:
            log.warning("%s; no reference yet: taring again on the next %d frames", outcome.reason, outcome.frames)
            self.start_tare(outcome.frames)
        else:
            log.warning("%s; the previous reference stays", outcome.reason)
        if self.on_tare is not None:
            self.on_tare(outcome)
