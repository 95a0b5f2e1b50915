"""The piezoresistive law of the conductive rubber and its inverse (numpy only).

Paper eqs. (2), (9), (11); docs/physics.md#material-law. With theta = -trace(strain) the
volumetric compression (positive when compressed):

    phi(theta)   = phi0 * exp(theta)                                  filler volume fraction
    rho(theta)   = rho_h * ((1 - phi_c) / (phi - phi_c)) ** tau       resistivity, ohm m
    sigma        = 1 / rho                                            conductivity, S/m
    pressure     = K * theta,  K = E / (3 (1 - 2 nu))                 mean stress, Pa

Limits, handled explicitly so that no NaN, negative or infinite conductivity ever leaves
this module (the FEM must stay solvable):

* Broken network: where phi <= phi_c the conductive network breaks and the true conductivity
  is 0. The law is clipped to the floor ``SIGMA_FLOOR_FRACTION * sigma0`` (1e-6 sigma0) and the
  cell is flagged. Just above phi_c the law itself falls below the floor; those cells are
  clipped and flagged too, so the clipped conductivity is continuous and monotone in theta.
* Saturation: phi cannot exceed 1 (the whole volume is filler); phi is capped at 1, i.e.
  sigma <= 1 / rho_h, and those cells are flagged. (theta > ln(1 / phi0) = 2.8 is far outside
  small strain anyway.)
* NaN: an undefined compression carries no information; it is treated like a broken cell
  (conductivity at the floor, flagged). theta = -inf is a broken cell, theta = +inf saturates.

The inverse maps a conductivity back to theta. Conductivities at or below the floor, zero,
negative or NaN are clipped to the floor (theta = the broken-network edge) and flagged;
conductivities above 1 / rho_h (including +inf) are clipped to it and flagged. Within
``[floor, 1 / rho_h]`` the forward law and the inverse round-trip to rounding error.

The reconstruction linearises the law at rest: d ln(sigma) / d theta = tau phi / (phi - phi_c),
which is tau phi0 / (phi0 - phi_c) = 12 for the reference material
(:func:`dlog_conductivity_dtheta`).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

from ..errors import ConfigError, require_positive

__all__ = [
    "CONTACT_PER_K",
    "CREEP_T0",
    "Material",
    "RESISTIVITY_PER_K",
    "SIGMA_FLOOR_FRACTION",
    "StressField",
    "conductivity_floor",
    "conductivity_ceiling",
    "conductivity_of_theta",
    "dlog_conductivity_dtheta",
    "phi_of_theta",
    "pressure_of_theta",
    "theta_of_conductivity",
    "theta_of_conductivity_change",
]

@dataclass(frozen=True)
class Material:
    """Piezoresistive rubber (paper eqs. (2), (9), (11)) and its elasticity."""

    E: float = 1.0e6  # Young's modulus, Pa
    nu: float = 0.45  # Poisson's ratio
    phi0: float = 0.06  # filler volume fraction at rest
    phi_c: float = 0.05  # percolation threshold
    rho_h: float = 4.0e-5  # filler resistivity, ohm m
    tau: float = 2.0  # percolation exponent

    def __post_init__(self) -> None:
        require_positive("material.E", self.E)
        if not 0.0 <= self.nu < 0.5:
            raise ConfigError(f"material.nu={self.nu!r}: expected 0 <= nu < 0.5")
        require_positive("material.rho_h", self.rho_h)
        require_positive("material.tau", self.tau)
        if not 0.0 < self.phi_c < self.phi0 < 1.0:
            raise ConfigError(
                f"material.phi_c={self.phi_c!r}, material.phi0={self.phi0!r}: expected 0 < phi_c < phi0 < 1"
            )

    @property
    def rho0(self) -> float:
        """Unloaded resistivity, ohm m (0.361 for the reference material)."""
        return self.rho_h * ((1.0 - self.phi_c) / (self.phi0 - self.phi_c)) ** self.tau

    @property
    def sigma0(self) -> float:
        """Unloaded conductivity, S/m."""
        return 1.0 / self.rho0

    @property
    def bulk_modulus(self) -> float:
        """K = E / (3 (1 - 2 nu)), Pa."""
        return self.E / (3.0 * (1.0 - 2.0 * self.nu))



SIGMA_FLOOR_FRACTION = 1.0e-6
"""The clipped conductivity of a broken network, as a fraction of the unloaded sigma0."""

#: Creep (docs/physics.md#device-changes): under a held load the rubber's strain grows by a fraction
#: c of its initial value per decade of time, counted from this many seconds after the load changed
#: (log10(max(t, CREEP_T0) / CREEP_T0)). The simulation's law and the stream's compensation both use it.
CREEP_T0 = 0.1

#: The typical device's temperature coefficients (docs/physics.md#device-changes), per K: the rubber's
#: resistivity (+0.2..+1.5 %/K; so a 2 % change is 2.5 K) and each contact's impedance (-0.5..-1.5 %/K):
#: the defaults of a timeline, the warm-up's and the full change's, what the robot bench converts with,
#: and what the diagnostics express the tracked change in.
RESISTIVITY_PER_K = 0.008
CONTACT_PER_K = -0.01


def conductivity_floor(mat: Material) -> float:
    """Smallest conductivity the law returns, S/m: ``SIGMA_FLOOR_FRACTION * sigma0``."""
    return SIGMA_FLOOR_FRACTION * mat.sigma0


def conductivity_ceiling(mat: Material) -> float:
    """Largest conductivity the law returns, S/m: ``1 / rho_h`` (phi = 1, all filler)."""
    return 1.0 / mat.rho_h


def phi_of_theta(theta: ArrayLike, mat: Material) -> np.ndarray:
    """Filler volume fraction phi = phi0 exp(theta) (paper eq. (9)).

    Parameters
    ----------
    theta : (...) array_like
        Volumetric compression -trace(strain), dimensionless, positive when compressed.
    mat : Material

    Returns
    -------
    phi : (...) ndarray
        Unclipped; ``inf`` for huge theta, 0 for theta = -inf, NaN for NaN.
    """
    with np.errstate(over="ignore"):
        return mat.phi0 * np.exp(np.asarray(theta, dtype=float))


def conductivity_of_theta(theta: ArrayLike, mat: Material) -> tuple[np.ndarray, np.ndarray]:
    """Conductivity of the rubber at a volumetric compression (paper eq. (11)), clipped.

    Parameters
    ----------
    theta : (...) array_like
        Volumetric compression, dimensionless (any float, including +-inf and NaN).
    mat : Material

    Returns
    -------
    sigma : (...) ndarray
        Conductivity, S/m, always finite and within
        ``[conductivity_floor(mat), conductivity_ceiling(mat)]``.
    clipped : (...) bool ndarray
        True where the law was clipped: broken network (phi <= phi_c, or the law below the
        floor), saturation (phi > 1) or NaN input. See the module docstring.
    """
    th = np.asarray(theta, dtype=float)
    phi = phi_of_theta(th, mat)
    floor = conductivity_floor(mat)
    ceil = conductivity_ceiling(mat)
    nan = np.isnan(th)
    saturated = phi > 1.0
    excess = np.clip(np.where(nan, 0.0, phi), mat.phi_c, 1.0) - mat.phi_c  # in [0, 1 - phi_c]
    sigma_law = ((excess / (1.0 - mat.phi_c)) ** mat.tau) / mat.rho_h  # finite, >= 0
    broken = nan | (sigma_law <= floor)
    sigma = np.where(broken, floor, np.minimum(sigma_law, ceil))
    return sigma, broken | saturated


def theta_of_conductivity(sigma: ArrayLike, mat: Material) -> tuple[np.ndarray, np.ndarray]:
    """Volumetric compression giving a conductivity: the inverse of :func:`conductivity_of_theta`.

    theta = ln(phi / phi0) with phi = phi_c + (1 - phi_c) (rho_h sigma) ** (1 / tau).

    Parameters
    ----------
    sigma : (...) array_like
        Conductivity, S/m.
    mat : Material

    Returns
    -------
    theta : (...) ndarray
        Always finite, within ``[theta(floor), ln(1 / phi0)]``.
    clipped : (...) bool ndarray
        True where sigma was outside ``(floor, 1 / rho_h]`` or not finite (NaN, +-inf, <= 0)
        and was clipped to that range first (NaN is clipped to the floor).
    """
    s = np.asarray(sigma, dtype=float)
    floor = conductivity_floor(mat)
    ceil = conductivity_ceiling(mat)
    nan = np.isnan(s)
    low = nan | (s <= floor)
    high = s > ceil
    s_c = np.where(low, floor, np.where(high, ceil, s))
    phi = mat.phi_c + (1.0 - mat.phi_c) * (mat.rho_h * s_c) ** (1.0 / mat.tau)
    theta = np.log(phi / mat.phi0)
    return theta, low | high


def theta_of_conductivity_change(dsigma: ArrayLike, mat: Material) -> tuple[np.ndarray, np.ndarray]:
    """Volumetric compression from a conductivity change, sigma = sigma0 + dsigma.

    Parameters
    ----------
    dsigma : (...) array_like
        Conductivity change from the unloaded sigma0, S/m.
    mat : Material

    Returns
    -------
    theta : (...) ndarray
    clipped : (...) bool ndarray
        As for :func:`theta_of_conductivity` (sigma <= 0 or not finite is clipped and flagged).
    """
    return theta_of_conductivity(mat.sigma0 + np.asarray(dsigma, dtype=float), mat)


def pressure_of_theta(theta: ArrayLike, mat: Material) -> np.ndarray:
    """Mean stress -trace(stress) / 3 = K theta, Pa, positive in compression.

    Parameters
    ----------
    theta : (...) array_like
    mat : Material

    Returns
    -------
    pressure : (...) ndarray, Pa
    """
    return mat.bulk_modulus * np.asarray(theta, dtype=float)


def dlog_conductivity_dtheta(mat: Material, theta: ArrayLike = 0.0) -> np.ndarray | float:
    """Sensitivity d ln(sigma) / d theta = tau phi / (phi - phi_c) of the unclipped law.

    At rest (theta = 0) this is tau phi0 / (phi0 - phi_c) (12 for the reference material); the
    reconstruction uses it to linearise: dsigma / sigma0 ~ 12 theta for small theta.

    Parameters
    ----------
    mat : Material
    theta : (...) array_like, default 0.0
        Must keep phi > phi_c (the sensitivity diverges at the percolation threshold).

    Returns
    -------
    float or (...) ndarray
    """
    phi = phi_of_theta(theta, mat)
    out = mat.tau * phi / (phi - mat.phi_c)
    return float(out) if np.ndim(out) == 0 else out


@dataclass(frozen=True)
class StressField:
    """Per-cell mechanical state recovered from a reconstructed conductivity change.

    Attributes
    ----------
    conductivity_change : (n,) ndarray
        dsigma, S/m, as given.
    volumetric_compression : (n,) ndarray
        theta = -trace(strain), dimensionless, positive when compressed.
    pressure : (n,) ndarray
        Mean stress K theta, Pa, positive in compression.
    clipped : (n,) bool ndarray
        Cells whose conductivity was outside the law's range (see :func:`theta_of_conductivity`).
    """

    conductivity_change: np.ndarray
    volumetric_compression: np.ndarray
    pressure: np.ndarray
    clipped: np.ndarray

    def __post_init__(self) -> None:
        shapes = {
            "conductivity_change": np.shape(self.conductivity_change),
            "volumetric_compression": np.shape(self.volumetric_compression),
            "pressure": np.shape(self.pressure),
            "clipped": np.shape(self.clipped),
        }
        if len(set(shapes.values())) != 1:
            raise ConfigError(f"StressField: arrays must share one shape, got {shapes}")

    @classmethod
    def from_conductivity_change(cls, dsigma: ArrayLike, mat: Material) -> StressField:
        """Apply the inverse law and K theta to a conductivity change.

        Parameters
        ----------
        dsigma : (n,) array_like
            Conductivity change from sigma0, S/m.
        mat : Material
        """
        ds = np.asarray(dsigma, dtype=float)
        theta, clipped = theta_of_conductivity_change(ds, mat)
        return cls(ds, theta, pressure_of_theta(theta, mat), clipped)
