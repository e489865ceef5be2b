"""The package's layering, as the README's module map states it: only ``dhg.core`` imports the
native module, no two modules import each other (directly or round a loop), and every module
says what it exports."""

from __future__ import annotations

import ast
import graphlib
from pathlib import Path

import pytest

import dhg

ROOT = Path(dhg.__file__).parent


def _modules() -> dict[str, ast.Module]:
    out = {}
    for p in sorted(ROOT.rglob("*.py")):
        parts = p.relative_to(ROOT.parent).with_suffix("").parts
        name = ".".join(parts[:-1] if parts[-1] == "__init__" else parts)
        out[name] = ast.parse(p.read_text(encoding="utf-8"), str(p))
    return out


MODULES = _modules()


def _imports(name: str, tree: ast.Module) -> set[str]:
    """Every dhg module ``name`` imports, at module level or inside a function."""
    deps = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            for target in [node.module, *(f"{node.module}.{a.name}" for a in node.names)]:
                if target in MODULES and target != name:
                    deps.add(target)
        elif isinstance(node, ast.Import):
            deps |= {a.name for a in node.names if a.name in MODULES and a.name != name}
    return deps


def _imports_native(tree: ast.Module) -> bool:
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom) and node.module == "dhg" and any(a.name == "_bone_sim" for a in node.names):
            return True
        if isinstance(node, ast.ImportFrom) and node.module == "dhg._bone_sim":
            return True
        if isinstance(node, ast.Import) and any(a.name == "dhg._bone_sim" for a in node.names):
            return True
    return False


def test_the_package_is_found_with_its_subpackages():
    # Guards the checks below against walking an empty or wrong tree.
    for sub in (
        "dhg.core",
        "dhg.bone",
        "dhg.operators",
        "dhg.data",
        "dhg.learning",
        "dhg.live",
        "dhg.study",
        "dhg.cli",
    ):
        assert sub in MODULES, sub
    assert len(MODULES) > 40


def test_only_the_core_layer_imports_the_native_module():
    importers = {name for name, tree in MODULES.items() if _imports_native(tree)}
    assert "dhg.core.session" in importers
    outside = sorted(n for n in importers if not n.startswith("dhg.core."))
    assert outside == [], f"modules outside dhg.core import dhg._bone_sim: {outside}"


def test_no_module_imports_the_root_package():
    # The root re-exports the public API from every layer: a module that imported a name from it
    # would depend on the layers above it, unseen by the checks below (which leave the root out).
    for name, tree in MODULES.items():
        if name == "dhg":
            continue
        for node in ast.walk(tree):
            if isinstance(node, ast.ImportFrom) and node.module == "dhg" and node.level == 0:
                names = sorted(a.name for a in node.names if a.name != "_bone_sim")
                assert names == [], f"{name} imports {names} from the root package dhg"
            if isinstance(node, ast.Import):
                assert all(a.name != "dhg" for a in node.names), f"{name} imports the root package dhg"


def test_no_import_cycle_between_modules():
    # The root package re-exports the public API, so it is left out: importing ``dhg`` imports it.
    graph = {n: {d for d in _imports(n, t) if d != "dhg"} for n, t in MODULES.items() if n != "dhg"}
    try:
        list(graphlib.TopologicalSorter(graph).static_order())
    except graphlib.CycleError as e:
        pytest.fail(f"import cycle: {' -> '.join(e.args[1])}")


def test_the_core_imports_no_higher_layer():
    higher = ("dhg.bone", "dhg.operators", "dhg.data", "dhg.learning", "dhg.live", "dhg.study", "dhg.cli")
    for name, tree in MODULES.items():
        if name.startswith("dhg.core"):
            bad = sorted(d for d in _imports(name, tree) if d.startswith(higher))
            assert bad == [], f"{name} imports {bad}"


def test_every_module_declares_its_exports():
    for name, tree in MODULES.items():
        if (
            name.split(".")[-1] in ("__main__",)
            or name == "dhg"
            or not any(isinstance(n, (ast.FunctionDef, ast.ClassDef)) for n in tree.body)
        ):
            continue
        names = [
            t.id
            for n in tree.body
            if isinstance(n, (ast.Assign, ast.AnnAssign))
            for t in getattr(n, "targets", [getattr(n, "target", None)])
            if isinstance(t, ast.Name)
        ]
        assert "__all__" in names, f"{name} has no __all__"


LAYERS = (
    ("dhg.core",),
    ("dhg.bone", "dhg.operators"),
    ("dhg.data", "dhg.learning"),
    ("dhg.live",),
    ("dhg.view", "dhg.study"),
    ("dhg.cli",),
)
"""The subpackages from the bottom up, as the README's module map orders them: a module may
import from its own layer and the layers below, never from one above."""


def test_each_subpackage_imports_only_from_its_layer_and_below():
    level = {pkg: i for i, layer in enumerate(LAYERS) for pkg in layer}

    def layer_of(module: str) -> int | None:
        return next((lv for pkg, lv in level.items() if module == pkg or module.startswith(pkg + ".")), None)

    for name, tree in MODULES.items():
        mine = layer_of(name)
        if mine is None:
            continue
        upward = sorted(d for d in _imports(name, tree) if (layer_of(d) or 0) > mine)
        assert upward == [], f"{name} (layer {mine}) imports from a layer above it: {upward}"
