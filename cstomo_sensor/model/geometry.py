"""Sensor geometries as data: YAML presets under ``config/sensors`` loaded into frozen dataclasses.

Units are SI everywhere (metres, siemens per metre, ohm square metres, amperes, pascals).
The body frame has z up and its origin at the centre of the bottom face (docs/physics.md#coordinate-frames).

A new sensor is a new YAML file (see ``config/sensors/cuboid_joint.yaml`` for every key); pass its
path wherever a sensor name is accepted. Which keys are required and which have defaults:
:data:`SENSOR_SCHEMA`.
"""
from __future__ import annotations

import hashlib
import json
import logging
import math
import os
import re
import sys
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any, Literal

import numpy as np
import yaml

from ..errors import ConfigError, require_positive
from .material import Material

log = logging.getLogger(__name__)

SURFACE_TOL = 1e-6  # m: how far an electrode centre may lie from the body surface
# The reference sensor and board (docs/physics.md#geometry), defined here once and imported everywhere else
# (the default sensor's name: settings.py, imported above):
N_ELECTRODES = 16  # the board drives 16 electrodes and the measurement pattern has 208 values
#: A: the board's constant current between adjacent electrodes (a sensor file's ``drive_current``).
DRIVE_CURRENT_A = 8.0e-3
#: dB: the default scene's noise (docs/physics.md#noise), also the noise the estimators and the reconstruction's
#: discrepancy rule assume when none is measured.
DEFAULT_SNR_DB = 60.0
#: A sensor name: it names cache files and the default tare file, so no path separator, no '..'.
NAME_PATTERN = re.compile(r"[A-Za-z0-9_][A-Za-z0-9_.-]{0,63}")
NAME_EXPECTED = "1..64 letters, digits, '_', '.' or '-', not starting with '.' (it names cache files)"


def noise_std(reference, snr_db: float) -> float:
    """The std (volts) of white noise ``snr_db`` dB below the rms of ``reference`` (a frame, frames, or
    their rms as one number): ``rms * 10^(-snr_db/20)`` (docs/physics.md#noise). The one rule of a noise
    given as an SNR: the simulated boards', the one the estimators and the reconstruction assume, the
    range a measured noise is checked against."""
    return float(np.sqrt(np.mean(np.square(reference)))) * 10 ** (-snr_db / 20)


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
    drive_current: float = DRIVE_CURRENT_A
    contact_impedance: float = 1.0e-5
    material: Material = field(default_factory=Material)

    def __post_init__(self) -> None:
        if not isinstance(self.name, str) or not NAME_PATTERN.fullmatch(self.name):
            raise ConfigError.bad_value("name", self.name, NAME_EXPECTED)
        if self.shape not in ("cuboid", "cylinder"):
            raise ConfigError(f"body.shape={self.shape!r}: expected one of 'cuboid', 'cylinder'")
        expected = 3 if self.shape == "cuboid" else 2
        if len(self.size) != expected:
            raise ConfigError(f"body.size={self.size!r}: expected {expected} values for a {self.shape}")
        for i, s in enumerate(self.size):
            require_positive(f"body.size[{i}]", s)
        require_positive("drive_current", self.drive_current)
        require_positive("contact_impedance", self.contact_impedance)
        if not (0 <= self.socket_radius < min(self.horizontal_half_extent, self.height)):
            raise ConfigError(
                f"socket.radius={self.socket_radius!r}: expected 0 <= radius < "
                f"{min(self.horizontal_half_extent, self.height)} (half the body's width and its height)"
            )
        n = len(self.electrodes)
        if n != N_ELECTRODES:
            raise ConfigError(f"electrodes: {n} given, expected {N_ELECTRODES} (the board and the measurement "
                              "pattern drive 16)")
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
    """Load a sensor from a preset name (``cuboid_joint``, ``cylinder``, ``disc``) or a YAML path.

    Every failure (a missing, unreadable, non-UTF-8 or malformed file, a bad value) is a
    :class:`ConfigError` naming the file and the key."""
    p = Path(name_or_path)
    try:
        is_path = p.suffix in (".yaml", ".yml") or p.exists()
    except (OSError, ValueError):  # e.g. an embedded NUL byte
        is_path = False
    if is_path:
        if not p.is_file():
            raise ConfigError(f"sensor file {str(p)!r}: not found; expected a sensor YAML file "
                              f"(docs/formats.md#sensor-file) or one of {preset_names()}")
        return sensor_from_dict(_read_yaml(p), source=str(p))
    if NAME_PATTERN.fullmatch(str(name_or_path)):  # a preset name never leaves the preset folders
        for d in preset_dirs():
            f = d / f"{name_or_path}.yaml"
            if f.is_file():
                return sensor_from_dict(_read_yaml(f), source=str(f))
    raise ConfigError(f"sensor={str(name_or_path)!r}: expected a YAML file path or one of {preset_names()}")


