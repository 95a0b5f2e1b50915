"""The per-frame path: tared difference -> image -> stress field -> force. No ROS, no serial.

Everything the node does with a frame is here, so the node, ``cstomo replay`` and the command line
give the same numbers. Per frame: one normalisation, one float32 matrix-vector product for the
image (only when the field is asked for), the estimator, into preallocated buffers.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from .angles import force_angles
from .errors import ConfigError, FrameError
from .geometry import SensorGeometry, load_sensor
from .landweber import LandweberSVD
from .material import StressField
from .reconstruction import ReconSpec, ReconstructionModel, build_model

log = logging.getLogger(__name__)

ESTIMATORS = ("linear", "model")


@dataclass(frozen=True)
class PipelineConfig:
    """Every setting of the per-frame path (the node's parameters map onto these)."""

    sensor: str = "cuboid_joint"
    cache_dir: str = ""
    estimator: str = "linear"
    mesh_size: float = 4.0e-3
    grid: tuple[int, int, int] = (8, 8, 4)
    iterations: int = 0  # 0 = chosen by the discrepancy rule
    damping: float = 0.0

    def __post_init__(self) -> None:
        if self.estimator not in ESTIMATORS:
            raise ConfigError(f"estimator={self.estimator!r}: expected one of {list(ESTIMATORS)}")
        if self.iterations < 0:
            raise ConfigError(f"iterations={self.iterations!r}: expected 0 (automatic) or a positive count")
        self.recon_spec  # validates mesh_size, grid, damping

    @property
    def recon_spec(self) -> ReconSpec:
        return ReconSpec(mesh_size=self.mesh_size, grid=tuple(self.grid),
                         iterations=self.iterations or None, damping=self.damping)


@dataclass
class FrameResult:
    """One frame's outputs. ``force`` in newtons in the wrench frame; angles in radians."""

    force: np.ndarray
    magnitude: float
    elevation: float
    azimuth: float
    residual: float
    field: StressField | None


class Pipeline:
    """Reference, mask, reconstruction model and force estimator of one sensor.

    Ready when constructed; :meth:`build` loads everything from the cache (or builds it).
    """

    def __init__(self, geometry: SensorGeometry, model: ReconstructionModel, estimator) -> None:
        self.geometry = geometry
        self.model = model
        self.estimator = estimator
        self.n_meas = model.n_meas
        self.centers = (model.centers - geometry.socket_center).astype(np.float32)  # wrench frame
        self.reference: np.ndarray | None = None
        self._svd: LandweberSVD | None = None
        self._R = model.R
        self._keep = np.ones(self.n_meas, dtype=bool)
        self._y = np.empty(self.n_meas, dtype=np.float64)
        self._y32 = np.empty(self.n_meas, dtype=np.float32)
        self._x = np.empty(model.n_cells, dtype=np.float32)

    @classmethod
    def build(cls, config: PipelineConfig, progress=None) -> "Pipeline":
        from .estimate import build_estimator

        geometry = load_sensor(config.sensor)
        model = build_model(geometry, config.recon_spec, config.cache_dir or None, progress)
        estimator = build_estimator(config.estimator, geometry, model, config.cache_dir or None, progress)
        return cls(geometry, model, estimator)

    @property
    def model_reference(self) -> np.ndarray:
        return self.model.model_reference

    @property
    def bad_channels(self) -> np.ndarray:
        return ~self._keep

    def set_reference(self, frame: np.ndarray) -> None:
        """Use the device's own unloaded frame (tare) as the difference reference."""
        ref = np.asarray(frame, dtype=float)
        if ref.shape != (self.n_meas,) or not np.all(np.isfinite(ref)):
            raise FrameError(f"reference of shape {ref.shape} with non-finite values or wrong length; "
                             f"expected ({self.n_meas},) finite volts")
        self.reference = ref.copy()

    def set_bad_channels(self, bad: np.ndarray) -> None:
        """Exclude measurements (saturated channel, dead electrode): R and the estimator get the mask.

        Re-SVDs the 208 x n_voxels sensitivity (milliseconds); the forward model is not rebuilt.
        """
        keep = ~np.asarray(bad, dtype=bool)
        if keep.shape != (self.n_meas,):
            raise ConfigError(f"bad channel mask of shape {keep.shape}, expected ({self.n_meas},)")
        if np.array_equal(keep, self._keep):
            return
        self._keep = keep
        if keep.all():
            self._R = self.model.R
        else:
            if self._svd is None:
                self._svd = LandweberSVD.from_jacobian(self.model.S)
            svd = self._svd.masked(keep)
            lam = self.model.damping * self._svd.s_max**2
            self._R = svd.matrix(self.model.iterations, self.model.step, lam, dtype=np.float32)
        self.estimator = self.estimator.masked(keep)

    def process(self, frame: np.ndarray, with_field: bool = True) -> FrameResult:
        """Estimate the force (and the field) from one frame of (n_meas,) volts.

        Raises :class:`FrameError` for a frame of the wrong length or with NaN/Inf in a used channel.
        """
        if self.reference is None:
            raise FrameError("no reference: tare the sensor (set_reference) before processing frames")
        v = np.asarray(frame, dtype=float)
        if v.shape != (self.n_meas,):
            raise FrameError(f"frame has shape {v.shape}, expected ({self.n_meas},) volts")
        y = self._y
        np.subtract(v, self.reference, out=y)
        y /= self.model.v_scale
        y[~self._keep] = 0.0
        if not np.all(np.isfinite(y)):
            raise FrameError(f"frame holds {int(np.sum(~np.isfinite(y)))} NaN/Inf values in used channels")
        force = self.estimator.estimate(y)
        mag, el, az = force_angles(force)
        field = None
        residual = float("nan")
        if with_field:
            self._y32[:] = y
            np.matmul(self._R, self._y32, out=self._x)
            dsigma = self._x.astype(np.float64) * self.model.sigma0
            field = StressField.from_conductivity_change(dsigma, self.geometry.material)
            r = y - (self.model.S @ self._x) * self._keep
            residual = float(np.linalg.norm(r) / max(np.linalg.norm(y), 1e-300))
        return FrameResult(force, float(mag), float(el), float(az), residual, field)
