"""The layer rule of the diagnostics, the viewer and the voxel keys: who may import whom, and no import cycle."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

SRC = Path(__file__).resolve().parents[1] / "src" / "driftmap"
DIAGNOSTICS_MAY_IMPORT = {"errors", "geometry", "voxels", "kernels", "frame", "config", "trajectory", "preprocess", "store",
                          "registration", "posegraph", "map", "volume", "diagnostics"}
"""Lower layers (and the package itself, .importlinter); never export, pipeline, cli, viewer, report or demo."""


def _driftmap_imports(path: Path) -> set[str]:
    """Every ``driftmap.X`` a module imports (module level, lazily inside functions, or for type checking)."""
    out = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom) and node.module and node.module.split(".")[0] == "driftmap":
            parts = node.module.split(".")
            out.update([parts[1]] if len(parts) > 1 else [alias.name for alias in node.names])
        elif isinstance(node, ast.Import):
            out.update(a.name.split(".")[1] for a in node.names if a.name.startswith("driftmap."))
    return out


def _diagnostics_modules() -> list[Path]:
    return sorted((SRC / "diagnostics").glob("*.py"))


@pytest.mark.parametrize("path", _diagnostics_modules(), ids=lambda p: p.stem)
def test_diagnostics_import_only_lower_layers(path: Path) -> None:
    assert _driftmap_imports(path) <= DIAGNOSTICS_MAY_IMPORT, path.name


def test_voxels_is_a_bottom_layer() -> None:
    assert _driftmap_imports(SRC / "voxels.py") <= {"errors", "geometry"}


def _module_level_imports(path: Path) -> set[str]:
    """The ``driftmap`` modules a module imports when it is imported (not lazily, not for type checking)."""
    out = set()
    for node in ast.parse(path.read_text()).body:
        if isinstance(node, ast.ImportFrom) and node.module and node.module.startswith("driftmap."):
            out.add(node.module)
            out.update(f"{node.module}.{a.name}" for a in node.names)  # ``from driftmap.x import module``
    return out


def test_no_import_cycle_through_the_diagnostics() -> None:
    files = {f"driftmap.diagnostics.{p.stem}": p for p in _diagnostics_modules() if p.stem != "__init__"}
    files.update({f"driftmap.{n}": SRC / f"{n}.py" for n in ("voxels", "viewer", "report")})
    graph = {m: {d for d in _module_level_imports(p) if d in files and d != m} for m, p in files.items()}
    state: dict[str, int] = {}

    def visit(m: str, path: list[str]) -> None:
        state[m] = 1
        for d in sorted(graph[m]):
            assert state.get(d) != 1, "import cycle: " + " -> ".join([*path, m, d])
            if d not in state:
                visit(d, [*path, m])
        state[m] = 2

    for m in sorted(graph):
        if m not in state:
            visit(m, [])
    assert "driftmap.diagnostics.samples" in graph["driftmap.diagnostics.surfaces"]  # the graph is not empty
