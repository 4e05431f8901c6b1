"""CSV files as spreadsheets write them: a UTF-8 byte-order mark is not part of the first column's name, and a
header that names a column twice is refused (which copy would be read is a guess)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from perception_model.errors import InputDataError
from perception_model.io import read_points
from perception_model.landmarks_file import read_landmarks

DATA = Path(__file__).parent / "data" / "landmarks_vtr_repeat.csv"


def test_a_bom_is_not_part_of_the_header(tmp_path):
    bom = tmp_path / "bom.csv"
    bom.write_bytes(b"\xef\xbb\xbf" + DATA.read_bytes())  # was: "missing column(s) t_ns"-like refusal
    a, b = read_landmarks(DATA), read_landmarks(bom)
    assert len(a.alpha) == len(b.alpha) > 0 and np.array_equal(a.alpha, b.alpha)
    pts = tmp_path / "points.csv"
    pts.write_text("\ufeffx,y,z\n1,2,3\n4,5,6\n", encoding="utf-8")
    assert read_points(pts).shape == (2, 3)


def test_a_duplicated_column_is_refused(tmp_path):
    head, *rows = DATA.read_text().splitlines()
    names = head.split(",")
    dup = tmp_path / "dup.csv"
    dup.write_text("\n".join([",".join([*names, names[2]]), *(r + "," + r.split(",")[2] for r in rows)]) + "\n")
    with pytest.raises(InputDataError, match=f"column '{names[2]}' appears twice"):
        read_landmarks(dup)
    pts = tmp_path / "points.csv"
    pts.write_text("x,y,z,x\n1,2,3,9\n")
    with pytest.raises(InputDataError, match="column 'x' appears twice"):
        read_points(pts)
