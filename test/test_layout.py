"""The house rules: the layers' import contract, no cycles, no heavy import in the core, one source of
truth for the settings, and the lint.

Layers (README.md, "What is where"): the core (``model``, ``inverse``, ``force``, ``frame_path``, ``board`` and the top-level helpers)
never imports ``ros`` or ``tools``; ``ros`` never imports ``tools``. Imports are read as text (module
level and inside functions), so a function-level import cannot hide a crossing.
"""
from __future__ import annotations

import ast
import json
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
PKG = ROOT / "cstomo_sensor"
EDGE = ("ros", "tools")
ROS_PACKAGES = {"rclpy", "rcl_interfaces", "std_msgs", "geometry_msgs", "sensor_msgs", "std_srvs", "diagnostic_msgs",
                "builtin_interfaces", "lifecycle_msgs", "launch", "launch_ros"}


def _modules() -> dict[str, Path]:
    out = {}
    for p in PKG.rglob("*.py"):
        parts = p.relative_to(ROOT).with_suffix("").parts
        name = ".".join(parts[:-1] if parts[-1] == "__init__" else parts)
        out[name] = p
    return out


MODULES = _modules()


def _imports(name: str, path: Path) -> tuple[set[str], set[str]]:
    """(package modules, external top-level packages) that module ``name`` imports anywhere."""
    pkg = name.split(".") if path.name == "__init__.py" else name.split(".")[:-1]
    inner, outer = set(), set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            targets = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = ".".join(pkg[: len(pkg) - node.level + 1] + ([node.module] if node.module else [])) if node.level \
                else node.module
            targets = [f"{base}.{a.name}" for a in node.names] + [base]
        else:
            continue
        for t in targets:
            if t.split(".")[0] != "cstomo_sensor":
                outer.add(t.split(".")[0])
                continue
            while t not in MODULES and "." in t:
                t = t.rsplit(".", 1)[0]
            if t in MODULES and t != name and not name.startswith(t + "."):
                inner.add(t)
    return inner, outer


GRAPH = {m: _imports(m, p) for m, p in MODULES.items()}


def layer(module: str) -> str:
    parts = module.split(".")
    return parts[1] if len(parts) > 2 else "(top)"


def test_the_graph_is_read():
    # guards the checks below against an empty or misread graph
    assert {"model", "inverse", "force", "board", "ros", "tools"} <= {layer(m) for m in MODULES}
    assert "cstomo_sensor.frame_path.pipeline" in GRAPH["cstomo_sensor.ros.node"][0]
    assert "rclpy" in GRAPH["cstomo_sensor.ros.node"][1]


def test_the_core_never_imports_ros_or_tools_and_ros_never_imports_tools():
    wrong = [f"{m} -> {t}" for m, (inner, _) in GRAPH.items() for t in inner
             if (layer(m) not in EDGE and layer(t) in EDGE) or (layer(m) == "ros" and layer(t) == "tools")]
    assert not wrong, wrong


def test_the_core_never_imports_a_ros_package():
    wrong = [f"{m} -> {sorted(outer & ROS_PACKAGES)}" for m, (_, outer) in GRAPH.items()
             if layer(m) not in EDGE and outer & ROS_PACKAGES]
    assert not wrong, wrong


def test_no_import_cycles():
    index, low, stack, on, cycles = {}, {}, [], set(), []

    def visit(v):
        index[v] = low[v] = len(index)
        stack.append(v)
        on.add(v)
        for w in GRAPH[v][0]:
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                cycles.append(sorted(comp))

    for v in GRAPH:
        if v not in index:
            visit(v)
    assert not cycles, cycles


def test_pyserial_is_imported_only_by_the_driver_and_its_url_handler():
    """``serial`` (pyserial) stays in board/driver.py and the ``virtual://`` handler it registers."""
    users = sorted(m for m, (_, outer) in GRAPH.items() if "serial" in outer)
    assert users == ["cstomo_sensor.board.driver", "cstomo_sensor.board.protocol_virtual"], users


@pytest.mark.slow  # starts a process
def test_core_modules_load_no_heavy_or_ros_package_at_import():
    """Importing every core module loads neither rclpy nor pyvista, pytetwild or scikit-fem (they
    load only in the code that meshes, renders, solves elasticity or runs the node)."""
    core = sorted(m for m in MODULES if layer(m) not in EDGE)
    code = ("import importlib, json, sys\n"
            f"for m in {core!r}:\n    importlib.import_module(m)\n"
            "print(json.dumps(sorted(k for k in sys.modules if k.split('.')[0] in "
            "('rclpy', 'pyvista', 'pytetwild', 'skfem', 'pyamg', 'vtk', 'matplotlib'))))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT, check=True)
    assert json.loads(out.stdout) == [], out.stdout


def test_cli_flags_take_their_defaults_and_choices_from_the_config():
    from cstomo_sensor.frame_path.config import PipelineConfig
    from cstomo_sensor.settings import ESTIMATORS
    from cstomo_sensor.tools import cli

    d = PipelineConfig()
    for parser in (cli.subcommand_parser(["estimate"])[0], cli.subcommand_parser(["replay"])[0]):
        args = parser.parse_args(["x", "--out", "o"] if parser.prog.endswith("replay") else
                                 ["--reference", "r", "--frames", "f", "--out", "o"])
        for k in ("sensor", "mesh_size", "iterations", "damping", "cache_dir", "estimator"):
            assert getattr(args, k) == getattr(d, k), k
        assert tuple(args.grid) == d.grid
        est = next(a for a in parser._actions if a.dest == "estimator")
        assert tuple(est.choices) == ESTIMATORS


def test_node_parameter_defaults_are_the_config_defaults():
    pytest.importorskip("rclpy")
    from cstomo_sensor.frame_path.config import PipelineConfig
    from cstomo_sensor.ros.params import PARAMETERS, NodeConfig
    from cstomo_sensor.settings import PROTOCOLS

    cfg = NodeConfig.from_parameters(lambda n: PARAMETERS[n][0])
    assert cfg.pipeline == PipelineConfig()
    assert cfg == NodeConfig(pipeline=PipelineConfig())
    assert cfg.protocol == PROTOCOLS[0]


@pytest.mark.slow  # starts a process
def test_ruff_finds_nothing():
    out = subprocess.run([sys.executable, "-m", "ruff", "check", "--no-cache", "."], capture_output=True, text=True,
                         cwd=ROOT)
    assert out.returncode == 0, out.stdout + out.stderr


def test_the_default_sensor_is_named_only_where_it_is_defined():
    """``DEFAULT_SENSOR`` (settings.py) is the one place the default sensor's name is written
    in code; every other module imports it (docstrings and comments may name it)."""
    from cstomo_sensor.settings import DEFAULT_SENSOR

    wrong = [f"{m}:{n.lineno}" for m, p in MODULES.items() if m != "cstomo_sensor.settings"
             for n in ast.walk(ast.parse(p.read_text())) if isinstance(n, ast.Constant) and n.value == DEFAULT_SENSOR]
    assert not wrong, wrong
