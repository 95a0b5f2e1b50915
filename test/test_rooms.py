"""The rooms (docs/design.md, *What is where*): the sub-packages of a folder import each other one way
only (force/: estimators <- checks <- slow_states <- reference; the frame path above them), and each room says
what it holds in its __init__ docstring. Imports are read as text, module level and inside functions."""
from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
PKG = ROOT / "cstomo_sensor"


def _modules() -> dict[str, Path]:
    out = {}
    for p in PKG.rglob("*.py"):
        parts = p.relative_to(ROOT).with_suffix("").parts
        out[".".join(parts[:-1] if parts[-1] == "__init__" else parts)] = p
    return out


MODULES = _modules()
PACKAGES = {m for m, p in MODULES.items() if p.name == "__init__.py"}


def _targets(name: str, path: Path) -> set[str]:
    pkg = name.split(".") if path.name == "__init__.py" else name.split(".")[:-1]
    out = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom):
            base = ".".join(pkg[: len(pkg) - node.level + 1] + ([node.module] if node.module else [])) if node.level \
                else node.module
            targets = [f"{base}.{a.name}" for a in node.names]
        elif isinstance(node, ast.Import):
            targets = [a.name for a in node.names]
        else:
            continue
        for t in targets:
            while t not in MODULES and "." in t:
                t = t.rsplit(".", 1)[0]
            if t in MODULES and t != name:
                out.add(t)
    return out


def room_edges() -> dict[tuple[str, str], list[str]]:
    """(room, room) -> the imports from the one to the other, for every two rooms (sub-packages) of one folder."""
    edges = {}
    for m, p in MODULES.items():
        for t in _targets(m, p):
            a, b = m.split("."), t.split(".")
            i = 0
            while i < min(len(a), len(b)) and a[i] == b[i]:
                i += 1
            ra, rb = ".".join(a[: i + 1]), ".".join(b[: i + 1])
            if i < len(a) and i < len(b) and ra in PACKAGES and rb in PACKAGES:
                edges.setdefault((ra, rb), []).append(f"{m} -> {t}")
    return edges


def loops(edges) -> list[str]:
    graph = {}
    for a, b in edges:
        graph.setdefault(a, set()).add(b)

    def reach(a):
        seen, todo = set(), [a]
        while todo:
            for b in graph.get(todo.pop(), ()):
                if b not in seen:
                    seen.add(b)
                    todo.append(b)
        return seen

    return sorted({f"{a} <-> {b}: {edges[(a, b)][:2]}" for a, b in edges if a in reach(b)})


def test_the_rooms_are_read():
    rooms = {r for pair in room_edges() for r in pair}
    assert {"cstomo_sensor.force.estimators", "cstomo_sensor.force.checks", "cstomo_sensor.force.slow_states",
            "cstomo_sensor.force.reference"} <= rooms, sorted(rooms)
    assert loops({("a", "b"): ["a -> b"], ("b", "c"): ["b -> c"], ("c", "a"): ["c -> a"]})  # the check can fail


def test_rooms_import_each_other_one_way():
    found = loops(room_edges())
    assert not found, found


def test_every_room_says_what_it_holds():
    silent = [m for m in PACKAGES if not ast.get_docstring(ast.parse(MODULES[m].read_text()))]
    assert not silent, silent
