"""Packaging metadata as current setuptools wants it (no deprecation warnings during pip install)."""

from __future__ import annotations

import tomllib
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def test_license_is_an_spdx_string_with_its_file():
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())
    meta = project["project"]
    assert isinstance(meta["license"], str) and meta["license"] == "MIT"  # PEP 639, not a table
    assert all((ROOT / f).is_file() for f in meta["license-files"])
    assert "setuptools>=77" in project["build-system"]["requires"]  # the first to read it
    assert meta["requires-python"] == ">=3.11"


def test_setup_script_announces_its_long_steps():
    text = (ROOT / ".ci" / "setup").read_text()
    for before in ("apt-get update", "pip install -q -e", "python3 -m vtr.vo.kernels"):
        lines = text.splitlines()
        at = next(i for i, line in enumerate(lines) if before in line)
        assert any(line.strip().startswith("step ") for line in lines[max(0, at - 3) : at]), before
