"""Forward model: exact checks, reciprocity, conservation, symmetry, convergence, caching."""
from pathlib import Path

import numpy as np
import pytest
from conftest import MODEL_H, TRUTH_H

from cstomo_sensor.cache import cache_load, cache_save
from cstomo_sensor.errors import MeshError
from cstomo_sensor.model.cem import CEMSystem, ForwardModel, local_stiffness
from cstomo_sensor.model.geometry import load_sensor
from cstomo_sensor.model.mesh import MeshSpec, TetMesh, build_mesh, face_patch


def box_mesh(lx, ly, lz, n):
    """Structured tetrahedral mesh of a box: n cubes per axis, 6 tetrahedra each (Kuhn)."""
    ax = [np.linspace(0, L, n + 1) for L in (lx, ly, lz)]
    P = np.stack(np.meshgrid(*ax, indexing="ij"), -1).reshape(-1, 3)
    idx = np.arange((n + 1) ** 3).reshape((n + 1,) * 3)
    tets = []
    paths = [(0, 1, 2), (0, 2, 1), (1, 0, 2), (1, 2, 0), (2, 0, 1), (2, 1, 0)]
    for i in range(n):
        for j in range(n):
            for k in range(n):
                for path in paths:
                    v = np.array([i, j, k])
                    chain = [idx[tuple(v)]]
                    for axis in path:
                        v = v.copy()
                        v[axis] += 1
                        chain.append(idx[tuple(v)])
                    tets.append(chain)
    tets = np.array(tets)
    m = TetMesh(P, tets)
    neg = m.volumes < 0
    tets[neg] = tets[neg][:, [0, 2, 1, 3]]
    return TetMesh(P, tets)


def test_unit_tetrahedron_stiffness():
    m = TetMesh(np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1.0]]), np.array([[0, 1, 2, 3]]))
    expected = np.array([[3, -1, -1, -1], [-1, 1, 0, 0], [-1, 0, 1, 0], [-1, 0, 0, 1]]) / 6.0
    np.testing.assert_allclose(local_stiffness(m)[0], expected, rtol=1e-12, atol=1e-12 * np.abs(expected).max())


def test_two_full_face_electrodes_give_exact_resistance():
    lx, ly, lz, rho, z, current = 0.03, 0.02, 0.01, 0.361, 1.0e-5, 8e-3
    mesh = box_mesh(lx, ly, lz, 4)
    cen, _, _ = mesh.boundary_geometry()
    left = face_patch(mesh, np.abs(cen[:, 0]) < 1e-12, "left")
    right = face_patch(mesh, np.abs(cen[:, 0] - lx) < 1e-12, "right")
    area = ly * lz
    assert left.area == pytest.approx(area, rel=1e-12)
    cem = CEMSystem(mesh, [left, right], z)
    f = cem.solve(np.full(mesh.n_cells, 1 / rho), np.array([current, -current]))
    resistance = (f.U[0, 0] - f.U[1, 0]) / current
    assert resistance == pytest.approx(rho * lx / area + 2 * z / area, rel=1e-9)


def test_electrode_patches_match_disc_area(cuboid_forward):
    for p, e in zip(cuboid_forward.patches, cuboid_forward.geometry.electrodes):
        assert p.area == pytest.approx(np.pi * e.radius**2, rel=0.02), p.name
        assert p.n_triangles >= 12, p.name


def test_mesh_quality_bounded(cuboid_forward):
    m = cuboid_forward.mesh
    assert np.all(m.volumes > 0)
    assert m.quality.min() > 0.05
    assert m.volumes.sum() == pytest.approx(cuboid_forward.geometry.volume, rel=2e-3)


def test_reciprocity(cuboid_forward, cuboid_solution):
    V = cuboid_solution.voltages
    rows = cuboid_forward.pattern.rows
    where = {tuple(r): i for i, r in enumerate(rows)}
    err = max(abs(V[i] - V[where[(m, d)]]) for (d, m), i in where.items())
    assert err <= 1e-9 * np.abs(V).max()


def test_zero_net_current_and_applied_currents(cuboid_forward, cuboid_solution):
    f = cuboid_solution.fields
    cem = cuboid_forward.cem
    # current through each electrode from the contact law: I_l = (A_l U_l - int u) / z_l
    I = np.array([(p.area * f.U[l] - np.einsum("ki,kip->p", p.load, f.u[p.nodes])) / cem.z[l]
                  for l, p in enumerate(cuboid_forward.patches)])
    np.testing.assert_allclose(I.sum(axis=0), 0.0, atol=1e-12)
    np.testing.assert_allclose(I, cuboid_forward.drive_currents, atol=1e-9 * 8e-3 * 1e3)


