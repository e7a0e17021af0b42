"""The package's layers import downward only, and no two modules import each other (import
statements read from the source, those under ``TYPE_CHECKING`` included)."""

from __future__ import annotations

import ast
from pathlib import Path

import torchcbf

ROOT = Path(torchcbf.__file__).parent
# docs/architecture.md: shared helpers, then dynamics/integrators/qp, then barriers, then
# filters/mppi/estimation/learning (and the arm roadmap), then sim, then scenarios/envs/
# sweep/viz, then the CLI
LAYERS = {
    "_autograd": 0, "_checks": 0, "_compile": 0, "_constants": 0, "_io": 0, "_native": 0,
    "_graphs": 0, "_triton": 0,
    "_random": 0, "_argtypes": 0,
    "_version": 0,
    "dynamics": 1, "integrators": 1, "qp": 1,
    "barriers": 2,
    "filters": 3, "mppi": 3, "estimation": 3, "learning": 3, "roadmap": 3,
    "sim": 4,
    "scenarios": 5, "envs": 5, "sweep": 5, "viz": 5,
    "cli": 6, "_info": 6,
}  # fmt: skip


def _module_name(path: Path) -> str:
    parts = path.relative_to(ROOT.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _imports() -> dict[str, set[str]]:
    """Module -> the torchcbf modules it imports (``from pkg import submodule`` counts as
    importing the submodule)."""
    paths = list(ROOT.rglob("*.py"))
    names = {_module_name(p) for p in paths}
    graph: dict[str, set[str]] = {}
    for path in paths:
        deps: set[str] = set()
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ImportFrom) and node.module:
                for alias in node.names:
                    sub = f"{node.module}.{alias.name}"
                    deps.add(sub if sub in names else node.module)
            elif isinstance(node, ast.Import):
                deps.update(a.name for a in node.names)
        graph[_module_name(path)] = {d for d in deps if d.startswith("torchcbf.")}
    return graph


# the package's face (torchcbf/__init__.py) imports the public names of every layer, so a
# module that imports from it reaches up; only the command line sits with it at the top
FACE = LAYERS["cli"]


def _layer(module: str) -> int | None:
    parts = module.split(".")
    return LAYERS.get(parts[1]) if len(parts) > 1 else FACE


def test_every_subpackage_has_a_layer():
    tops = {p.stem for p in ROOT.glob("*.py")} | {p.parent.name for p in ROOT.glob("*/__init__.py")}
    missing = sorted(t for t in tops if t not in LAYERS and t != "__init__")
    assert not missing, f"give these modules a layer: {missing}"


def test_imports_go_down_the_layers():
    up = []
    for module, deps in _imports().items():
        mine = _layer(module)
        for dep in deps:
            theirs = _layer(dep)
            if mine is not None and theirs is not None and theirs > mine:
                up.append(f"{module} -> {dep}")
    assert not up, f"imports reaching up a layer: {sorted(up)}"


def test_no_import_cycles_between_modules():
    graph = _imports()
    cycles = sorted(
        f"{a} <-> {b}" for a, deps in graph.items() for b in deps if a < b and a in graph.get(b, ())
    )
    assert not cycles, f"modules importing each other: {cycles}"
