"""Compare two output folders of the same command (e.g. ``vtr demo`` before and after a code move).

Every file is compared byte for byte, except the three that hold the time of the run:

- ``run.json``: compared after removing the clock (``start``, ``end``, and timings: ``seconds``, ``fps``,
  ``*_ms_*``) and the command line (``argv``), with both folders' paths written as ``<out>`` and the paths of
  the package's shipped data (``.../datasets/``) as ``<repo>/datasets/`` (a checkout elsewhere is the same run);
- a map (``*.vtrmap``): compared row by row in every table, without the creation times, paths written as in
  ``run.json``;
- ``.vtr-outputs`` (the output folder's marker, which holds the run's time): skipped.

Prints one line per file that differs and a summary; exit 1 when anything differs.

    python tools/compare_outputs.py out/demo-before out/demo-after
"""

from __future__ import annotations

import argparse
import json
import re
import sqlite3
import sys
from pathlib import Path

CLOCK_KEYS = {"start", "end", "created", "seconds", "fps"}
# where a run happened, not what it did: the command line (``vtr`` or ``python -m vtr``)
PLACE_KEYS = {"argv"}
# the package's shipped data, wherever the checkout is (``/work/main/datasets/...``, a worktree's copy)
_SHIPPED = re.compile(r"/[^\s\"']*?/datasets/")


def _place_free(text: str, root: str) -> str:
    return _SHIPPED.sub("<repo>/datasets/", text.replace(root, "<out>"))


def _without_clock(value, a: str, b: str):
    if isinstance(value, dict):
        return {
            k: _without_clock(v, a, b)
            for k, v in value.items()
            if k not in CLOCK_KEYS | PLACE_KEYS and "_ms_" not in k and not k.endswith("_seconds")
        }
    if isinstance(value, list):
        return [_without_clock(v, a, b) for v in value]
    if isinstance(value, str):
        return _place_free(_place_free(value, a), b)
    return value


def _map_rows(path: Path, root: Path) -> dict[str, list[tuple]]:
    con = sqlite3.connect(f"file:{path}?mode=ro", uri=True)
    try:
        tables = [r[0] for r in con.execute("SELECT name FROM sqlite_master WHERE type='table' ORDER BY name")]
        rows = {}
        for table in tables:
            columns = [r[1] for r in con.execute(f"PRAGMA table_info({table})")]
            keep = [c for c in columns if c != "created"]
            found = con.execute(f"SELECT {', '.join(keep)} FROM {table} ORDER BY 1").fetchall()
            if table == "meta":  # the map's creation time is a meta row
                found = [r for r in found if r[0] != "created"]
            rows[table] = [
                tuple(_place_free(v, str(root)) if isinstance(v, str) else v for v in r) for r in found
            ]  # a run's source is a path inside the folder
        return rows
    finally:
        con.close()


def differs(rel: Path, a: Path, b: Path, root_a: Path, root_b: Path) -> str | None:
    """Why file ``rel`` differs between the folders, or None."""
    if rel.name == ".vtr-outputs":
        return None
    if not b.is_file():
        return "missing in the second folder"
    if rel.name == "run.json":
        ja = _without_clock(json.loads(a.read_text()), str(root_a), str(root_b))
        jb = _without_clock(json.loads(b.read_text()), str(root_a), str(root_b))
        return None if ja == jb else "run.json differs (beyond the clock)"
    if rel.suffix == ".vtrmap":
        ra, rb = _map_rows(a, root_a), _map_rows(b, root_b)
        bad = [t for t in sorted(set(ra) | set(rb)) if ra.get(t) != rb.get(t)]
        return None if not bad else f"map tables differ: {', '.join(bad)}"
    return None if a.read_bytes() == b.read_bytes() else "bytes differ"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("first", type=Path)
    parser.add_argument("second", type=Path)
    args = parser.parse_args(argv)
    files = sorted(p.relative_to(args.first) for p in args.first.rglob("*") if p.is_file())
    extra = sorted(
        p.relative_to(args.second)
        for p in args.second.rglob("*")
        if p.is_file() and not (args.first / p.relative_to(args.second)).is_file()
    )
    bad = 0
    for rel in files:
        why = differs(rel, args.first / rel, args.second / rel, args.first, args.second)
        if why:
            bad += 1
            print(f"{rel}: {why}")
    for rel in extra:
        bad += 1
        print(f"{rel}: only in the second folder")
    compared = len(files) - sum(rel.name == ".vtr-outputs" for rel in files)
    print(
        f"{compared} files compared ({sum(r.suffix == '.vtrmap' for r in files)} maps by rows, run.json without the "
        f"clock): {'identical' if not bad else f'{bad} differ'}"
    )
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
