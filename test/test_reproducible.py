"""Reproducible models: the default sensor's shipped meshes, and two builds from nothing equal to rounding.

pytetwild gives a slightly different mesh on every run, so the default model's meshes ship with the
package (model/mesh.py). Expected values here are the shipped files' own bytes and a second,
independent build in another process (other BLAS thread count), never numbers of the build under test.
"""
import json
import os
import shutil
import subprocess
import sys

import numpy as np
import pytest

from cstomo_sensor.force.estimators.training import CalibrationSpec, calibration_set
from cstomo_sensor.inverse.reconstruction import ReconSpec, build_model
from cstomo_sensor.model import mesh as meshmod
from cstomo_sensor.model.mesh import MeshSpec, build_mesh
from cstomo_sensor.model.simulate import MECHANICS_MESH_SIZE, TRUTH_MESH_SIZE

#: The meshes the default model, its calibration and the default simulated device need.
DEFAULT_SPECS = [MeshSpec(h=ReconSpec.mesh_size), MeshSpec(h=CalibrationSpec.mechanics_mesh_size,
                                                              h_electrode=CalibrationSpec.mechanics_mesh_size),
                 MeshSpec(h=TRUTH_MESH_SIZE), MeshSpec(h=MECHANICS_MESH_SIZE, h_electrode=MECHANICS_MESH_SIZE)]

BUILD = """
import json, sys, numpy as np
from cstomo_sensor.model.geometry import load_sensor
from cstomo_sensor.inverse.reconstruction import ReconSpec, build_model
from cstomo_sensor.force.estimators.training import CalibrationSpec, calibration_set
g = load_sensor("cuboid_joint")
m = build_model(g, ReconSpec(), sys.argv[1])
f, y = calibration_set(g, m, CalibrationSpec(), sys.argv[1])
np.savez(sys.argv[2], forces=f, y=y, k=m.iterations, **m.arrays())
"""


@pytest.mark.parametrize("spec", DEFAULT_SPECS, ids=lambda s: f"h{s.h * 1e3:g}he{s.he * 1e3:g}")
def test_the_default_meshes_ship_and_are_used(cuboid, tmp_path, spec):
    mesh = build_mesh(cuboid, spec, tmp_path)
    assert mesh.info.get("shipped") is True
    path = meshmod.SHIPPED_DIR / f"cuboid-{mesh.info['key']}.npz"
    with np.load(path) as z:
        assert str(z["cache_key"]) == mesh.info["key"]
        assert np.array_equal(z["points"], mesh.points) and np.array_equal(z["tets"], mesh.tets)
    assert not (tmp_path / "meshes").exists()  # nothing meshed, nothing cached
    assert sum(p.stat().st_size for p in meshmod.SHIPPED_DIR.glob("*.npz")) < 3e6


def test_a_shipped_mesh_for_other_inputs_is_not_used(cuboid, tmp_path, monkeypatch):
    """A file under a shipped name whose key belongs to other inputs is ignored: the cache's entry
    for these inputs is used instead (no meshing here: the cache holds one)."""
    four, _ = meshmod._shipped(cuboid, meshmod._mesh_inputs_base(cuboid, DEFAULT_SPECS[0]))
    six, _ = meshmod._shipped(cuboid, meshmod._mesh_inputs_base(cuboid, DEFAULT_SPECS[1]))
    shipped = tmp_path / "shipped"
    shipped.mkdir()
    monkeypatch.setattr(meshmod, "SHIPPED_DIR", shipped)
    spec = MeshSpec(h=5e-3)
    name, _ = meshmod._shipped(cuboid, meshmod._mesh_inputs_base(cuboid, spec))
    shutil.copy(four, name)  # the 4 mm mesh under the 5 mm mesh's shipped name
    key = meshmod.input_hash(meshmod._mesh_inputs(cuboid, spec))
    with np.load(six) as z:  # a cache entry for the 5 mm inputs: the 6 mm mesh's arrays
        points, tets = z["points"], z["tets"].astype(np.int64)
    meshmod.cache_save(tmp_path / "meshes" / f"cuboid-{key}.npz", key, points=points, tets=tets)
    got = build_mesh(cuboid, spec, tmp_path)
    assert not got.info.get("shipped") and got.info["key"] == key
    assert np.array_equal(got.points, points)


@pytest.mark.slow  # starts a process
def test_the_default_meshes_need_no_pytetwild(tmp_path):
    code = ("import sys; sys.modules['pytetwild'] = None\n"
            "from cstomo_sensor.model.geometry import load_sensor\n"
            "from cstomo_sensor.model.mesh import MeshSpec, build_mesh\n"
            f"m = build_mesh(load_sensor('cuboid_joint'), MeshSpec(h=4e-3), {str(tmp_path)!r})\n"
            "assert m.info['shipped']\n")
    subprocess.run([sys.executable, "-c", code], check=True)


@pytest.mark.slow
def test_two_cold_builds_of_the_default_model_are_bit_identical(cuboid, cuboid_model, tmp_path):
    """Model (R, S, reference, k) and calibration set, built from nothing twice: the suite's own (its cache
    holds them, built in this run on a fresh clone by the first test that needed the default model:
    ``cuboid_model``, and the calibration every default pipeline uses) and one from an empty cache in another
    process with another BLAS thread count: equal to rounding (tolerances scaled to each array; BLAS kernels
    and thread counts may round otherwise, and a calibration keys the model to 6 digits). The suite's build
    serves here rather than a third one: two independent builds are what the comparison needs."""
    b_dir = tmp_path / "b"
    model = cuboid_model
    assert model.key == build_model(cuboid, ReconSpec()).key  # the default model (conftest's MODEL_H is its mesh)
    forces, y = calibration_set(cuboid, model, CalibrationSpec())
    env = dict(os.environ, OPENBLAS_NUM_THREADS="2", OMP_NUM_THREADS="2")
    subprocess.run([sys.executable, "-c", BUILD, str(b_dir), str(tmp_path / "b.npz")], check=True, env=env)
    with np.load(tmp_path / "b.npz") as b:
        assert int(b["k"]) == model.iterations
        for name, a in model.arrays().items():
            np.testing.assert_allclose(b[name], a, rtol=1e-9, atol=1e-12 * np.abs(a).max(), err_msg=name)
        np.testing.assert_allclose(b["forces"], forces, rtol=1e-12)
        np.testing.assert_allclose(b["y"], y, rtol=1e-9, atol=1e-12 * np.abs(y).max())
    assert json.dumps(model.meta["mesh"]) == json.dumps(build_model(cuboid, ReconSpec(), b_dir).meta["mesh"])
