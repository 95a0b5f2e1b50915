"""The settings of the benchmark table and the models and estimators they need, built (or loaded
from the cache) once per mesh and grid and shared by the settings."""
from __future__ import annotations

import time
import tracemalloc
from dataclasses import dataclass, field

import numpy as np

from ...force.estimators.estimate import build_estimator
from ...frame_path.config import PipelineConfig
from ...frame_path.pipeline import Pipeline
from ...inverse.reconstruction import ReconSpec, build_model, discrepancy_iterations
from ...model.geometry import load_sensor
from ...settings import DEFAULT_SENSOR

#: The image before issue 13: plain Landweber, k by the discrepancy rule at tau = 1.1.
PLAIN = {"weight_power": 0.0, "tau": 1.1}


@dataclass
class Setting:
    name: str
    varied: str
    mesh_size: float = ReconSpec.mesh_size  # m
    grid: tuple = ReconSpec.grid
    basis_grid: tuple = ReconSpec.basis_grid  # the unknowns' grid (averaged onto ``grid``)
    iterations: str | int = "auto"  # "auto", "few", "many" or a count
    damping: float = 0.0
    weight_power: float | None = None  # None = the model's (ReconSpec default); k by the rule for it
    tau: float | None = None  # discrepancy level of that rule; None = ReconSpec's
    dtype: str = "float32"
    estimator: str = PipelineConfig.estimator  # the default, model
    row: dict = field(default_factory=dict)


def settings_for(mode: str) -> list[Setting]:
    s = [Setting("default", "-")]
    if mode == "smoke":
        return s
    s += [Setting("grid 6x6x3", "grid", grid=(6, 6, 3)),
          Setting("grid 10x10x5", "grid", grid=(10, 10, 5)),
          Setting("iterations few", "iterations", iterations="few"),
          Setting("iterations many", "iterations", iterations="many"),
          Setting("damping 0.1", "damping", damping=0.1),
          Setting("basis 16x16x8", "basis", basis_grid=(16, 16, 8)),
          Setting("basis = image grid (before)", "basis", basis_grid=(8, 8, 4)),
          Setting("plain (p=0, tau=1.1: before)", "weight", **PLAIN),
          Setting("weight p=1", "weight", weight_power=1.0),
          Setting("float64", "dtype", dtype="float64"),
          Setting("estimator linear", "estimator", estimator="linear"),
          Setting("mesh 6 mm", "mesh", mesh_size=6.0e-3)]
    return s


class Builder:
    """Models and estimators, built (or loaded) once per mesh / grid and shared by settings."""

    def __init__(self, cache_dir, say=print) -> None:

        self.cache_dir = cache_dir or None
        self.geometry = load_sensor(DEFAULT_SENSOR)
        self.say = say
        self._models: dict = {}
        self._est: dict = {}

    @staticmethod
    def _traced(fn):
        tracemalloc.start()
        t = time.perf_counter()
        try:
            out = fn()
        finally:
            dt = time.perf_counter() - t
            _, peak = tracemalloc.get_traced_memory()
            tracemalloc.stop()
        return out, dt, peak / 2**20

    def model(self, mesh_size: float, grid: tuple, basis_grid: tuple = ReconSpec.basis_grid):

        key = (mesh_size, tuple(grid), tuple(basis_grid))
        if key not in self._models:
            spec = ReconSpec(mesh_size=mesh_size, grid=tuple(grid), basis_grid=tuple(basis_grid))
            self._models[key] = self._traced(lambda: build_model(self.geometry, spec, self.cache_dir))
        return self._models[key]

    def estimator(self, mesh_size: float, name: str):

        key = (mesh_size, name)
        if key not in self._est:
            base, *_ = self.model(mesh_size, ReconSpec.grid)  # the calibration depends on the mesh only
            self._est[key] = self._traced(lambda: build_estimator(name, self.geometry, base, self.cache_dir))
        return self._est[key]

    def pipeline(self, s: Setting):
        """(pipeline, build seconds, build MB) for a setting."""

        model, t_load, mb = self.model(s.mesh_size, s.grid, s.basis_grid)
        build_s = float(sum(model.meta.get("seconds", {}).values()))
        est, t_est, mb_est = self.estimator(s.mesh_size, s.estimator)
        extra = 0.0
        if s.iterations != "auto" or s.damping or s.weight_power is not None or s.tau is not None:
            k0 = model.iterations
            if s.weight_power is not None or s.tau is not None:  # k by the discrepancy rule for this p, tau
                svd = model.svd(s.weight_power)
                k0 = discrepancy_iterations(self.geometry, svd, model.S, model.v_scale, model.model_reference,
                                            model.basis_centers, 1.0 / svd.s_max**2, 0.0, tau=s.tau or ReconSpec.tau)
            k = {"auto": k0, "few": max(1, k0 // 4), "many": 4 * k0}.get(s.iterations, s.iterations)
            model, extra, mb2 = self._traced(lambda: model.with_settings(int(k), s.damping, s.weight_power))
            mb = max(mb, mb2)
        pipe = Pipeline(self.geometry, model, est, image_dtype=np.dtype(s.dtype))
        return pipe, build_s + extra + t_est, max(mb, mb_est)
