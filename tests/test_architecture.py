"""The package tree imports only downward.

Layer order (the single written statement of it, repeated in the README's Architecture section): a module
may import from its own subpackage or from a layer to its left, never to its right.

    bottom modules (errors, conventions, config, geometry, camera, timing, types, parallel, signals, and the
    ``vtr`` package itself) < io < vo < map < state < navigation < sim < control < app < cli

Every import is checked, including those inside functions and under ``TYPE_CHECKING`` (read with ``ast``
from the source, nothing is imported). ``perception_model`` is a separate package and imports nothing
from ``vtr``. In both packages no library module imports a command-line module (``CLI_MODULES``: ``vtr.cli``
and its submodules, ``vtr.__main__``, ``perception_model.cli``, ``perception_model.commandline``,
``perception_model.__main__``); command-line modules may import each other.

Owners of outside libraries: only the map's file layer (``vtr.map.database``) imports ``sqlite3``, in
``vtr`` and ``perception_model`` (tests and tools may open map files directly); the WNOA algebra
(``vtr.state.wnoa``) imports no GTSAM.
"""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

LAYERS = ("bottom", "io", "vo", "map", "state", "navigation", "sim", "control", "app", "cli")
RANK = {name: i for i, name in enumerate(LAYERS)}
BOTTOM_MODULES = {
    "vtr",
    "vtr.errors",
    "vtr.conventions",
    "vtr.config",
    "vtr.geometry",
    "vtr.camera",
    "vtr.timing",
    "vtr.types",
    "vtr.parallel",
    "vtr.signals",
}
ENTRY_POINTS = {"vtr.__main__": "cli"}  # ``python -m vtr`` runs the command line
SQLITE_OWNER = "vtr.map.database"  # the one module that talks to SQLite
GTSAM_FREE = ("vtr.state.wnoa",)  # pure numpy algebra
#: The command-line modules (a name and everything below it); every other module of both packages is a library
#: module, and no library module imports one of these.
CLI_MODULES = (
    "vtr.cli",
    "vtr.__main__",
    "perception_model.cli",
    "perception_model.commandline",
    "perception_model.__main__",
)


def module_name(path: Path) -> str:
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def is_module(name: str) -> bool:
    p = ROOT.joinpath(*name.split("."))
    return p.with_suffix(".py").is_file() or (p / "__init__.py").is_file()


def imports(path: Path) -> list[tuple[int, str]]:
    """(line, absolute module name) of every import in a source file, wherever it sits."""
    mod = module_name(path)
    package = mod if path.name == "__init__.py" else mod.rpartition(".")[0]
    found = []
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            found += [(node.lineno, alias.name) for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                parts = package.split(".")
                base = ".".join(parts[: len(parts) - node.level + 1] + ([node.module] if node.module else []))
            else:
                base = node.module or ""
            for alias in node.names:  # ``from pkg import module`` imports the module
                sub = f"{base}.{alias.name}"
                found.append((node.lineno, sub if is_module(sub) else base))
    return found


def layer(module: str) -> str:
    if module in ENTRY_POINTS:
        return ENTRY_POINTS[module]
    if module in BOTTOM_MODULES or module.startswith("vtr.config."):  # the config package's modules
        return "bottom"
    sub = module.split(".")[1]
    assert sub in RANK, f"{module} is in no declared layer: add it to LAYERS or BOTTOM_MODULES"
    return sub


def sources(package: str) -> list[Path]:
    return sorted((ROOT / package).rglob("*.py"))


def test_every_vtr_module_has_a_layer():
    for path in sources("vtr"):
        layer(module_name(path))


def test_vtr_imports_only_its_own_subpackage_or_lower_layers():
    bad = []
    for path in sources("vtr"):
        mod = module_name(path)
        here = layer(mod)
        for line, target in imports(path):
            if target != "vtr" and not target.startswith("vtr."):
                continue
            there = layer(target)
            if there != here and RANK[there] >= RANK[here]:
                bad.append(f"{path.relative_to(ROOT)}:{line}: {mod} ({here}) imports {target} ({there})")
    assert not bad, "imports against the layer order " + " < ".join(LAYERS) + ":\n" + "\n".join(bad)


def test_perception_model_imports_nothing_from_vtr():
    bad = [
        f"{path.relative_to(ROOT)}:{line}: {target}"
        for path in sources("perception_model")
        for line, target in imports(path)
        if target == "vtr" or target.startswith("vtr.")
    ]
    assert not bad, "perception_model imports vtr:\n" + "\n".join(bad)


def test_only_the_map_file_layer_imports_sqlite3():
    bad = [
        f"{path.relative_to(ROOT)}:{line}: {module_name(path)} imports {target}"
        for package in ("vtr", "perception_model")
        for path in sources(package)
        if module_name(path) != SQLITE_OWNER
        for line, target in imports(path)
        if target == "sqlite3" or target.startswith("sqlite3.")
    ]
    assert not bad, f"only {SQLITE_OWNER} may import sqlite3 (use the map API):\n" + "\n".join(bad)


def test_wnoa_algebra_imports_no_gtsam():
    bad = [
        f"{path.relative_to(ROOT)}:{line}: {target}"
        for path in sources("vtr")
        if module_name(path) in GTSAM_FREE
        for line, target in imports(path)
        if target == "gtsam" or target.startswith("gtsam.")
    ]
    assert not bad, "the WNOA algebra is numpy only:\n" + "\n".join(bad)


def is_cli(module: str) -> bool:
    return any(module == name or module.startswith(name + ".") for name in CLI_MODULES)


def test_the_cli_modules_exist():
    assert [name for name in CLI_MODULES if not is_module(name) and name != "perception_model.__main__"] == []


def test_no_library_module_imports_a_cli_module():
    bad = [
        f"{path.relative_to(ROOT)}:{line}: {mod} imports {target}"
        for package in ("vtr", "perception_model")
        for path in sources(package)
        if not is_cli(mod := module_name(path))
        for line, target in imports(path)
        if is_cli(target)
    ]
    assert not bad, "library modules import command-line modules:\n" + "\n".join(bad)
