"""Sensor geometry files: presets as in docs/physics.md#geometry, and clear errors for bad input."""
import copy
import re

import numpy as np
import pytest
import yaml
from hypothesis import given, settings
from hypothesis import strategies as st

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


# --- complete validation of a sensor file (issue 14) -----------------------------------------------

@pytest.mark.parametrize("mutate,field", [
    (lambda d: d["socket"].__setitem__("radius", float("nan")), "socket.radius"),
    (lambda d: d["socket"].__setitem__("radius", float("inf")), "socket.radius"),
    (lambda d: d["electrodes"].__setitem__("layers", 2.7), "electrodes.layers"),
    (lambda d: d["electrodes"].__setitem__("layers", True), "electrodes.layers"),
    (lambda d: d["electrodes"].__setitem__("positions", d["electrodes"]["positions"][:8]), "16"),
    (lambda d: d["electrodes"].__setitem__("positions", d["electrodes"]["positions"][:12]), "16"),
    (lambda d: d.__setitem__("name", "../../etc/evil"), "name"),
    (lambda d: d.__setitem__("name", "a/b"), "name"),
    (lambda d: d.__setitem__("name", ""), "name"),
    (lambda d: d.__setitem__("name", 7), "name"),
    (lambda d: d.__setitem__("drive_current", "lots"), "drive_current"),
    (lambda d: d.__setitem__("drive_current", [1]), "drive_current"),
    (lambda d: d.__setitem__("contact_impedance", float("nan")), "contact_impedance"),
    (lambda d: d["body"].__setitem__("size", [0.04, 0.04]), "body.size"),
    (lambda d: d["body"].__setitem__("size", 0.04), "body.size"),
    (lambda d: d["body"].__setitem__("shape", ["cuboid"]), "body.shape"),
    (lambda d: d["electrodes"]["positions"][3].__setitem__(2, None), r"electrodes.positions[3]"),
    (lambda d: d["electrodes"]["positions"].__setitem__(3, [0.01, 0.02]), r"electrodes.positions[3]"),
    (lambda d: d["material"].__setitem__("nu", float("nan")), "material.nu"),
    (lambda d: d["material"].__setitem__("E", "soft"), "material.E"),
    (lambda d: d.__setitem__("material", [1, 2]), "material"),
    (lambda d: d.__setitem__("socket", 3), "socket"),
    (lambda d: d.__setitem__("electrodes", None), "electrodes"),
    (lambda d: d.__setitem__("socekt", {"radius": 0.006}), "socekt"),
])
def test_every_value_of_a_sensor_file_is_checked_and_named(cuboid_dict, mutate, field):
    d = copy.deepcopy(cuboid_dict)
    mutate(d)
    with pytest.raises(ConfigError, match=re.escape(field)):
        sensor_from_dict(d)


def test_a_sensor_file_that_is_not_yaml_or_not_utf8_is_named(tmp_path):
    for text in (b"name: [unclosed\n", b"\xff\xfe\x00binary", b"- a list\n- not a mapping\n", b""):
        f = tmp_path / "s.yaml"
        f.write_bytes(text)
        with pytest.raises(ConfigError, match=re.escape(str(f))):
            load_sensor(f)


def test_an_unsafe_preset_name_is_not_looked_up_outside_the_preset_folders():
    with pytest.raises(ConfigError, match="cuboid_joint"):
        load_sensor("../sensors/cuboid_joint")


_leaf = st.one_of(st.none(), st.booleans(), st.integers(-10**30, 10**30), st.floats(allow_nan=True, allow_infinity=True),
                  st.text(max_size=20), st.just([]), st.just({}))
_value = st.recursive(_leaf, lambda c: st.one_of(st.lists(c, max_size=4), st.dictionaries(st.text(max_size=8), c, max_size=3)),
                      max_leaves=8)


def _paths(d, prefix=()):
    if isinstance(d, dict):
        for k, v in d.items():
            yield prefix + (k,)
            yield from _paths(v, prefix + (k,))
    elif isinstance(d, list):
        for i, v in enumerate(d):
            yield prefix + (i,)
            yield from _paths(v, prefix + (i,))


