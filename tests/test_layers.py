"""The package's import graph: no circle, and no module imports a layer above its own.

Read from the source with ``ast`` (nothing is imported): every ``import`` of a ``lerobot_cso`` module counts, at
module level, inside functions and under ``TYPE_CHECKING`` alike, so a circle cannot hide behind a lazy import.
"""

from __future__ import annotations

import ast
from pathlib import Path

import lerobot_cso

ROOT = Path(lerobot_cso.__file__).parent
# Lowest first: a module may import its own layer and those below it only. A module's layer is that of the longest
# prefix listed here.
LAYERS: tuple[tuple[str, ...], ...] = (
    ("lerobot_cso", "lerobot_cso.errors", "lerobot_cso.seeds", "lerobot_cso.stage", "lerobot_cso.frames"),
    ("lerobot_cso.durable", "lerobot_cso.sampling"),
    ("lerobot_cso.policy",),
    ("lerobot_cso.checkpoints", "lerobot_cso.cso.objectives", "lerobot_cso.untrained"),
    ("lerobot_cso.rollout",),  # the rollout machinery: engine, backend, pool; no world, no stage
    ("lerobot_cso.worlds",),
    ("lerobot_cso.distributed", "lerobot_cso.records"),
    ("lerobot_cso.rollout_stage",),
    ("lerobot_cso.evaluation", "lerobot_cso.demos", "lerobot_cso.il", "lerobot_cso.train", "lerobot_cso.cso"),
    ("lerobot_cso.pipeline",),
    ("lerobot_cso.cli",),
)


def module_name(path: Path) -> str:
    parts = path.relative_to(ROOT.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def modules() -> dict[str, Path]:
    return {module_name(p): p for p in sorted(ROOT.rglob("*.py"))}


def imports(path: Path, known: set[str]) -> set[str]:
    """The package's modules that ``path`` imports anywhere in its body (``from a import b`` counts ``a.b`` when
    that is a module, else ``a``)."""
    found = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            found |= {alias.name for alias in node.names}
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            found |= {
                f"{node.module}.{a.name}" if f"{node.module}.{a.name}" in known else node.module for a in node.names
            }
    return {name for name in found if name in known}


def layer(name: str) -> int:
    best = max((p for layer in LAYERS for p in layer if name == p or name.startswith(p + ".")), key=len)
    return next(i for i, layer in enumerate(LAYERS) if best in layer)


def graph() -> dict[str, set[str]]:
    found = modules()
    return {name: imports(path, set(found)) - {name} for name, path in found.items()}


def test_every_module_has_a_layer():
    for name in modules():
        layer(name)


def test_no_module_imports_a_layer_above_its_own():
    upward = [
        f"{name} (layer {layer(name)}) imports {dep} (layer {layer(dep)})"
        for name, deps in graph().items()
        for dep in sorted(deps)
        if layer(dep) > layer(name)
    ]
    assert not upward, "\n".join(upward)


def test_the_rollout_machinery_knows_no_world_and_no_stage():
    for name, deps in graph().items():
        if name.startswith("lerobot_cso.rollout."):
            assert not {d for d in deps if d.startswith(("lerobot_cso.worlds", "lerobot_cso.rollout_stage"))}, name


def test_there_is_no_import_circle():
    edges = graph()
    state: dict[str, int] = {}  # 1: on the current path, 2: done
    path: list[str] = []

    def visit(name: str) -> None:
        state[name] = 1
        path.append(name)
        for dep in sorted(edges[name]):
            if state.get(dep) == 1:
                raise AssertionError("import circle: " + " -> ".join([*path[path.index(dep) :], dep]))
            if dep not in state:
                visit(dep)
        path.pop()
        state[name] = 2

    for name in sorted(edges):
        if name not in state:
            visit(name)