def _read_yaml(path: Path) -> Any:
    try:
        text = path.read_text(encoding="utf-8")
    except UnicodeDecodeError as err:
        raise ConfigError(f"sensor file {path}: not UTF-8 text (byte {err.start}); expected a YAML file") from None
    except OSError as err:
        raise ConfigError(f"sensor file {path}: cannot be read ({err.strerror or err})") from None
    try:
        return yaml.safe_load(text)
    except yaml.YAMLError as err:
        where = getattr(err, "problem_mark", None)
        at = f" at line {where.line + 1}, column {where.column + 1}" if where is not None else ""
        what = getattr(err, "problem", None) or str(err).splitlines()[0]
        raise ConfigError(f"sensor file {path}: malformed YAML{at}: {what}") from None
    except RecursionError:
        raise ConfigError(f"sensor file {path}: malformed YAML (nested too deeply)") from None


class _Required:
    def __repr__(self) -> str:
        return "REQUIRED"


#: Marks a key of :data:`SENSOR_SCHEMA` that a sensor file must give.
REQUIRED: Any = _Required()

#: A sensor file's keys, the one place that says which are required and what the others default to.
#: ``REQUIRED`` keys missing are a :class:`ConfigError` naming them, as is any key not listed here.
#: ``socket`` (absent, or without ``radius``) means no socket, silently: a flat top is a sensor of its
#: own. Each ``material.*`` key missing takes the reference rubber's value (the defaults of
#: :class:`~.material.Material`, the paper's) and is logged as a WARNING naming the key and the value
#: used. Not an error, so that a sensor of the reference rubber (another body or electrode layout)
#: need not copy six numbers; not silent, because a sensor of another rubber that forgot a key would
#: otherwise get models of the wrong rubber without a word.
SENSOR_SCHEMA: dict[str, Any] = {
    "name": REQUIRED,
    "body": {"shape": REQUIRED, "size": REQUIRED},
    "socket": {"radius": 0.0},
    "electrodes": {"radius": REQUIRED, "layers": REQUIRED, "positions": REQUIRED},
    "drive_current": REQUIRED,
    "contact_impedance": REQUIRED,
    "material": {k: f.default for k, f in Material.__dataclass_fields__.items()},
}


def _bad(source: str, key: str, value: object, expected: str) -> ConfigError:
    """A :class:`ConfigError` naming the file and the key (the value's repr cut to 60 characters)."""
    r = repr(value)
    err = ConfigError(f"{source}: {key}={r if len(r) <= 60 else r[:57] + '...'}: expected {expected}")
    err.key, err.value, err.expected = key, value, expected
    return err


def _number(source: str, key: str, v: object) -> float:
    """A finite float; numbers written as strings are taken (PyYAML reads ``1e-5`` as a string)."""
    if isinstance(v, bool) or not isinstance(v, (int, float, str)):
        raise _bad(source, key, v, "a finite number")
    try:
        f = float(v)
    except (ValueError, OverflowError):
        raise _bad(source, key, v, "a finite number") from None
    if not math.isfinite(f):
        raise _bad(source, key, v, "a finite number")
    return f


def _mapping(source: str, key: str, v: object, allowed) -> dict:
    if not isinstance(v, dict):
        raise _bad(source, key or "the file", v, "a mapping")
    unknown = sorted(str(k) for k in v if k not in allowed)
    if unknown:
        raise ConfigError(f"{source}: unknown keys {unknown} in {key or 'the top level'}; expected some of {sorted(allowed)}")
    return v


