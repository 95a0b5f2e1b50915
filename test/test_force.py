"""Force estimation and stress images on honestly simulated scenes (docs/physics.md#loads, #honest-simulation).

Stated tolerances: each estimator recovers the paper's planar cases (20 N at 30, 90, 120 deg,
60 dB) within 5 degrees and 10 % of the magnitude; on held-out random forces (5-40 N, elevation
20-90 deg) the medians are under 3 degrees and 5 %. Image locations: stated per test.
"""
from pathlib import Path

import numpy as np
import pytest
from conftest import MODEL_H, TRUTH_H

from cstomo_sensor.angles import angle_between, force_from_angles, planar_angle
from cstomo_sensor.frame_path.config import PipelineConfig
from cstomo_sensor.frame_path.pipeline import Pipeline
from cstomo_sensor.model.simulate import Load, Scene, Truth, add_noise, simulate

SCENES = Path(__file__).resolve().parent.parent / "scenes"


@pytest.fixture(scope="module", params=["linear", "model"])
def pipe(request):
    return Pipeline.build(PipelineConfig(estimator=request.param, mesh_size=MODEL_H))


@pytest.fixture(scope="module")
def planar():
    return simulate(Scene.load(SCENES / "cuboid_planar_60db.yaml"))


def test_planar_cases_angle_and_magnitude(pipe, planar):
    ref, frames, forces = planar
    pipe.set_reference(ref)
    for v, f in zip(frames, forces):
        r = pipe.process(v)
        err = np.degrees(angle_between(r.force, f))
        assert err < 5.0, (pipe.estimator.__class__.__name__, f, r.force)
        assert abs(r.magnitude - 20.0) < 2.0, (f, r.force)
        assert abs(np.degrees(planar_angle(r.force) - planar_angle(f))) < 5.0


def test_planar_cases_hot_region_under_socket_on_pushed_side(pipe, planar):
    ref, frames, forces = planar
    pipe.set_reference(ref)
    for v, f in zip(frames, forces):
        field = pipe.process(v).field
        x = field.conductivity_change
        hot = x >= 0.7 * x.max()
        c = (pipe.centers[hot] * x[hot, None]).sum(0) / x[hot].sum()  # wrench frame (socket centre)
        assert c[2] < 0 and np.hypot(c[0], c[1]) < 15e-3, c  # under the socket
        if abs(f[0]) > 5:  # tilted: on the side the force pushes
            assert np.sign(c[0]) == np.sign(f[0]), (f, c)
        else:
            assert abs(c[0]) < 5e-3, (f, c)
        assert np.all(field.pressure[hot] > 0)  # compressed there


@pytest.mark.parametrize("case", [
    pytest.param(0, marks=pytest.mark.xfail(strict=True, reason=(
        "30 deg (rim contact): the image's maximum lands at the +x face, 12.7 mm from the axis; the "
        "truth's own peak voxel is 8.2 mm out at 5 mm voxels, and the settings that pass put every "
        "socket load's maximum beside the socket (README, numerical choices)"))),
    1, 2])
def test_planar_cases_image_maximum_near_socket_axis_on_pushed_side(cuboid_model, planar, case):
    """Stated: the EIT image's maximum voxel (5 mm voxels) within 8 mm of the socket axis, and on
    the side the force pushes towards (x > 0 for 30 deg, x < 0 for 120 deg)."""
    ref, frames, forces = planar
    x = cuboid_model.reconstruct(frames[case], ref)
    c = cuboid_model.centers[np.argmax(x)]  # body frame: the socket axis is x = y = 0
    assert np.hypot(c[0], c[1]) < 8e-3, (forces[case], c)
    if abs(forces[case][0]) > 5:
        assert np.sign(c[0]) == np.sign(forces[case][0]), (forces[case], c)


