"""Readers of landmarks.csv, landmark positions and path positions: content and error messages."""

from __future__ import annotations

import math

import numpy as np
import pytest

from perception_model.errors import InputDataError
from perception_model.io import read_points, read_positions
from perception_model.landmarks_file import (
    LANDMARK_COLUMNS,
    Observations,
)
from perception_model.landmarks_file import read_landmarks as read_landmarks_csv
from perception_model.landmarks_file import read_landmarks_files as read_landmarks_csvs
from perception_model.landmarks_file import write_landmarks as write_landmarks_csv
from perception_model.model import PerceptionModel
from perception_model.synthetic import simulate_observations

HEADER = ",".join(LANDMARK_COLUMNS)


def _write(tmp_path, name, lines):
    path = tmp_path / name
    path.write_text("\n".join(lines) + "\n")
    return path


def test_roundtrip_and_concatenation(tmp_path):
    obs = simulate_observations(PerceptionModel.thesis(), 1200, np.random.default_rng(0))
    write_landmarks_csv(tmp_path / "a.csv", obs)
    write_landmarks_csv(tmp_path / "b.csv", obs.take(np.arange(100)))
    back = read_landmarks_csv(tmp_path / "a.csv")
    assert np.allclose(back.alpha, obs.alpha, rtol=1e-15) and np.array_equal(back.inlier, obs.inlier)
    assert np.array_equal(back.t_ns, obs.t_ns)
    both = read_landmarks_csvs([tmp_path / "a.csv", tmp_path / "b.csv"])
    assert len(both) == 1300 and [s.count for s in both.sources] == [1200, 100]
    groups = both.frame_groups()
    assert groups[0] != groups[1200]  # same t_ns in another file is another localization
    d = both.describe()
    assert d["n_observations"] == 1300 and d["parallax_deg_range"][1] <= 20.0


def test_column_order_extra_columns_and_large_timestamps(tmp_path):
    t_ns = 1_600_000_000_123_456_789  # beyond float64 precision: must stay exact
    path = _write(
        tmp_path,
        "x.csv",
        [
            "view_deg,extra,inlier,parallax_deg,range_m,landmark_id,trunk_id,leaf_id,t_ns",
            f"30.5,foo,true,2.5,,7,8,9,{t_ns}",
        ],
    )
    obs = read_landmarks_csv(path)
    assert obs.t_ns[0] == t_ns and obs.inlier[0] and math.isnan(obs.range_m[0])
    assert obs.theta[0] == pytest.approx(math.radians(30.5)) and obs.alpha[0] == pytest.approx(math.radians(2.5))


@pytest.mark.parametrize(
    "lines, match",
    [
        ([], "empty file"),
        ([HEADER], "no data rows"),
        (
            ["t_ns,leaf_id,inlier,parallax_deg", "1,1,1,2"],
            r"missing column\(s\) trunk_id, landmark_id, view_deg, range_m",
        ),
        ([HEADER, "1,1,1,1,1,2.0,30,10", "2,1,1,2,0,nan,30,10"], r"line 3: column parallax_deg is 'nan'"),
        ([HEADER, "1,1,1,1,1,2.0,,10"], r"line 2: column view_deg is 'empty'"),
        ([HEADER, "1,1,1,1,1,2.0,abc,10"], r"line 2: column view_deg: not a number"),
        ([HEADER, "1,1,1,1,1,2.0,190,10"], r"outside \[0, 180\]"),
        ([HEADER, "1,1,1,1,1,-2.0,10,10"], r"outside \[0, 180\]"),
        ([HEADER, "1,1,1,1,yes-ish,2.0,10,10"], r"line 2: column inlier: expected 0/1"),
        ([HEADER, "1.5,1,1,1,1,2.0,10,10"], r"line 2: column t_ns: not an integer"),
        ([HEADER, "1,1,1,1,1,2.0,10"], r"line 2: 7 fields, header has 8"),
    ],
)
def test_bad_landmark_files_name_file_and_line(tmp_path, lines, match):
    path = _write(tmp_path, "bad.csv", lines) if lines else (tmp_path / "bad.csv")
    if not lines:
        path.write_text("")
    with pytest.raises(InputDataError, match=match) as info:
        read_landmarks_csv(path)
    assert "bad.csv" in str(info.value)


def test_missing_file_and_no_files(tmp_path):
    with pytest.raises(InputDataError, match="cannot read"):
        read_landmarks_csv(tmp_path / "nope.csv")
    with pytest.raises(InputDataError, match="no landmarks"):
        read_landmarks_csvs([])
    with pytest.raises(InputDataError, match="no observations"):
        Observations.concatenate([])


def test_points_and_positions(tmp_path):
    pts = np.array([[1.0, 2.0, -10.0], [3.0, -1.0, -12.0]])
    np.save(tmp_path / "lm.npy", pts)
    assert np.array_equal(read_points(tmp_path / "lm.npy"), pts)
    _write(tmp_path, "lm.csv", ["x,y,z", "1,2,-10", "3,-1,-12"])
    assert np.array_equal(read_points(tmp_path / "lm.csv"), pts)
    np.save(tmp_path / "bad.npy", np.zeros((3, 2)))
    with pytest.raises(InputDataError, match=r"\(M, 3\)"):
        read_points(tmp_path / "bad.npy")
    _write(tmp_path, "nan.csv", ["x,y,z", "1,2,-10", "3,nan,-12"])
    with pytest.raises(InputDataError, match="line 3"):
        read_points(tmp_path / "nan.csv")
    _write(tmp_path, "pos.csv", ["x,y,z,yaw_deg", "0,0,0,90", "1,0,0,0"])
    path = read_positions(tmp_path / "pos.csv")
    assert path.positions.shape == (2, 3) and path.yaw[0] == pytest.approx(math.pi / 2)
    _write(tmp_path, "pos2.csv", ["x,y,z", "0,0,0"])
    assert read_positions(tmp_path / "pos2.csv").yaw is None
    _write(tmp_path, "pos3.csv", ["x,y", "0,0"])
    with pytest.raises(InputDataError, match="missing column"):
        read_positions(tmp_path / "pos3.csv")
