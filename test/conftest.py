"""Shared fixtures: one on-disk cache per checkout (empty on a fresh machine), expensive models
built once per run, DDS kept on this host."""
import os
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
os.environ.setdefault("CSTOMO_CACHE_DIR", str(ROOT / ".cache" / "test"))
os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
os.environ.setdefault("ROS_DOMAIN_ID", str(100 + os.getpid() % 100))

# Mesh sizes of the test suite (metres): the model that reconstructs, and an independent finer
# mesh that simulates the truth (REFERENCE_SENSOR.md section 7).
MODEL_H = 4.0e-3
TRUTH_H = 3.0e-3


@pytest.fixture(scope="session")
def cuboid():
    from cstomo_sensor.geometry import load_sensor

    return load_sensor("cuboid_joint")


@pytest.fixture(scope="session")
def cuboid_forward(cuboid):
    from cstomo_sensor.fem import ForwardModel
    from cstomo_sensor.mesh import MeshSpec, build_mesh

    return ForwardModel(cuboid, build_mesh(cuboid, MeshSpec(h=MODEL_H)))


@pytest.fixture(scope="session")
def cuboid_solution(cuboid_forward):
    return cuboid_forward.solve()


@pytest.fixture(scope="session")
def cuboid_model(cuboid):
    """The default reconstruction model (h = 4 mm, 8 x 8 x 4 voxels, k by the discrepancy rule)."""
    from cstomo_sensor.reconstruction import ReconSpec, build_model

    return build_model(cuboid, ReconSpec(mesh_size=MODEL_H))


@pytest.fixture(scope="session")
def cuboid_truth(cuboid):
    """The honestly simulated device: independent finer mesh, mismatched electrodes (seed 3)."""
    from cstomo_sensor.simulate import Truth

    return Truth(cuboid, truth_h=TRUTH_H, seed=3)
