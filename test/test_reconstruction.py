"""Sensitivity matrix, closed-form Landweber matrix, difference imaging on honest data, extremes."""
import numpy as np
import pytest
import scipy.sparse as sp
from reference_landweber import landweber

from cstomo_sensor.cache import input_hash
from cstomo_sensor.errors import ConfigError, FrameError, ModelMismatchError
from cstomo_sensor.inverse.landweber import LandweberSVD, column_weight
from cstomo_sensor.inverse.reconstruction import ReconSpec, ReconstructionModel, model_inputs
from cstomo_sensor.model.pattern import MeasurementPattern
from cstomo_sensor.model.simulate import Load, add_noise


@pytest.fixture(scope="module")
def jac(cuboid_forward, cuboid_solution):
    return cuboid_forward.jacobian(solution=cuboid_solution)


def test_jacobian_taylor_error_falls_as_h_squared(cuboid_forward, cuboid_solution, jac):
    rng = np.random.default_rng(1)
    s0 = cuboid_forward.sigma0
    dv = rng.standard_normal(len(s0)) * s0
    V = cuboid_solution.voltages
    errs = [np.linalg.norm(cuboid_forward.voltages(s0 + h * dv) - V - h * jac @ dv) for h in (1e-2, 1e-3)]
    assert 60 < errs[0] / errs[1] < 140, errs  # second order: a factor 100 per decade


def test_adjoint_identity_tangent_against_geselowitz(cuboid_forward, cuboid_solution, jac):
    """w.(J v) with J v from the tangent-linear solve (differentiating the system matrix) equals
    v.(J^T w) from the explicit adjoint-field Jacobian."""
    fm, sol = cuboid_forward, cuboid_solution
    rng = np.random.default_rng(2)
    v = rng.standard_normal(fm.mesh.n_cells) * fm.sigma0
    w = rng.standard_normal(len(sol.voltages))
    n, L = fm.cem.n_nodes, fm.cem.n_electrodes
    dK = sp.bmat([[fm.cem.stiffness(v), None], [None, sp.csr_matrix((L - 1, L - 1))]]).tocsr()
    x = np.vstack([sol.fields.u, sol.fields.U[:-1]])
    dx = -fm.cem.factorize(fm.sigma0)(dK @ x)
    dU = np.vstack([dx[n:], np.zeros((1, dx.shape[1]))])
    Jv = fm.pattern.voltages(dU.T)
    assert w @ Jv == pytest.approx(v @ (jac.T @ w), rel=1e-9)


@pytest.mark.slow  # seconds of computation
@pytest.mark.parametrize("p", [0.0, 0.7, 1.0])
def test_closed_form_equals_iterations_on_the_real_sensitivity(cuboid_model, p):
    """The model's R (float32) against the weighted iteration g += step (W S^T (y - S g) - lam g) on
    the basis, averaged onto the image's voxels; ``fit`` against S g."""
    S = cuboid_model.S
    y = S @ np.random.default_rng(3).standard_normal(S.shape[1]) * 0.01
    w = column_weight(S, p)
    for k, damping in [(1, 0.0), (5, 0.0), (40, 0.01)]:
        m = cuboid_model.with_settings(k, damping, weight_power=p)
        assert m.weight_power == p
        lam = damping * np.linalg.norm(S * np.sqrt(w), 2) ** 2
        g = landweber(S, y, k, step=m.step, damping=lam, weight=w if p else None)
        x = m.average @ g
        np.testing.assert_allclose(m.R.astype(float) @ y, x, rtol=1e-5, atol=1e-6 * np.abs(x).max())
        np.testing.assert_allclose(m.fit.astype(float) @ y, S @ g, rtol=1e-4, atol=1e-6 * np.abs(S @ g).max())


def test_weight_power_zero_is_the_plain_matrix_exactly(cuboid_model):
    plain = LandweberSVD.from_jacobian(cuboid_model.S)
    m = cuboid_model.with_settings(7, 0.0, weight_power=0.0)
    Rb = plain.matrix(7, 1.0 / plain.s_max**2, dtype=np.float64)
    assert np.array_equal(m.R, (cuboid_model.average @ Rb).astype(np.float32))
    assert cuboid_model.weight_power == ReconSpec.weight_power > 0  # the default model is weighted
    with pytest.raises(ConfigError, match="weight_power"):
        ReconSpec(weight_power=-0.1)
    with pytest.raises(ConfigError, match="tau"):
        ReconSpec(tau=0.0)


def test_sensitivity_rank_is_at_most_104(cuboid_model):
    svd = LandweberSVD.from_jacobian(cuboid_model.S)
    assert svd.rank <= 104
    print(f"S: rank {svd.rank}, condition {svd.condition:.3g}, k = {cuboid_model.iterations}")


