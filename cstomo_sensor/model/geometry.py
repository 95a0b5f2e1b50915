"""Sensor geometries as data: YAML presets under ``config/sensors`` loaded into frozen dataclasses.

Units are SI everywhere (metres, siemens per metre, ohm square metres, amperes, pascals).
The body frame has z up and its origin at the centre of the bottom face (REFERENCE_SENSOR.md s.1).

A new sensor is a new YAML file (see ``config/sensors/cuboid_joint.yaml`` for every key); pass its
path wherever a sensor name is accepted.
"""
from __future__ import annotations

import hashlib
import json
import os
import sys
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any, Literal

import numpy as np
import yaml

from ..errors import ConfigError, require_positive
from .material import Material

SURFACE_TOL = 1e-6  # m: how far an electrode centre may lie from the body surface


@dataclass(frozen=True)
class Electrode:
    """A disc electrode on a side face: centre (m), outward unit normal, radius (m)."""

    name: str
    center: tuple[float, float, float]
    normal: tuple[float, float, float]
    radius: float


@dataclass(frozen=True)
class SensorGeometry:
    """A sensor body with its electrodes, drive current and material.

    ``shape`` is ``cuboid`` (``size`` = (lx, ly, lz)) or ``cylinder`` (``size`` = (radius, height));
    the ``disc`` preset is a cylinder 5 mm high. ``socket_radius`` > 0 cuts a concave hemisphere
    centred on the top face. ``layers`` (1 or 2) fixes the drive/measurement pair list.
    """

    name: str
    shape: Literal["cuboid", "cylinder"]
    size: tuple[float, ...]
    electrodes: tuple[Electrode, ...]
    layers: int = 1
    socket_radius: float = 0.0
    drive_current: float = 8.0e-3
    contact_impedance: float = 1.0e-5
    material: Material = field(default_factory=Material)

    def __post_init__(self) -> None:
        if self.shape not in ("cuboid", "cylinder"):
            raise ConfigError(f"body.shape={self.shape!r}: expected one of 'cuboid', 'cylinder'")
        expected = 3 if self.shape == "cuboid" else 2
        if len(self.size) != expected:
            raise ConfigError(f"body.size={self.size!r}: expected {expected} values for a {self.shape}")
        for i, s in enumerate(self.size):
            require_positive(f"body.size[{i}]", s)
        require_positive("drive_current", self.drive_current)
        require_positive("contact_impedance", self.contact_impedance)
        if self.socket_radius < 0 or self.socket_radius >= min(self.horizontal_half_extent, self.height):
            raise ConfigError(
                f"socket.radius={self.socket_radius!r}: expected 0 <= radius < "
                f"{min(self.horizontal_half_extent, self.height)} (half the body's width and its height)"
            )
        n = len(self.electrodes)
        if n < 4:
            raise ConfigError(f"electrodes: {n} given, expected at least 4")
        if self.layers not in (1, 2) or n % self.layers:
            raise ConfigError(f"electrodes.layers={self.layers!r}: expected 1 or 2, dividing {n} electrodes")
        for e in self.electrodes:
            require_positive(f"electrodes.radius ({e.name})", e.radius)
            self._check_on_surface(e)
        c = np.array([e.center for e in self.electrodes])
        d = np.linalg.norm(c[:, None, :] - c[None, :, :], axis=-1)
        r = np.array([e.radius for e in self.electrodes])
        overlap = np.argwhere(np.triu(d < (r[:, None] + r[None, :]), 1))
        if len(overlap):
            i, j = overlap[0]
            raise ConfigError(
                f"electrodes.positions: {self.electrodes[i].name} and {self.electrodes[j].name} overlap "
                f"(centres {d[i, j] * 1e3:.3f} mm apart, radii {r[i] * 1e3:.2f} + {r[j] * 1e3:.2f} mm)"
            )

    # -- derived geometry -------------------------------------------------------------------
    @property
    def height(self) -> float:
        return float(self.size[-1])

    @property
    def horizontal_half_extent(self) -> float:
        return float(min(self.size[0], self.size[1]) / 2 if self.shape == "cuboid" else self.size[0])

    @property
    def socket_center(self) -> np.ndarray:
        """Centre of the socket sphere (the wrench frame origin), m, body frame."""
        return np.array([0.0, 0.0, self.height])

    @property
    def n_electrodes(self) -> int:
        return len(self.electrodes)

    @property
    def volume(self) -> float:
        if self.shape == "cuboid":
            v = float(np.prod(self.size))
        else:
            v = float(np.pi * self.size[0] ** 2 * self.size[1])
        return v - 2.0 / 3.0 * np.pi * self.socket_radius**3

    def electrode_centers(self) -> np.ndarray:
        """(n_electrodes, 3) centres, m."""
        return np.array([e.center for e in self.electrodes], dtype=float)

    def with_electrodes(self, electrodes: tuple[Electrode, ...]) -> SensorGeometry:
        return replace(self, electrodes=tuple(electrodes))

    def with_contact_impedance(self, z: float) -> SensorGeometry:
        return replace(self, contact_impedance=float(z))

    def digest(self) -> str:
        """A hash of every field (used to key caches)."""
        return hashlib.sha256(json.dumps(asdict(self), sort_keys=True).encode()).hexdigest()[:16]

    def _check_on_surface(self, e: Electrode) -> None:
        x, y, z = e.center
        h = self.height
        if not (e.radius - SURFACE_TOL <= z <= h - e.radius + SURFACE_TOL):
            raise ConfigError(
                f"electrodes.positions ({e.name}) z={z * 1e3:.3f} mm: the disc of radius "
                f"{e.radius * 1e3:.2f} mm must lie within the side face, z in [{e.radius * 1e3:.2f}, "
                f"{(h - e.radius) * 1e3:.2f}] mm"
            )
        if self.shape == "cuboid":
            hx, hy = self.size[0] / 2, self.size[1] / 2
            on_x = abs(abs(x) - hx) < SURFACE_TOL and abs(y) <= hy - e.radius + SURFACE_TOL
            on_y = abs(abs(y) - hy) < SURFACE_TOL and abs(x) <= hx - e.radius + SURFACE_TOL
            ok = on_x or on_y
        else:
            ok = abs(np.hypot(x, y) - self.size[0]) < SURFACE_TOL
        if not ok:
            raise ConfigError(
                f"electrodes.positions ({e.name}) = ({x * 1e3:.3f}, {y * 1e3:.3f}, {z * 1e3:.3f}) mm: "
                f"not on a side face of the {self.shape} {tuple(round(s * 1e3, 3) for s in self.size)} mm "
                "(whole disc within one face)"
            )


