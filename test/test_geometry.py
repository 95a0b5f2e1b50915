"""Sensor geometry files: presets as in REFERENCE_SENSOR.md, and clear errors for bad input."""
import copy

import numpy as np
import pytest
import yaml

from cstomo_sensor.errors import ConfigError
from cstomo_sensor.model.geometry import load_sensor, preset_dirs, sensor_from_dict


@pytest.fixture()
def cuboid_dict():
    path = next(d / "cuboid_joint.yaml" for d in preset_dirs() if (d / "cuboid_joint.yaml").is_file())
    return yaml.safe_load(path.read_text())


def test_presets_match_reference():
    c = load_sensor("cuboid_joint")
    assert c.size == (0.04, 0.04, 0.02) and c.socket_radius == 0.006 and c.layers == 2
    e = c.electrode_centers() * 1e3
    np.testing.assert_allclose(e[:8, :2], [(20, -10), (20, 10), (10, 20), (-10, 20), (-20, 10), (-20, -10),
                                          (-10, -20), (10, -20)])
    np.testing.assert_allclose(e[8:, :2], e[:8, :2])
    assert np.all(e[:8, 2] == 5) and np.all(e[8:, 2] == 15)
    assert c.material.rho0 == pytest.approx(0.361, rel=1e-12)
    d = load_sensor("disc")
    ang = np.degrees(np.arctan2(d.electrode_centers()[:, 1], d.electrode_centers()[:, 0])) % 360
    np.testing.assert_allclose(ang, 22.5 * np.arange(16), atol=1e-9)
    cyl = load_sensor("cylinder")
    assert cyl.layers == 2 and cyl.size == (0.02, 0.02)


def test_user_yaml_file_defines_a_new_sensor(tmp_path, cuboid_dict):
    d = copy.deepcopy(cuboid_dict)
    d["name"] = "bigger"
    d["body"]["size"] = [0.05, 0.05, 0.02]
    d["socket"]["radius"] = 0.008
    d["electrodes"]["positions"] = [[p[0] * 1.25, p[1] * 1.25, p[2]] for p in d["electrodes"]["positions"]]
    f = tmp_path / "bigger.yaml"
    f.write_text(yaml.safe_dump(d))
    g = load_sensor(f)
    assert g.name == "bigger" and g.socket_radius == 0.008


@pytest.mark.parametrize("mutate,field", [
    (lambda d: d.pop("drive_current"), "drive_current"),
    (lambda d: d["electrodes"].pop("radius"), "electrodes.radius"),
    (lambda d: d["electrodes"]["positions"][0].__setitem__(0, 0.019), "e1"),
    (lambda d: d["electrodes"]["positions"][1].__setitem__(1, -0.009), "overlap"),
    (lambda d: d["material"].__setitem__("rho_h", -1.0), "material.rho_h"),
    (lambda d: d["material"].__setitem__("rho_h", 0.0), "material.rho_h"),
    (lambda d: d.__setitem__("contact_impedance", 0.0), "contact_impedance"),
    (lambda d: d["body"].__setitem__("shape", "sphere"), "body.shape"),
])
def test_bad_geometry_names_the_field(cuboid_dict, mutate, field):
    d = copy.deepcopy(cuboid_dict)
    mutate(d)
    with pytest.raises(ConfigError, match=field.replace(".", r"\.")):
        sensor_from_dict(d)


def test_unknown_preset_lists_the_valid_ones():
    with pytest.raises(ConfigError, match="cuboid_joint"):
        load_sensor("no_such_sensor")
