"""The calibration's fit on load means (fast, pure numpy: outside the slow test_calibration module)."""
import numpy as np
import pytest

from cstomo_sensor.errors import ConfigError
from cstomo_sensor.force.reference.calibration import calibrate, fit_correction, load_groups


def _device(seed: int = 8):
    rng = np.random.default_rng(seed)
    n_meas = 30
    F_cal = rng.uniform(-20, 20, (60, 3))
    S = rng.standard_normal((n_meas, 3)) * 1e-3
    model = lambda F: F @ S.T + 1e-5 * (F**2) @ np.abs(S).T  # noqa: E731  a smooth, slightly non-linear response
    loads = rng.uniform(-15, 15, (6, 3))
    counts = np.array([1, 3, 7, 2, 5, 4])
    A_true = np.eye(3) + 0.05 * rng.standard_normal((3, 3))
    return rng, n_meas, F_cal, model, loads, counts, A_true


def test_the_fit_on_load_means_with_counts_is_the_fit_on_every_frame():
    """A load's frames enter the fit as their mean weighted by their count (how calibrate() fits a
    20 000-frame recording in seconds): the same A and D as the fit on every frame, row by row."""
    rng, n_meas, F_cal, model, loads, counts, A_true = _device()
    F = np.repeat(loads, counts, axis=0)
    noise = np.full(n_meas, 2e-4)
    y = model(F @ A_true.T) + noise * rng.standard_normal((len(F), n_meas))
    A1, D1 = fit_correction(F_cal, model(F_cal), F, y, noise)
    y_mean = np.array([y[np.repeat(np.arange(6), counts) == g].mean(0) for g in range(6)])
    A2, D2 = fit_correction(F_cal, model(F_cal), loads, y_mean, noise, counts=counts)
    np.testing.assert_allclose(A2, A1, rtol=0, atol=1e-8)
    np.testing.assert_allclose(D2, D1, rtol=0, atol=1e-8 * np.abs(D1).max())
    assert np.abs(A1 - A_true).max() < 0.02  # and the fit finds the device's force map
    # the counts matter: equal weights give another fit
    A3, _ = fit_correction(F_cal, model(F_cal), loads, y_mean, noise)
    assert np.abs(A3 - A1).max() > 1e-6



def test_a_reference_force_that_wanders_within_a_load_fits_as_every_frame_to_its_own_error():
    """A reference F/T sensor's reading wanders within a held load (up to load_groups' 0.5 N; the
    rubber feels each frame's own force): the fit on the load's mean force and mean frame differs from
    the fit on every frame by far less than either differs from the device (the approximation is of
    second order in that spread)."""
    rng, n_meas, F_cal, model, loads, counts, A_true = _device(11)
    counts = counts * 10
    F = np.repeat(loads, counts, axis=0)
    F = F + rng.uniform(-0.12, 0.12, F.shape)  # two frames of a load differ by <= 0.42 N: one load (load_groups)
    groups = load_groups(F)
    assert groups.max() + 1 == len(loads)
    noise = np.full(n_meas, 2e-4)
    y = model(F @ A_true.T) + noise * rng.standard_normal((len(F), n_meas))
    A1, D1 = fit_correction(F_cal, model(F_cal), F, y, noise)
    f_mean = np.array([F[groups == g].mean(0) for g in range(len(loads))])
    y_mean = np.array([y[groups == g].mean(0) for g in range(len(loads))])
    A2, D2 = fit_correction(F_cal, model(F_cal), f_mean, y_mean, noise, counts=np.bincount(groups))
    # measured: 1e-5 against 1e-3 (A), 1.3 % of D's own error (this device's true D is zero)
    assert np.abs(A2 - A1).max() < 0.1 * np.abs(A1 - A_true).max()
    assert np.abs(D2 - D1).max() < 0.1 * np.abs(D1).max()


def test_loads_in_one_plane_are_refused_saying_so():
    """The paper's three planar cases (30, 90, 120 deg, all in the x-z plane) cannot fix A: refused in
    words, before the pipeline is used (it printed "loads='3 loads spanning 2 directions'")."""
    planar = np.array([[17.32, 0, -10], [0, 0, -20], [-10, 0, -17.32]])
    with pytest.raises(ConfigError, match=r"^3 loads, all in one plane: expected at least 3 loads in independent "
                                          r"directions \(forces not all in one plane through the origin\)$"):
        calibrate(None, np.zeros((3, 208)), planar)
    with pytest.raises(ConfigError, match=r"^2 loads, all in one plane: "):
        calibrate(None, np.zeros((2, 208)), planar[:2])