def _outward_normal(shape: str, size: tuple[float, ...], c: np.ndarray) -> tuple[float, float, float]:
    if shape == "cylinder":
        r = np.hypot(c[0], c[1]) or 1.0
        return (float(c[0] / r), float(c[1] / r), 0.0)
    hx, hy = size[0] / 2, size[1] / 2
    if abs(abs(c[0]) - hx) <= abs(abs(c[1]) - hy):
        return (float(np.sign(c[0])), 0.0, 0.0)
    return (0.0, float(np.sign(c[1])), 0.0)


# -- loading -----------------------------------------------------------------------------------
def preset_dirs() -> list[Path]:
    """Where preset names are looked up: $CSTOMO_SENSOR_PATH, the source tree, the install share."""
    dirs = [Path(p) for p in os.environ.get("CSTOMO_SENSOR_PATH", "").split(os.pathsep) if p]
    dirs.append(Path(__file__).resolve().parents[2] / "config" / "sensors")
    dirs.append(Path(sys.prefix) / "share" / "cstomo_sensor" / "config" / "sensors")
    try:  # a colcon install on a robot
        from ament_index_python.packages import get_package_share_directory  # type: ignore

        dirs.append(Path(get_package_share_directory("cstomo_sensor")) / "config" / "sensors")
    except Exception:  # noqa: BLE001 - ament is optional; any failure means "not installed that way"
        pass
    return dirs


def preset_names() -> list[str]:
    return sorted({p.stem for d in preset_dirs() if d.is_dir() for p in d.glob("*.yaml")})


def load_sensor(name_or_path: str | os.PathLike) -> SensorGeometry:
    """Load a sensor from a preset name (``cuboid_joint``, ``cylinder``, ``disc``) or a YAML path."""
    p = Path(name_or_path)
    if p.suffix in (".yaml", ".yml") or p.exists():
        if not p.is_file():
            raise ConfigError(f"sensor file {str(p)!r}: not found")
        return sensor_from_dict(yaml.safe_load(p.read_text()), source=str(p))
    for d in preset_dirs():
        f = d / f"{name_or_path}.yaml"
        if f.is_file():
            return sensor_from_dict(yaml.safe_load(f.read_text()), source=str(f))
    raise ConfigError(f"sensor={str(name_or_path)!r}: expected a YAML file path or one of {preset_names()}")


def sensor_from_dict(d: Any, source: str = "<dict>") -> SensorGeometry:
    """Build a :class:`SensorGeometry` from the YAML mapping (every missing key is named)."""

    def need(m: Any, key: str, where: str) -> Any:
        if not isinstance(m, dict) or key not in m:
            raise ConfigError(f"{source}: missing key '{where}{key}'")
        return m[key]

    body = need(d, "body", "")
    shape = need(body, "shape", "body.")
    size = tuple(float(v) for v in need(body, "size", "body."))
    el = need(d, "electrodes", "")
    radius = float(need(el, "radius", "electrodes."))
    layers = int(need(el, "layers", "electrodes."))
    positions = np.asarray(need(el, "positions", "electrodes."), dtype=float)
    if positions.ndim != 2 or positions.shape[1] != 3:
        raise ConfigError(f"{source}: electrodes.positions has shape {positions.shape}, expected (n, 3)")
    electrodes = tuple(
        Electrode(f"e{i + 1}", tuple(map(float, c)), _outward_normal(shape, size, c), radius)
        for i, c in enumerate(positions)
    )
    mat = d.get("material", {}) or {}
    unknown = set(mat) - set(Material.__dataclass_fields__)
    if unknown:
        raise ConfigError(f"{source}: unknown material keys {sorted(unknown)}")
    try:
        return SensorGeometry(
            name=str(need(d, "name", "")),
            shape=shape,
            size=size,
            electrodes=electrodes,
            layers=layers,
            socket_radius=float((d.get("socket") or {}).get("radius", 0.0)),
            drive_current=float(need(d, "drive_current", "")),
            contact_impedance=float(need(d, "contact_impedance", "")),
            material=Material(**{k: float(v) for k, v in mat.items()}),
        )
    except ConfigError as err:
        raise ConfigError(f"{source}: {err}") from None
