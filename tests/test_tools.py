"""Every benchmark and tool in ``tools/`` still imports against the package (a rename in ``vtr`` that a tool was not
told of fails here, not in the middle of someone's benchmark run). Importing runs no tool: each keeps its work behind
``if __name__ == "__main__"`` or in functions."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import pytest

TOOLS = sorted((Path(__file__).resolve().parents[1] / "tools").glob("*.py"))


@pytest.mark.parametrize("path", TOOLS, ids=[p.stem for p in TOOLS])
def test_tool_imports(path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.syspath_prepend(str(path.parent))  # tools import their sibling helpers by name
    spec = importlib.util.spec_from_file_location(f"_tool_{path.stem}", path)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    monkeypatch.setitem(sys.modules, spec.name, module)
    spec.loader.exec_module(module)


def test_every_tool_is_collected() -> None:
    assert len(TOOLS) >= 20, [p.name for p in TOOLS]