@pytest.mark.slow  # seconds of computation
def test_held_out_random_forces(pipe):
    rng = np.random.default_rng(2024)  # no calibration sees these seeds, meshes or mismatch
    truth = Truth(pipe.geometry, truth_h=TRUTH_H, seed=99)
    ref = add_noise(truth.reference, truth.reference, 60, rng)
    pipe.set_reference(ref)
    errs, mags = [], []
    for _ in range(8):
        f = force_from_angles(rng.uniform(5, 40), np.radians(rng.uniform(20, 90)), rng.uniform(-np.pi, np.pi))
        v = add_noise(truth.voltages(Load("socket", force=tuple(f))), truth.reference, 60, rng)
        r = pipe.process(v, with_field=False)
        errs.append(np.degrees(angle_between(r.force, f)))
        mags.append(abs(r.magnitude - np.linalg.norm(f)) / np.linalg.norm(f))
    assert np.median(errs) < 3.0, errs
    assert np.median(mags) < 0.05, mags
    assert max(errs) < 10.0, errs


def test_zero_load_gives_near_zero_force(pipe, planar):
    ref, _, _ = planar
    pipe.set_reference(ref)
    r = pipe.process(ref)
    assert r.magnitude < 1.0 and np.all(np.isfinite(r.force))


def _hot(model, x, frac=0.5):
    return model.centers[x >= frac * x.max()]


@pytest.mark.parametrize("scene,checks", [
    ("disc_square_fig6.yaml", [(0.0, 0.0)]),
    ("disc_square_offcentre.yaml", [(0.008, 0.0)]),
    ("cylinder_two_heads_fig8.yaml", [(-0.008, 0.0), (0.008, 0.0)]),
])
@pytest.mark.slow
def test_patch_loads_imaged_at_the_loaded_place(scene, checks):
    from cstomo_sensor.inverse.reconstruction import ReconSpec, build_model
    from cstomo_sensor.model.geometry import load_sensor

    sc = Scene.load(SCENES / scene)
    g = load_sensor(sc.sensor)
    h, grid = (3e-3, (8, 8, 2)) if g.name == "disc" else (4e-3, (8, 8, 4))
    assert sc.truth_mesh_size < h
    model = build_model(g, ReconSpec(mesh_size=h, grid=grid))
    ref, frames, forces = simulate(sc)
    np.testing.assert_allclose(forces[0], [0, 0, -20.0])
    x = model.reconstruct(frames[0], ref)
    peak = model.centers[np.argmax(x)]
    # stated distance: the peak voxel lies within 6 mm (horizontally) of a loaded patch's centre
    # and, with two electrode layers, in the upper half of the body; with two heads, both sides are hot
    d = min(np.hypot(peak[0] - cx, peak[1] - cy) for cx, cy in checks)
    assert d < 6e-3, (peak, checks)
    if g.layers == 2:  # one ring at mid-thickness of a slab cannot tell top from bottom (mirror symmetry)
        assert peak[2] > g.height / 2, peak
    if len(checks) == 2:
        hot = _hot(model, x)
        assert (hot[:, 0] < -4e-3).any() and (hot[:, 0] > 4e-3).any()


@pytest.mark.slow
def test_cli_simulate_then_estimate(tmp_path):
    from cstomo_sensor.frames_io import read_forces
    from cstomo_sensor.tools.cli import main

    assert main(["simulate", "--scene", str(SCENES / "cuboid_planar_60db.yaml"), "--out", str(tmp_path)]) == 0
    for name in ("reference.csv", "frames.csv", "truth.csv"):
        assert (tmp_path / name).stat().st_size > 0
    assert main(["estimate", "--reference", str(tmp_path / "reference.csv"), "--frames", str(tmp_path / "frames.csv"),
                 "--out", str(tmp_path / "forces.csv"), "--estimator", "linear"]) == 0
    header = (tmp_path / "forces.csv").read_text().splitlines()[0]
    assert header == "frame,fx,fy,fz,magnitude,elevation_deg,azimuth_deg,consistency,foreign_load,sigma_n"
    rows = (tmp_path / "forces.csv").read_text().splitlines()[1:]
    assert [r.split(",")[-2] for r in rows] == ["0", "0", "0"]  # socket loads: no foreign load
    assert all(0 < float(r.split(",")[-1]) < 5 for r in rows), rows  # each force with its 1-sigma, N
    est, truth = read_forces(tmp_path / "forces.csv"), read_forces(tmp_path / "truth.csv")
    assert est.shape == truth.shape == (3, 3)
    assert np.degrees(angle_between(est, truth)).max() < 5.0