def test_image_is_the_volume_average_of_the_basis(cuboid_forward, cuboid_model):
    """``average`` against the forward cells: a basis image that is a linear function of position
    averages to that function at each image voxel's centroid (exact: the grids nest), rows
    sum to 1, and every basis voxel's volume lands in the image (none lost)."""
    from cstomo_sensor.inverse.reconstruction import voxel_basis

    A = cuboid_model.average
    np.testing.assert_allclose(np.asarray(A.sum(axis=1)).ravel(), 1.0, rtol=1e-12)
    lin = cuboid_model.basis_centers @ np.array([1.0, -2.0, 3.0]) + 0.5
    np.testing.assert_allclose(A @ lin, cuboid_model.centers @ np.array([1.0, -2.0, 3.0]) + 0.5, rtol=1e-9)
    mesh = cuboid_forward.mesh
    _, _, basis_volumes = voxel_basis(None, mesh, ReconSpec().basis_grid)
    np.testing.assert_allclose(A.T @ cuboid_model.volumes, basis_volumes, rtol=1e-9)
    assert cuboid_model.S.shape[1] == len(basis_volumes) > 4 * cuboid_model.n_cells


# stated distance: the peak voxel (5 x 5 x 5 mm voxels) lies within 10 mm (two voxel widths) of
# the inclusion's centre, and on the inclusion's side of the body's mid-planes
@pytest.mark.parametrize("center", [
    (0.0, 0.0, 0.011),        # right under the socket
    (0.006, -0.005, 0.003),   # near the bottom
    (0.010, 0.008, 0.010),    # off centre
    (-0.012, 0.0, 0.015),     # near the upper electrode layer
])
def test_inclusion_reconstructed_at_its_place_on_independent_mesh(cuboid_model, cuboid_truth, center):
    assert cuboid_truth.truth_h < cuboid_model.meta["mesh_h"]  # finer, independent mesh
    rng = np.random.default_rng(4)
    ref = add_noise(cuboid_truth.reference, cuboid_truth.reference, 60, rng)
    v = add_noise(cuboid_truth.voltages(Load("inclusion", inclusion=(*center, 0.004, 1.0))),
                  cuboid_truth.reference, 60, rng)
    x = cuboid_model.reconstruct(v, ref)
    peak = cuboid_model.centers[np.argmax(x)]
    assert np.linalg.norm(peak - center) < 10e-3, peak
    for i in (0, 1):
        if abs(center[i]) > 4e-3:
            assert np.sign(peak[i]) == np.sign(center[i]), peak


def test_zero_difference_gives_exactly_zero(cuboid_model):
    ref = cuboid_model.model_reference
    assert np.all(cuboid_model.reconstruct(ref, ref) == 0.0)


@pytest.mark.parametrize("k", [1, 10**6])
def test_extreme_iteration_counts_stay_finite(cuboid_model, cuboid_truth, k):
    m = cuboid_model.with_settings(k)
    v = cuboid_truth.voltages(Load("inclusion", inclusion=(0, 0, 0.01, 0.004, 1.0)))
    x = m.reconstruct(v, cuboid_truth.reference)
    assert np.all(np.isfinite(x)) and np.all(np.isfinite(m.R))
    assert np.abs(x).max() < 1e3 * cuboid_model.sigma0


def test_step_at_stability_bound_stays_bounded(cuboid_model):
    S = cuboid_model.S
    smax = np.linalg.norm(S, 2)
    y = S @ np.ones(S.shape[1]) * 0.01
    norms = []
    landweber(S, y, 200, step=2.0 / smax**2, callback=lambda k, g: norms.append(np.linalg.norm(g)))
    assert np.all(np.isfinite(norms)) and max(norms) < 1e4 * np.linalg.norm(np.linalg.pinv(S) @ y)


def test_ill_conditioned_sensitivity_reported_and_finite(cuboid_model):
    svd = LandweberSVD.from_jacobian(cuboid_model.S)
    assert svd.condition > 100, f"condition number {svd.condition:.3g}"
    R = svd.matrix(10**9)
    assert np.all(np.isfinite(R))


def test_float32_matches_float64(cuboid_model, cuboid_truth):
    svd = cuboid_model.svd()
    R64, _ = cuboid_model.matrices(svd, cuboid_model.iterations, cuboid_model.step, dtype=np.float64)
    y = cuboid_model.normalise(cuboid_truth.voltages(Load("inclusion", inclusion=(0, 0, 0.01, 0.004, 1.0))),
                               cuboid_truth.reference)
    x32 = cuboid_model.R @ y.astype(np.float32)
    np.testing.assert_allclose(x32, R64 @ y, rtol=1e-4, atol=1e-5 * np.abs(R64 @ y).max())


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
def test_frames_with_nan_or_inf_refused(cuboid_model, bad):
    v = cuboid_model.model_reference.copy()
    v[17] = bad
    with pytest.raises(FrameError, match="NaN/Inf"):
        cuboid_model.reconstruct(v, cuboid_model.model_reference)


