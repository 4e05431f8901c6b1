"""``vtr.app.batch`` is one module per concern with imports one way: each module imports only modules listed before
it in ORDER (the package's ``__init__`` imports them all), so no concern reaches back into a later one."""

from __future__ import annotations

import ast
from pathlib import Path

BATCH = Path(__file__).resolve().parents[2] / "vtr" / "app" / "batch"
ORDER = ("layout", "manifest", "outcome", "resume", "run", "options", "tls", "cluster", "lock", "model_fit", "driver")


def sibling_imports(path: Path) -> set[str]:
    """The modules of the package that ``path`` imports (``from .x import ...``, anywhere in the file)."""
    found = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.ImportFrom) and node.level == 1:
            if node.module:
                found.add(node.module.split(".")[0])
            else:
                found.update(alias.name for alias in node.names)
    return found


def test_every_module_is_in_the_order():
    assert sorted(p.stem for p in BATCH.glob("*.py") if p.stem != "__init__") == sorted(ORDER)


def test_imports_go_one_way():
    back = [
        f"{name} imports {other}"
        for i, name in enumerate(ORDER)
        for other in sorted(sibling_imports(BATCH / f"{name}.py"))
        if other not in ORDER[:i]
    ]
    assert back == []