def sensor_from_dict(d: Any, source: str = "<dict>") -> SensorGeometry:
    """Build a :class:`SensorGeometry` from the YAML mapping; every missing required, unknown,
    mistyped, non-finite or out-of-range value raises :class:`ConfigError` naming its key; a missing
    ``material.*`` key is a WARNING naming it and the value used (:data:`SENSOR_SCHEMA`)."""

    def need(m: dict, key: str, where: str) -> Any:
        if key not in m:
            raise ConfigError(f"{source}: missing key '{where}{key}'")
        return m[key]

    _mapping(source, "", d, SENSOR_SCHEMA)
    name = need(d, "name", "")
    if not isinstance(name, str) or not NAME_PATTERN.fullmatch(name):
        raise _bad(source, "name", name, NAME_EXPECTED)
    body = _mapping(source, "body", need(d, "body", ""), SENSOR_SCHEMA["body"])
    shape = need(body, "shape", "body.")
    if shape not in ("cuboid", "cylinder"):
        raise _bad(source, "body.shape", shape, "one of 'cuboid', 'cylinder'")
    size = need(body, "size", "body.")
    n_size = 3 if shape == "cuboid" else 2
    if not isinstance(size, list) or len(size) != n_size:
        raise _bad(source, "body.size", size, f"a list of {n_size} lengths for a {shape}")
    size = tuple(_number(source, f"body.size[{i}]", v) for i, v in enumerate(size))
    socket = d.get("socket")
    socket = {} if socket is None else _mapping(source, "socket", socket, SENSOR_SCHEMA["socket"])
    socket_radius = _number(source, "socket.radius", socket.get("radius", SENSOR_SCHEMA["socket"]["radius"]))
    el = _mapping(source, "electrodes", need(d, "electrodes", ""), SENSOR_SCHEMA["electrodes"])
    radius = _number(source, "electrodes.radius", need(el, "radius", "electrodes."))
    layers = need(el, "layers", "electrodes.")
    if isinstance(layers, bool) or not isinstance(layers, int):
        raise _bad(source, "electrodes.layers", layers, "an integer, 1 or 2")
    positions = need(el, "positions", "electrodes.")
    if not isinstance(positions, list) or len(positions) != N_ELECTRODES:
        n = len(positions) if isinstance(positions, list) else positions
        raise _bad(source, "electrodes.positions", n,
                   f"a list of {N_ELECTRODES} electrode centres (the board and the measurement pattern drive 16)")
    centres = []
    for i, c in enumerate(positions):
        if not isinstance(c, list) or len(c) != 3:
            raise _bad(source, f"electrodes.positions[{i}]", c, "[x, y, z] in metres")
        centres.append(np.array([_number(source, f"electrodes.positions[{i}][{j}]", v) for j, v in enumerate(c)]))
    electrodes = tuple(
        Electrode(f"e{i + 1}", tuple(map(float, c)), _outward_normal(shape, size, c), radius)
        for i, c in enumerate(centres)
    )
    mat = d.get("material")
    nominal = SENSOR_SCHEMA["material"]
    mat = {} if mat is None else _mapping(source, "material", mat, nominal)
    try:
        geometry = SensorGeometry(
            name=name,
            shape=shape,
            size=size,
            electrodes=electrodes,
            layers=layers,
            socket_radius=socket_radius,
            drive_current=_number(source, "drive_current", need(d, "drive_current", "")),
            contact_impedance=_number(source, "contact_impedance", need(d, "contact_impedance", "")),
            material=Material(**{k: _number(source, f"material.{k}", mat.get(k, v)) for k, v in nominal.items()}),
        )
    except ConfigError as err:
        if str(err).startswith(f"{source}: "):
            raise
        raise ConfigError(f"{source}: {err}") from None
    missing = [k for k in nominal if k not in mat]
    if missing:
        log.warning("%s: not given, the reference rubber's value used: %s", source,
                    ", ".join(f"material.{k} = {nominal[k]:g}" for k in missing))
    return geometry
