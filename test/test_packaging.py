"""What a robot install needs is declared where rosdep and a reader find it: package.xml's keys,
README's pip line for what has no key, and the start-up error's install command (one mapping,
cstomo_sensor/errors.py OPTIONAL_MODULES)."""
from __future__ import annotations

import ast
import os
import re
import sys
import xml.etree.ElementTree as ET
from pathlib import Path

import pytest

from cstomo_sensor.errors import OPTIONAL_MODULES, install_hint

ROOT = Path(__file__).resolve().parent.parent
#: rosdep keys of ros/rosdistro rosdep/python.yaml, checked there by hand (issue 21): the pip keys of
#: the optional modules; scikit-fem and pytetwild have none.
ROSDISTRO_PIP_KEYS = {"python3-pyvista-pip", "python3-rosbags-pip"}


def _depends(kind: str) -> set[str]:
    return {e.text.strip() for e in ET.parse(ROOT / "package.xml").getroot().iter(kind)}


def _full_extra() -> list[str]:
    tree = ast.parse((ROOT / "setup.py").read_text())
    for node in ast.walk(tree):
        if isinstance(node, ast.keyword) and node.arg == "extras_require":
            return ast.literal_eval(node.value)["full"]
    raise AssertionError("no extras_require in setup.py")


def test_every_module_of_the_full_extra_has_its_key_in_package_xml_or_is_on_the_readme_pip_line():
    deps = _depends("exec_depend")
    by_pip = {pip: key for pip, key in OPTIONAL_MODULES.values()}
    readme = (ROOT / "README.md").read_text()
    pip_line = next(ln for ln in readme.splitlines() if "pip install --user" in ln)
    for pip_name in _full_extra():
        assert pip_name in by_pip, f"{pip_name}: not in errors.OPTIONAL_MODULES"
        key = by_pip[pip_name]
        if key:
            assert key in deps, f"{pip_name}: rosdep key {key} missing from package.xml"
            assert not re.search(rf"\b{re.escape(pip_name)}\b", pip_line), f"{pip_name} has a key: not on {pip_line}"
        else:
            assert re.search(rf"\b{re.escape(pip_name)}\b", pip_line), f"{pip_name}: not on README's pip line {pip_line}"
    assert ROSDISTRO_PIP_KEYS <= deps
    assert {k for _, k in OPTIONAL_MODULES.values() if k and k.endswith("-pip")} <= ROSDISTRO_PIP_KEYS


@pytest.mark.slow  # starts a process
@pytest.mark.parametrize("module, pip_name", [("skfem", "scikit-fem"), ("skfem.helpers", "scikit-fem"),
                                              ("pytetwild", "pytetwild")])
def test_the_install_command_names_the_pip_package_of_the_module(monkeypatch, module, pip_name):
    monkeypatch.setattr(sys, "prefix", sys.base_prefix)  # a system Python: a colcon install
    hint = install_hint(module)
    assert f"python3 -m pip install --user --break-system-packages {pip_name}" in hint, hint
    assert "cstomo_sensor[full]" not in hint and "rosdep" in hint and "no rosdep key" in hint
    monkeypatch.setattr(sys, "prefix", "/some/venv")  # a virtual environment: its own pip
    hint = install_hint(module)
    assert hint.endswith(f"{sys.executable} -m pip install {pip_name}") and "--user" not in hint, hint


def test_a_module_with_a_rosdep_key_is_named_with_it(monkeypatch):
    monkeypatch.setattr(sys, "prefix", sys.base_prefix)
    hint = install_hint("rosbags.rosbag2")
    assert "python3-rosbags-pip" in hint and "pip install --user --break-system-packages rosbags" in hint, hint


def test_the_nodes_start_up_error_names_the_command():
    pytest.importorskip("rclpy")
    from cstomo_sensor.ros.node import failure_cause

    err = ModuleNotFoundError("No module named 'skfem'", name="skfem")
    msg = failure_cause(err)
    assert "'skfem'" in msg and "scikit-fem" in msg and "pip install" in msg and "cstomo_sensor[full]" not in msg, msg


def setup_keywords() -> dict:
    """The keywords setup.py hands to ``setup`` (run with ``setup`` captured, in the repository root
    as a build runs it)."""
    import runpy

    import setuptools

    got = {}
    cwd = os.getcwd()
    original = setuptools.setup
    try:
        os.chdir(ROOT)
        setuptools.setup = lambda **kw: got.update(kw)
        runpy.run_path(str(ROOT / "setup.py"))
    finally:
        setuptools.setup = original
        os.chdir(cwd)
    return got


def installed_files() -> dict[str, Path]:
    """install path (``share/cstomo_sensor/...``) -> source file, from setup.py's ``data_files``."""
    return {f"{dest}/{Path(src).name}": ROOT / src for dest, sources in setup_keywords()["data_files"] for src in sources}


def scene_references(scene: Path) -> list[str]:
    """The files a scene names by a relative path (resolved from the scene's folder): its sensor file
    and its timeline's load script."""
    import yaml

    doc = yaml.safe_load(scene.read_text())
    refs = [doc.get("sensor", ""), (doc.get("timeline") or {}).get("load_script", "")]
    return [str(r) for r in refs if r and Path(str(r)).suffix and not Path(str(r)).is_absolute()]


def test_every_scene_and_what_it_refers_to_is_installed():
    from cstomo_sensor.model.geometry import preset_names

    files = installed_files()
    share = "share/cstomo_sensor"
    scenes = sorted(ROOT.glob("scenes/**/*.yaml"))
    assert scenes and all(f"{share}/{s.relative_to(ROOT)}" in files for s in scenes), sorted(files)
    presets = {Path(k).stem for k in files if k.startswith(f"{share}/config/sensors/")}
    assert presets == set(preset_names()), presets
    for key, src in files.items():
        if not key.startswith(f"{share}/scenes/"):
            continue
        for ref in scene_references(src):
            target = os.path.normpath(str(Path(key).parent / ref))
            assert target in files, f"{key} refers to {ref}: {target} is not installed"
    assert any(scene_references(s) for s in scenes)  # the check checks something: device_a names its device