@pytest.mark.slow  # seconds of computation
@settings(max_examples=200, deadline=None)
@given(data=st.data())
def test_fuzz_mutated_sensor_dicts_raise_only_package_errors(data):
    from cstomo_sensor.errors import CstomoError

    path = next(d / "cuboid_joint.yaml" for d in preset_dirs() if (d / "cuboid_joint.yaml").is_file())
    d = yaml.safe_load(path.read_text())
    for _ in range(data.draw(st.integers(1, 3))):
        paths = list(_paths(d))
        p = data.draw(st.sampled_from(paths))
        parent = d
        for k in p[:-1]:
            parent = parent[k]
        if data.draw(st.booleans()) and isinstance(parent, dict):
            del parent[p[-1]]
        else:
            parent[p[-1]] = data.draw(_value)
    try:
        sensor_from_dict(d)
    except CstomoError:
        pass


_PRESET_TEXTS = [p.read_bytes() for d in preset_dirs() if d.is_dir() for p in sorted(d.glob("*.yaml"))][:3]


@pytest.mark.slow  # seconds of computation
@settings(max_examples=300, deadline=None)
@given(raw=st.one_of(st.binary(max_size=200), st.text(max_size=200).map(lambda t: t.encode("utf-8", "surrogatepass")),
                     st.builds(lambda base, cut, extra: base[:cut] + extra.encode("utf-8", "surrogatepass"),
                               st.sampled_from(_PRESET_TEXTS), st.integers(0, 2000), st.text(max_size=40))))
def test_fuzz_random_yaml_text_raises_only_package_errors(tmp_path_factory, raw):
    from cstomo_sensor.errors import CstomoError

    f = tmp_path_factory.getbasetemp() / "fuzz_sensor.yaml"
    f.write_bytes(raw)
    try:
        load_sensor(f)
    except CstomoError:
        pass


# --- the schema: required keys, defaults (issue 19) -------------------------------------------------

@pytest.mark.parametrize("key", ["tau", "E"])
def test_a_missing_material_key_is_logged_with_the_value_used(cuboid_dict, caplog, key):
    from cstomo_sensor.model.material import Material

    d = copy.deepcopy(cuboid_dict)
    del d["material"][key]
    with caplog.at_level("WARNING", logger="cstomo_sensor.model.geometry"):
        g = sensor_from_dict(d, source="s.yaml")
    nominal = getattr(Material(), key)
    assert getattr(g.material, key) == nominal
    warned = [r.getMessage() for r in caplog.records if r.levelname == "WARNING"]
    assert len(warned) == 1 and "s.yaml" in warned[0] and f"material.{key} = {nominal:g}" in warned[0], warned
    assert "material.nu" not in warned[0]  # only the missing key is named


def test_a_complete_sensor_file_logs_nothing(cuboid_dict, caplog):
    with caplog.at_level("DEBUG", logger="cstomo_sensor.model.geometry"):
        sensor_from_dict(copy.deepcopy(cuboid_dict))
    assert not caplog.records


@pytest.mark.parametrize("where,key", [("", "materials"), ("material", "rho"), ("body", "radius"),
                                       ("electrodes", "count"), ("socket", "depth")])
def test_an_unknown_key_is_refused_naming_it(cuboid_dict, where, key):
    d = copy.deepcopy(cuboid_dict)
    (d[where] if where else d)[key] = 1.0
    with pytest.raises(ConfigError, match=f"unknown keys \\['{key}'\\] in {where or 'the top level'}"):
        sensor_from_dict(d)


def test_the_schema_names_every_key_of_the_full_preset_and_the_required_ones_are_required(cuboid_dict):
    from cstomo_sensor.model.geometry import REQUIRED, SENSOR_SCHEMA

    assert set(SENSOR_SCHEMA) == set(cuboid_dict)
    for top, spec in SENSOR_SCHEMA.items():
        if isinstance(spec, dict):
            assert set(spec) == set(cuboid_dict[top]), top
        subkeys = spec.items() if isinstance(spec, dict) else [(None, spec)]
        for sub, default in subkeys:
            if default is not REQUIRED:
                continue
            d = copy.deepcopy(cuboid_dict)
            (d[top] if sub else d).pop(sub or top)
            with pytest.raises(ConfigError, match=re.escape(f"missing key '{top + '.' + sub if sub else top}'")):
                sensor_from_dict(d)
