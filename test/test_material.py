"""The piezoresistive law (docs/physics.md#material-law) against hand-computed values and its limits."""
import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from cstomo_sensor.model.material import (
    SIGMA_FLOOR_FRACTION,
    Material,
    StressField,
    conductivity_of_theta,
    dlog_conductivity_dtheta,
    phi_of_theta,
    pressure_of_theta,
    theta_of_conductivity,
    theta_of_conductivity_change,
)

MAT = Material()
# hand values of the reference material: rho_h = 4e-5, phi0 = 0.06, phi_c = 0.05, tau = 2
RHO0 = 4.0e-5 * (0.95 / 0.01) ** 2  # = 0.361 ohm m
SAFE = st.floats(min_value=-0.17, max_value=2.5, allow_nan=False)


def test_rest_resistivity_is_0_361():
    sigma, clipped = conductivity_of_theta(0.0, MAT)
    assert 1.0 / float(sigma) == pytest.approx(0.361, rel=1e-12)
    assert not clipped


def test_hand_value_at_theta_0_01():
    phi = 0.06 * math.exp(0.01)
    rho = 4.0e-5 * ((1 - 0.05) / (phi - 0.05)) ** 2.0
    sigma, clipped = conductivity_of_theta(np.array([0.01]), MAT)
    assert 1.0 / sigma[0] == pytest.approx(rho, rel=1e-12)
    assert rho < RHO0  # compression raises the conductivity
    assert phi_of_theta(0.01, MAT) == pytest.approx(phi, rel=1e-12)
    assert not clipped[0]


def test_hand_value_decompressed():
    theta = -0.1
    phi = 0.06 * math.exp(theta)
    sigma_hand = 1.0 / (4.0e-5 * (0.95 / (phi - 0.05)) ** 2)
    sigma, clipped = conductivity_of_theta([theta], MAT)
    assert sigma[0] == pytest.approx(sigma_hand, rel=1e-12)
    assert not clipped[0]


def test_dlog_rho_dtheta_at_rest_is_minus_12_by_finite_differences():
    h = 1e-5
    s, _ = conductivity_of_theta(np.array([-h, h]), MAT)
    dlnrho = (math.log(1 / s[1]) - math.log(1 / s[0])) / (2 * h)
    assert dlnrho == pytest.approx(-12.0, rel=1e-8)
    assert dlog_conductivity_dtheta(MAT) == pytest.approx(12.0, rel=1e-12)


def test_pressure_uses_bulk_modulus():
    # K = E / (3 (1 - 2 nu)) = 1e6 / 0.3
    assert pressure_of_theta(0.003, MAT) == pytest.approx(0.003 * 1e6 / 0.3, rel=1e-12)


@pytest.mark.parametrize("theta", [-1.0, -10.0, -np.inf, np.log(0.05 / 0.06), np.log(0.05 / 0.06) - 1e-12, -1e300])
def test_percolation_limit_clipped_and_flagged(theta):
    sigma, clipped = conductivity_of_theta(np.array([theta]), MAT)
    assert np.isfinite(sigma).all() and (sigma > 0).all()
    assert sigma[0] == pytest.approx(SIGMA_FLOOR_FRACTION / RHO0, rel=1e-12)
    assert clipped[0]


@pytest.mark.parametrize("theta", [np.inf, 1e300, 50.0, 3.0])
def test_saturation_is_finite_and_flagged(theta):
    # phi = 0.06 e^theta > 1: capped at phi = 1, i.e. sigma = 1 / rho_h
    sigma, clipped = conductivity_of_theta(np.array([theta]), MAT)
    assert sigma[0] == pytest.approx(1.0 / 4.0e-5, rel=1e-12)
    assert clipped[0]


def test_nan_is_a_flagged_broken_cell():
    sigma, clipped = conductivity_of_theta(np.array([np.nan, 0.0]), MAT)
    assert np.isfinite(sigma).all()
    assert sigma[0] == pytest.approx(SIGMA_FLOOR_FRACTION / RHO0)
    assert clipped.tolist() == [True, False]


def test_clipped_law_is_monotone_and_continuous():
    theta = np.linspace(-0.5, 3.5, 20001)
    sigma, _ = conductivity_of_theta(theta, MAT)
    assert (np.diff(sigma) >= 0).all()


@settings(max_examples=200, deadline=None)
@given(SAFE)
def test_inverse_round_trip(theta):
    sigma, clipped = conductivity_of_theta(theta, MAT)
    assert not clipped
    back, clipped_back = theta_of_conductivity(sigma, MAT)
    assert not clipped_back
    assert float(back) == pytest.approx(theta, abs=1e-12, rel=1e-12)
    back2, _ = theta_of_conductivity_change(sigma - 1 / RHO0, MAT)
    assert float(back2) == pytest.approx(theta, abs=1e-9)


@pytest.mark.parametrize("dsigma", [-1 / RHO0, -10.0, -np.inf, np.nan])
def test_inverse_clips_non_positive_and_nonfinite(dsigma):
    theta, clipped = theta_of_conductivity_change(np.array([dsigma]), MAT)
    assert np.isfinite(theta).all() and clipped[0]
    # clipped to the floor: the edge of the broken network, just above phi = phi_c
    phi_edge = 0.05 + 0.95 * math.sqrt(4e-5 * SIGMA_FLOOR_FRACTION / RHO0)
    assert theta[0] == pytest.approx(math.log(phi_edge / 0.06), rel=1e-12)


def test_inverse_clips_above_ceiling():
    theta, clipped = theta_of_conductivity(np.array([np.inf, 1e9]), MAT)
    assert np.allclose(theta, math.log(1 / 0.06)) and clipped.all()


def test_stress_field_from_conductivity_change():
    theta = np.array([0.0, 0.01, -0.05])
    sigma, _ = conductivity_of_theta(theta, MAT)
    f = StressField.from_conductivity_change(sigma - 1 / RHO0, MAT)
    np.testing.assert_allclose(f.volumetric_compression, theta, atol=1e-12)
    np.testing.assert_allclose(f.pressure, theta * 1e6 / 0.3, atol=1e-5)
    assert not f.clipped.any()
    with pytest.raises(ValueError, match="shape"):
        StressField(np.zeros(3), np.zeros(2), np.zeros(3), np.zeros(3, bool))
