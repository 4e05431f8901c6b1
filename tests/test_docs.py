"""The design documentation lives in the repository: every ``docs/<page>.md`` cited by code, tests, tools or
the README exists, every relative link between the pages resolves, and nothing cites a design file users
never get."""

from __future__ import annotations

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SOURCES = [
    *ROOT.glob("vtr/**/*.py"),
    *ROOT.glob("perception_model/**/*.py"),
    *ROOT.glob("tools/*.py"),
    *ROOT.glob("tests/**/*.py"),
    ROOT / "README.md",
]
CITATION = re.compile(r"docs/([A-Za-z0-9_]+\.md)")
LINK = re.compile(r"\]\(([^)#:]+\.md)(#[^)]*)?\)")


def test_cited_pages_exist():
    cited = {(p.relative_to(ROOT), m) for p in SOURCES for m in CITATION.findall(p.read_text())}
    assert len({m for _p, m in cited}) >= 5  # the modules do point at the pages
    missing = sorted((str(p), m) for p, m in cited if not (ROOT / "docs" / m).is_file())
    assert not missing, missing


def test_links_between_pages_resolve():
    pages = sorted((ROOT / "docs").glob("*.md"))
    assert pages
    broken = [
        (p.name, link)
        for p in pages
        for link, _anchor in LINK.findall(p.read_text())
        if not (p.parent / link).is_file()
    ]
    assert not broken, broken


def test_no_citation_of_an_outside_design_file():
    offenders = [
        str(p.relative_to(ROOT)) for p in SOURCES if p != Path(__file__).resolve() and "DESIGN" + ".md" in p.read_text()
    ]
    assert not offenders, offenders


def test_ramp_clip_source_names_the_turn_its_poses_make():
    """SOURCE.md's turn direction agrees with poses.txt (camera x right, z forward: a heading turning from +z
    towards +x is a right turn)."""
    import numpy as np

    clip = ROOT / "datasets" / "kitti00_ramp_clip"
    P = np.loadtxt(clip / "poses.txt").reshape(-1, 3, 4)
    forward = P[-1, :, 2]
    turn_deg = float(np.degrees(np.arctan2(forward[0], forward[2])))
    side = "right" if turn_deg > 0 else "left"
    text = (clip / "SOURCE.md").read_text()
    assert f"{side} turn" in text and f"turns {side} by about {abs(round(turn_deg))} degrees" in text, turn_deg
