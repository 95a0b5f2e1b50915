"""Force angles of docs/physics.md#force-angles (radians; in degrees for people: :func:`force_angles_deg`)."""
from __future__ import annotations

import math

import numpy as np


def force_angles(f: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(magnitude, elevation, azimuth) of force vectors ``f`` (..., 3) in the wrench frame.

    elevation = atan2(-Fz, hypot(Fx, Fy)) (positive pushing down); azimuth = atan2(Fy, Fx), and 0
    when the force is vertical (horizontal part below 1e-9 of the magnitude).
    """
    f = np.asarray(f, dtype=float)
    mag = np.linalg.norm(f, axis=-1)
    h = np.hypot(f[..., 0], f[..., 1])
    el = np.arctan2(-f[..., 2], h)
    az = np.where(h > 1e-9 * np.maximum(mag, 1e-300), np.arctan2(f[..., 1], f[..., 0]), 0.0)
    return mag, el, az


def force_angles_deg(f: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(magnitude, elevation, azimuth) of :func:`force_angles` with the angles in degrees, as files and
    people read them: elevation -90..90, azimuth 0..360 (0 for a vertical force), no -0."""
    mag, el, az = force_angles(f)
    az = np.degrees(az) % 360.0
    return mag, np.degrees(el) + 0.0, np.where(az >= 360.0, 0.0, az) + 0.0


def force_angles3(f) -> tuple[float, float, float]:
    """:func:`force_angles` of one force (3,) as Python floats, without numpy's per-call overhead
    (the per-frame path: about 1 us instead of 9)."""
    fx, fy, fz = float(f[0]), float(f[1]), float(f[2])
    h = math.hypot(fx, fy)
    mag = math.hypot(h, fz)
    az = math.atan2(fy, fx) if h > 1e-9 * max(mag, 1e-300) else 0.0
    return mag, math.atan2(-fz, h), az


def planar_angle(f: np.ndarray) -> np.ndarray:
    """The paper's angle for a force in the x-z plane: gamma = atan2(-Fz, Fx)."""
    f = np.asarray(f, dtype=float)
    return np.arctan2(-f[..., 2], f[..., 0])


def force_from_angles(magnitude: float, elevation: float, azimuth: float) -> np.ndarray:
    """Inverse of :func:`force_angles` (radians)."""
    c = np.cos(elevation)
    return magnitude * np.array([c * np.cos(azimuth), c * np.sin(azimuth), -np.sin(elevation)])


def angle_between(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Angle error: arccos of the normalised dot product of estimated and true vectors (radians)."""
    a, b = np.asarray(a, float), np.asarray(b, float)
    na, nb = np.linalg.norm(a, axis=-1), np.linalg.norm(b, axis=-1)
    c = np.sum(a * b, axis=-1) / np.maximum(na * nb, 1e-300)
    return np.arccos(np.clip(c, -1.0, 1.0))