def _any_voltage(pattern, U, a, b, m, n):
    """V of driving a->b and measuring m-n from the pair-drive potentials U (pairs, electrodes)."""
    pairs = [tuple(p) for p in pattern.pairs]
    sign, d = (1.0, pairs.index((a, b))) if (a, b) in pairs else (-1.0, pairs.index((b, a)))
    return sign * (U[d, m] - U[d, n])


@pytest.mark.parametrize("axis", [0, 1])
def test_mirror_symmetry_maps_reference_frame_onto_itself(cuboid_forward, cuboid_solution, axis):
    g = cuboid_forward.geometry
    c = g.electrode_centers()
    mirrored = c.copy()
    mirrored[:, axis] *= -1
    perm = np.array([np.argmin(np.linalg.norm(c - q, axis=1)) for q in mirrored])
    assert np.allclose(c[perm], mirrored)
    U = cuboid_solution.fields.U.T
    p = cuboid_forward.pattern
    V = cuboid_solution.voltages
    Vm = np.array([_any_voltage(p, U, perm[a], perm[b], perm[m], perm[n])
                   for (a, b), (m, n) in zip(p.drive, p.measure)])
    # The tetrahedral mesh is not symmetric (pytetwild meshes even differ from build to build): the
    # frame and its mirror image each carry the 4 mm discretisation error e, so they may differ by
    # up to 2 e. e is estimated here, not assumed: Richardson from the 4 and 3 mm frames with the
    # second order of P1 voltage functionals, e = |V4 - V3| / (1 - (3/4)^2). A wrong electrode map
    # or sign errs by ~|V| (0.05-0.1 V), far above the bound (~0.005-0.009 V).
    V3 = ForwardModel(g, build_mesh(g, MeshSpec(h=TRUTH_H))).voltages()
    e = np.abs(V - V3).max() / (1 - (TRUTH_H / MODEL_H) ** 2)
    assert np.abs(Vm - V).max() <= 2 * e, (np.abs(Vm - V).max(), e)
    assert 2 * e < 0.1 * np.abs(V).max()  # and the bound itself is tight


@pytest.mark.slow
def test_reference_frame_converges_with_mesh_size(cuboid):
    """Against a 2 mm reference (electrodes 0.4 mm), refining everything together (electrodes at
    h / 5): the error falls from 6 to 3 mm by at least 1.25x (measured 2.0-3.5x over four sets of
    meshes, 1.45x on a fresh CI machine), and the model's own 4 mm mesh (electrodes 0.6 mm, the
    shipped one every default model is built on) gives a frame within the stated 2.5 % (measured
    0.9 %; 1.4-1.7 % with electrodes at 0.8 mm). Adjacent sizes (6 vs 4 mm) are not compared:
    pytetwild meshes differ from build to build by about as much.

    Every mesh here is a shipped one (cstomo_sensor/data/meshes): the 3 and 4 mm ones the default sensor
    uses (MeshSpec's default electrodes: 0.6 mm, which is h / 5 at 3 mm), and the 2 and 6 mm ones of this
    check (before, built here: 50 and 26 s of pytetwild on a core; shipped: 6 mm 3.5x the 3 mm error, the
    4 mm 0.9 %)."""
    def frame(spec):
        return ForwardModel(cuboid, build_mesh(cuboid, spec)).voltages()

    best = frame(MeshSpec(h=2e-3, h_electrode=0.4e-3))
    err = {spec.h: np.linalg.norm(frame(spec) - best) / np.linalg.norm(best)
           for spec in (MeshSpec(h=6e-3, h_electrode=1.2e-3), MeshSpec(h=MODEL_H), MeshSpec(h=TRUTH_H))}
    assert MeshSpec(h=TRUTH_H).he == pytest.approx(TRUTH_H / 5)  # refined together: electrodes at h / 5
    assert err[TRUTH_H] < err[6e-3] / 1.25, err
    assert err[MODEL_H] < 0.025, err


def test_stale_cache_entry_is_rebuilt_not_used(tmp_path):
    path = tmp_path / "entry.npz"
    cache_save(path, "key-a", x=np.arange(3))
    assert cache_load(path, "key-b") is None
    np.testing.assert_array_equal(cache_load(path, "key-a")["x"], np.arange(3))
    path.write_bytes(b"not an npz")
    assert cache_load(path, "key-a") is None


