"""The README's python code blocks run, in order, as a user would run them after the commands above them:
in a fresh folder holding the shipped datasets, a map taught on the clip's even frames
(``out/route.vtrmap``) and a fitted model (``out/model/model.json``). A block that names an undefined variable or
a moved API fails here."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
BLOCK = re.compile(r"^```python\n(.*?)^```", re.S | re.M)


def python_blocks() -> list[str]:
    return BLOCK.findall((ROOT / "README.md").read_text())


def test_readme_has_python_blocks():
    assert len(python_blocks()) >= 2


@pytest.fixture(scope="module")
def workdir(tmp_path_factory, kitti_clip):
    from click.testing import CliRunner

    from perception_model.model import PerceptionModel
    from vtr.cli import main

    d = tmp_path_factory.mktemp("readme")
    (d / "datasets").mkdir()
    (d / "datasets" / kitti_clip.name).symlink_to(kitti_clip)
    r = CliRunner().invoke(
        main,
        ["teach", str(d / "datasets" / kitti_clip.name), "--map", str(d / "out" / "route.vtrmap"), "--frames", "0::2"],
    )
    assert r.exit_code == 0, r.output
    (d / "out" / "model").mkdir()
    PerceptionModel.thesis().save(d / "out" / "model" / "model.json")
    return d


@pytest.mark.parametrize("index", range(len(python_blocks())))
def test_readme_python_block_runs(index, workdir):
    code = python_blocks()[index]
    r = subprocess.run([sys.executable, "-c", code], cwd=workdir, capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, f"README python block {index + 1}:\n{code}\n{r.stderr[-3000:]}"
    assert len(r.stdout) < 5000, f"block {index + 1} printed {len(r.stdout)} characters"  # short reprs