def test_masked_channels_ignored(cuboid_model, cuboid_truth):
    from cstomo_sensor.force.estimators.estimate import LinearEstimator
    from cstomo_sensor.frame_path.pipeline import Pipeline

    n = cuboid_model.n_meas
    est = LinearEstimator(np.random.default_rng(0).standard_normal((20, 3)),
                          np.random.default_rng(1).standard_normal((20, n)) * 0.01, np.full(n, 1e-3), 1e-3)
    from cstomo_sensor.model.geometry import load_sensor

    pipe = Pipeline(load_sensor("cuboid_joint"), cuboid_model, est)
    pipe.set_reference(cuboid_truth.reference)
    v = cuboid_truth.voltages(Load("inclusion", inclusion=(0, 0, 0.01, 0.004, 1.0)))
    bad = MeasurementPattern(16, 2).electrode_rows(4)  # a dead electrode
    bad[100] = True  # and a saturated channel
    pipe.set_bad_channels(bad)
    clean = pipe.process(v)
    junk = v.copy()
    junk[bad] = 1e6
    dirty = pipe.process(junk)
    np.testing.assert_array_equal(clean.field.conductivity_change, dirty.field.conductivity_change)
    np.testing.assert_array_equal(clean.force, dirty.force)
    assert np.all(np.isfinite(clean.field.pressure))
    # the masked image is the model's weighted iteration on the kept rows (the weight of the whole S)
    keep = ~bad
    y = pipe.normalise(v)  # by the device's own reference scale (issue 11), as process forms it
    g = landweber(cuboid_model.S[keep], y[keep], cuboid_model.iterations, step=cuboid_model.step,
                  weight=column_weight(cuboid_model.S, cuboid_model.weight_power))
    x = cuboid_model.average @ g
    np.testing.assert_allclose(clean.field.conductivity_change, x * cuboid_model.sigma0, rtol=1e-4,
                               atol=1e-5 * np.abs(x).max() * cuboid_model.sigma0)


@pytest.mark.parametrize("contrast", [1e-3 - 1.0, 1e3])
def test_extreme_contrasts_give_finite_images(cuboid_model, cuboid_truth, contrast):
    v = cuboid_truth.voltages(Load("inclusion", inclusion=(0, 0, 0.01, 0.004, contrast)))
    x = cuboid_model.reconstruct(v, cuboid_truth.reference)
    assert np.all(np.isfinite(x))
    from cstomo_sensor.model.material import StressField

    f = StressField.from_conductivity_change(x, cuboid_truth.geometry.material)
    assert np.all(np.isfinite(f.pressure)) and np.all(np.isfinite(f.volumetric_compression))


def test_model_file_round_trip_and_mismatch(cuboid_model, cuboid, tmp_path):
    p = tmp_path / "model.npz"
    cuboid_model.save(p)
    back = ReconstructionModel.load(p, cuboid_model.key)
    np.testing.assert_array_equal(back.R, cuboid_model.R)
    assert back.iterations == cuboid_model.iterations
    other = input_hash(model_inputs(cuboid.with_contact_impedance(2e-5), ReconSpec()))
    assert other != cuboid_model.key
    with pytest.raises(ModelMismatchError, match="rebuild"):
        ReconstructionModel.load(p, other)
    with np.load(p, allow_pickle=False) as z:  # no pickle inside
        assert all(z[k].dtype != object for k in z.files)


def test_cli_reconstruct_writes_field(cuboid_model, cuboid_truth, tmp_path):
    from cstomo_sensor.frames_io import write_frames
    from cstomo_sensor.tools.cli import main

    write_frames(tmp_path / "ref.csv", cuboid_truth.reference[None])
    frames = np.array([cuboid_truth.voltages(Load("inclusion", inclusion=(0, 0, 0.01, 0.004, 1.0)))] * 2)
    write_frames(tmp_path / "frames.csv", frames)
    assert main(["reconstruct", "--reference", str(tmp_path / "ref.csv"), "--frames", str(tmp_path / "frames.csv"),
                 "--out", str(tmp_path / "field.npz")]) == 0
    with np.load(tmp_path / "field.npz", allow_pickle=False) as z:
        assert z["centers"].shape == (cuboid_model.n_cells, 3)
        assert z["volumes"].shape == (cuboid_model.n_cells,)
        assert z["conductivity_change"].shape == (2, cuboid_model.n_cells)
        np.testing.assert_allclose(z["conductivity_change"][0], cuboid_model.reconstruct(frames[0], cuboid_truth.reference),
                                   rtol=1e-4, atol=1e-6)  # CSV keeps 10 significant digits
