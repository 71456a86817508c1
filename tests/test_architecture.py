"""The layers of driftmap (docs/architecture.md): imports run only downward (import-linter on .importlinter), no
import cycle, ``import driftmap.store`` stays without numba, no private name is imported across modules, and the
deprecated module paths are the same objects as the new ones."""

from __future__ import annotations

import ast
import configparser
import importlib
import pkgutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SRC = ROOT / "src" / "driftmap"
CONFIG = ROOT / ".importlinter"


def _layer_modules() -> list[str]:
    """Every module named in the layers contract of ``.importlinter`` (``a : b`` share a layer)."""
    parser = configparser.ConfigParser()
    parser.read(CONFIG)
    layers = parser["importlinter:contract:layers"]["layers"]
    return [name.strip() for line in layers.splitlines() for name in line.split(":") if name.strip()]


def test_imports_run_only_downward() -> None:
    """import-linter checks the layers contract of ``.importlinter``: a module imports only from layers below its
    own (the two deprecated alias modules are its only declared exceptions)."""
    lint_imports = Path(sys.executable).parent / "lint-imports"
    out = subprocess.run([str(lint_imports), "--no-cache", str(CONFIG)], capture_output=True, text=True,
                         cwd=ROOT, timeout=300)
    assert out.returncode == 0, out.stdout + out.stderr
    assert "Contracts: 1 kept, 0 broken." in out.stdout, out.stdout


def test_every_top_level_module_has_a_layer() -> None:
    """A new package or top-level module must be given its place in ``.importlinter`` (else nothing checks it)."""
    top_level = {f"driftmap.{m.name}" for m in pkgutil.iter_modules([str(SRC)])}
    assert top_level == set(_layer_modules())


def test_no_import_cycle() -> None:
    """No cycle among the modules as they import each other when run (imports for type checking only, which never
    run, are left out: an annotation may name a class of a module that imports this one)."""
    import grimp

    graph = grimp.build_graph("driftmap", exclude_type_checking_imports=True)
    imports = {m: graph.find_modules_directly_imported_by(m) for m in graph.modules}
    state: dict[str, int] = {}  # 1: on the current path, 2: done

    def visit(module: str, path: list[str]) -> None:
        state[module] = 1
        for imported in sorted(imports[module]):
            assert state.get(imported) != 1, "import cycle: " + " -> ".join([*path, module, imported])
            if imported not in state:
                visit(imported, [*path, module])
        state[module] = 2

    sys.setrecursionlimit(max(sys.getrecursionlimit(), 10 * len(imports)))
    for module in sorted(imports):
        if module not in state:
            visit(module, [])
    assert "driftmap.export.foxglove" in imports["driftmap.cli.store_cmds"] | imports["driftmap.demo"]  # not empty


def test_importing_the_store_does_not_import_numba() -> None:
    code = "import driftmap.store, driftmap.store.frame_store, sys; assert 'numba' not in sys.modules, 'numba'"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr


def _module_name(path: Path) -> str:
    parts = path.relative_to(SRC.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _imported_from(node: ast.ImportFrom, module: str, is_package: bool) -> str:
    """The absolute name of the module ``from X import ...`` reads (relative imports resolved)."""
    if not node.level:
        return node.module or ""
    base = module.split(".") if is_package else module.split(".")[:-1]
    base = base[: len(base) - (node.level - 1)]
    return ".".join(base + ([node.module] if node.module else []))


def _private_imports() -> list[str]:
    found = []
    for path in sorted(SRC.rglob("*.py")):
        module = _module_name(path)
        for node in ast.walk(ast.parse(path.read_text())):
            if not isinstance(node, ast.ImportFrom):
                continue
            source = _imported_from(node, module, path.name == "__init__.py")
            if source.split(".")[0] != "driftmap" or source == module:
                continue
            for alias in node.names:
                name = alias.name
                if name.startswith("_") and not (name.startswith("__") and name.endswith("__")):
                    found.append(f"{path.relative_to(ROOT)}:{node.lineno}: from {source} import {name}")
    return found


def test_no_private_name_is_imported_across_modules() -> None:
    """A name with a leading underscore belongs to its module: another module that needs it gets a public name."""
    assert _private_imports() == []


def test_the_private_import_check_finds_one(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    pkg = tmp_path / "driftmap"
    (pkg / "sub").mkdir(parents=True)
    (pkg / "sub" / "__init__.py").write_text("")
    (pkg / "sub" / "a.py").write_text("_hidden = 1\n")
    (pkg / "sub" / "b.py").write_text("from driftmap.sub.a import _hidden\nfrom .a import _hidden as h\n")
    (pkg / "sub" / "c.py").write_text("from driftmap._version import __version__\n")
    monkeypatch.setattr(sys.modules[__name__], "SRC", pkg)
    monkeypatch.setattr(sys.modules[__name__], "ROOT", tmp_path)
    assert _private_imports() == ["driftmap/sub/b.py:1: from driftmap.sub.a import _hidden",
                                  "driftmap/sub/b.py:2: from driftmap.sub.a import _hidden"]


@pytest.mark.parametrize(("old", "new"), [
    ("driftmap.map.foxglove_export", "driftmap.export.foxglove"),
    ("driftmap.sources.mcap_export", "driftmap.export.mcap"),
])
def test_deprecated_module_paths_hand_on_the_same_objects(old: str, new: str) -> None:
    old_module, new_module = importlib.import_module(old), importlib.import_module(new)
    export = importlib.import_module("driftmap.export")
    for name in old_module.__all__:
        value = getattr(old_module, name)
        home = new_module if hasattr(new_module, name) else export
        assert value is getattr(home, name), f"{old}.{name}"


def test_every_exception_class_lives_in_errors() -> None:
    """Every exception class driftmap defines is in :mod:`driftmap.errors`; the modules that defined one before
    re-export the same class."""
    import driftmap.errors as errors

    defined_elsewhere = []
    for info in pkgutil.walk_packages([str(SRC)], "driftmap."):
        if info.name.endswith("__main__"):
            continue
        module = importlib.import_module(info.name)
        for name, value in vars(module).items():
            if isinstance(value, type) and issubclass(value, BaseException) and value.__module__ == info.name \
                    and info.name != "driftmap.errors":
                defined_elsewhere.append(f"{info.name}.{name}")
    assert defined_elsewhere == []
    from driftmap.map.foxglove_export import EmptyStoreExportError
    from driftmap.posegraph import PoseGraphError
    from driftmap.sources.cloud_headers import NotACloudFile
    from driftmap.sources.mcap_export import ExportError
    from driftmap.sources.tf import TfError
    from driftmap.store.frame_store import StoreCorruptError

    assert (ExportError, EmptyStoreExportError, TfError, NotACloudFile, PoseGraphError, StoreCorruptError) == (
        errors.ExportError, errors.EmptyStoreExportError, errors.TfError, errors.NotACloudFile,
        errors.PoseGraphError, errors.StoreCorruptError)