def test_cache_key_changes_with_every_mesh_input(cuboid):
    from cstomo_sensor.cache import input_hash
    from cstomo_sensor.model.mesh import _mesh_inputs

    base = input_hash(_mesh_inputs(cuboid, MeshSpec(h=4e-3)))
    moved = cuboid.with_electrodes((cuboid.electrodes[0].__class__(
        "e1", (0.02, -0.0099, 0.005), (1.0, 0.0, 0.0), 0.0015),) + cuboid.electrodes[1:])
    assert input_hash(_mesh_inputs(moved, MeshSpec(h=4e-3))) != base
    assert input_hash(_mesh_inputs(cuboid, MeshSpec(h=4.1e-3))) != base
    assert input_hash(_mesh_inputs(cuboid, MeshSpec(h=4e-3, refine_socket=False))) != base


@pytest.mark.slow  # the sizing field on a 1 mm grid, four times (seconds)
def test_a_mesh_not_refined_at_the_electrodes_is_one_for_every_place_of_them(cuboid):
    """With h_electrode = h (the mechanics' meshes) the sizing field, the mesher's only input that reads the
    electrodes, does not depend on their places: the key leaves them out, so a device whose electrodes
    moved uses the body's shipped mechanics mesh; refined at them (h_electrode < h), it does and keys them."""
    from cstomo_sensor.cache import input_hash
    from cstomo_sensor.model.mesh import _mesh_inputs, _sizing_field

    moved = cuboid.with_electrodes((cuboid.electrodes[0].__class__(
        "e1", (0.02, -0.0099, 0.005), (1.0, 0.0, 0.0), 0.0015),) + cuboid.electrodes[1:])
    plain, refined = MeshSpec(h=4e-3, h_electrode=4e-3), MeshSpec(h=4e-3)
    assert np.array_equal(_sizing_field(moved, plain)[2], _sizing_field(cuboid, plain)[2])
    assert not np.array_equal(_sizing_field(moved, refined)[2], _sizing_field(cuboid, refined)[2])
    assert input_hash(_mesh_inputs(moved, plain)) == input_hash(_mesh_inputs(cuboid, plain))
    assert input_hash(_mesh_inputs(moved, refined)) != input_hash(_mesh_inputs(cuboid, refined))
    device_a = load_sensor(Path(__file__).resolve().parent.parent / "scenes/devices/cuboid_joint_device_a.yaml")
    assert build_mesh(device_a, plain).info.get("shipped") is True


@pytest.mark.slow
def test_meshing_leaves_nothing_in_the_working_directory(tmp_path, monkeypatch):
    """pytetwild (fTetWild) writes ``__tracked_surface.stl`` into its working directory: a mesh built
    from here (the disc at 5 mm: a few seconds, not shipped, an empty cache) leaves the directory
    it was started in empty, and the mesher's temporary directory is removed."""
    from cstomo_sensor.model.geometry import load_sensor

    cwd, tmp = tmp_path / "cwd", tmp_path / "tmp"
    cwd.mkdir()
    tmp.mkdir()
    monkeypatch.chdir(cwd)
    monkeypatch.setattr("tempfile.tempdir", str(tmp))
    mesh = build_mesh(load_sensor("disc"), MeshSpec(h=5e-3), tmp_path / "cache")
    assert mesh.info["cache_hit"] is False and mesh.n_cells > 1000
    assert list(cwd.iterdir()) == [] and list(tmp.iterdir()) == []


@pytest.mark.slow  # runs the mesher's child
@pytest.mark.parametrize("child,exc,match", [
    ("import sys; print('tetwild: boom', file=sys.stderr); sys.exit(5)", MeshError, "exit status 5.*boom"),
    ("import sys; sys.exit(3)", ModuleNotFoundError, "pytetwild"),
])
def test_a_failing_mesher_is_a_named_error(monkeypatch, child, exc, match):
    """The child process that runs pytetwild: a crash is a MeshError with its last words, a missing
    pytetwild a ModuleNotFoundError naming it (as the import in this process was)."""
    from cstomo_sensor.model import mesh as meshmod

    monkeypatch.setattr(meshmod, "_TETWILD_CHILD", child)
    with pytest.raises(exc, match=match) as info:
        meshmod._tetrahedralize(np.zeros((3, 3)), np.zeros((1, 3), np.int32), 1e-3, np.zeros((4, 3)),
                                np.zeros((1, 4), np.int32), np.ones(4))
    if exc is ModuleNotFoundError:
        assert info.value.name == "pytetwild"
