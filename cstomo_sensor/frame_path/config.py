"""The settings of the per-frame path (:class:`PipelineConfig`, frame_path/pipeline.py) and of the frame
stream (:class:`StreamConfig`, frame_path/stream.py). The defaults, ranges and descriptions of those the node
has as parameters are declared once in cstomo_sensor/settings.py and checked from there
(:func:`~cstomo_sensor.settings.check_config`): a bad value is a :class:`ConfigError` naming it and its range.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

from ..errors import ConfigError
from ..force.reference.tare_rules import TARE_MAX_SPREAD
from ..settings import check_config, default

if TYPE_CHECKING:
    from ..inverse.reconstruction import ReconSpec


@dataclass(frozen=True)
class PipelineConfig:
    """Every setting of the per-frame path."""

    sensor: str = default("sensor")
    cache_dir: str = default("cache_dir")  # '' = default_cache_dir()
    estimator: str = default("estimator")
    mesh_size: float = default("mesh_size")  # m
    grid: tuple[int, int, int] = default("grid")
    iterations: int = default("iterations")  # 0 = chosen by the discrepancy rule
    damping: float = default("damping")
    max_force: float = default("max_force")  # N; larger estimates (and frames no such load explains) are implausible
    calibration_file: str = default("calibration_file")  # a device calibration (cstomo calibrate); '' = the nominal model

    def __post_init__(self) -> None:
        check_config(self)
        object.__setattr__(self, "grid", self.recon_spec.grid)  # a tuple

    @property
    def recon_spec(self) -> ReconSpec:
        from ..inverse.reconstruction import ReconSpec  # here: a config (a command's --help) loads no model code

        return ReconSpec(mesh_size=self.mesh_size, grid=tuple(self.grid),
                         iterations=self.iterations or None, damping=self.damping)


@dataclass(frozen=True)
class StreamConfig:
    """Every setting of the frame stream."""

    tare_frames: int = default("tare_frames")
    tare_max_spread: float = TARE_MAX_SPREAD  # a fraction of the reference rms (force/reference/tare_rules.py)
    stress_field_every: int = default("stress_field_every")  # the fields of every N-th processed frame (the first); 0 never
    wrench_filter_hz: float = default("wrench_filter_hz")  # 0 = no filtered wrench
    stale_timeout: float = default("stale_timeout")  # s: a frame older is late (dropped); a gap longer restarts the filter
    drift_tracking: bool = default("drift_tracking")  # follow the device's slow uniform change (force/slow_states/drift.py)
    creep_per_decade: float = default("creep_per_decade")  # the rubber's creep (force/slow_states/creep.py) unless the calibration's; 0 off
    noise_estimation: bool = True  # a reference without a measured noise: estimate it from the frames (force/reference/noise_estimate.py)
    max_sigma_n: float = default("max_sigma_n")  # N: a force's 1-sigma above it is said in the diagnostics; 0 off
    frame_id: str = default("frame_id")  # the wrench's frame: an expected load in another is refused (force/checks/expected.py)
    expected_wrench_tolerance: float = default("expected_wrench_tolerance")  # s: an expected load's stamp vs the frames'

    @classmethod
    def offline(cls, **settings) -> StreamConfig:
        """The frame stream of a file, a bench or a test: the node's settings but no stress fields
        (``stress_field_every`` 0: they cost a reconstruction each and no one reads them), ``settings``
        overriding any (``cstomo replay --stress-field-every`` asks for them)."""
        return cls(**{"stress_field_every": 0, **settings})

    def __post_init__(self) -> None:
        check_config(self)
        if not self.tare_max_spread > 0:  # no node setting
            raise ConfigError.bad_value("tare_max_spread", self.tare_max_spread, "> 0 (a fraction of the reference rms)")
