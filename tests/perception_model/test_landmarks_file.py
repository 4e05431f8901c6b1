"""The landmarks file format: columnar reader = strict reader, CSV/Parquet round trips, one-line errors."""

from __future__ import annotations

import csv
import math
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest
from click.testing import CliRunner

from perception_model.cli import main
from perception_model.errors import InputDataError
from perception_model.landmarks_file import (
    ALL_FIELDS,
    FIT_FIELDS,
    LANDMARK_COLUMNS,
    LandmarksWriter,
    read_landmarks,
    read_landmarks_csv_strict,
    read_landmarks_files,
    write_landmarks,
)
from perception_model.model import PerceptionModel
from perception_model.synthetic import simulate_observations

DATA = Path(__file__).parent / "data"
FIXTURES = [DATA / "landmarks_vtr_repeat.csv", DATA / "landmarks_pm_writer.csv"]


def _same(x, y) -> bool:
    if x is None or y is None:
        return x is None and y is None
    return x.dtype == y.dtype and np.array_equal(x, y, equal_nan=x.dtype.kind == "f")


def _assert_same_observations(a, b, fields=ALL_FIELDS):
    assert len(a) == len(b) and a.sources == b.sources
    for f in fields:
        assert _same(getattr(a, f), getattr(b, f)), f


@pytest.mark.parametrize("path", FIXTURES, ids=lambda p: p.name)
def test_columnar_reader_equals_strict_reader_and_the_text(path):
    fast = read_landmarks(path)
    _assert_same_observations(fast, read_landmarks_csv_strict(path))
    # and both equal the numbers in the text, parsed independently here
    with path.open(newline="") as fh:
        rows = list(csv.DictReader(fh))
    assert len(fast) == len(rows) > 0
    assert fast.t_ns.tolist() == [int(r["t_ns"]) for r in rows]
    assert fast.leaf_id.tolist() == [int(r["leaf_id"]) for r in rows]
    assert fast.inlier.tolist() == [r["inlier"] == "1" for r in rows]
    assert np.array_equal(fast.alpha, np.radians([float(r["parallax_deg"]) for r in rows]))
    assert np.array_equal(fast.theta, np.radians([float(r["view_deg"]) for r in rows]))
    if "matched" in rows[0]:
        assert fast.matched.tolist() == [r["matched"] == "1" for r in rows]
        assert not (fast.inlier & ~fast.matched).any()
    else:
        assert fast.matched is None


def test_fit_fields_read_only_what_a_fit_needs():
    obs = read_landmarks(FIXTURES[0], FIT_FIELDS)
    assert obs.leaf_id is None and obs.range_m is None and obs.matched is None
    assert obs.t_ns.dtype == np.int64 and obs.inlier.dtype == np.bool_ and obs.alpha.dtype == np.float64
    full = read_landmarks(FIXTURES[0])
    _assert_same_observations(obs, full, FIT_FIELDS)


@pytest.mark.parametrize("suffix", [".csv", ".parquet"])
def test_round_trip_csv_and_parquet(tmp_path, suffix):
    obs = simulate_observations(PerceptionModel.thesis(), 2_500, np.random.default_rng(3), name="x")
    obs = type(obs)(**{**vars(obs), "matched": obs.inlier | (np.arange(len(obs)) % 3 == 0)})
    path = tmp_path / f"lm{suffix}"
    with LandmarksWriter(path) as w:  # appended in blocks, as vtr repeat does per localization
        for start in range(0, len(obs), 1000):
            w.write(obs.take(np.arange(start, min(start + 1000, len(obs)))))
    assert w.rows == len(obs)
    back = read_landmarks(path)
    for f in ("t_ns", "leaf_id", "trunk_id", "landmark_id", "inlier", "matched", "range_m"):
        assert _same(getattr(back, f), getattr(obs, f)), f
    # degrees in the file, radians in memory: one conversion each way, < 1 ulp of difference
    assert np.allclose(back.alpha, obs.alpha, rtol=1e-15, atol=0) and np.allclose(back.theta, obs.theta, rtol=1e-15)
    if suffix == ".csv":
        header = path.read_text().splitlines()[0]
        assert header == ",".join((*LANDMARK_COLUMNS, "matched"))
        _assert_same_observations(back, read_landmarks_csv_strict(path))
    else:
        pf = pq.ParquetFile(path)
        assert pf.schema_arrow.field("parallax_deg").type == pa.float64()
        assert pf.metadata.num_row_groups == 1  # small blocks are gathered into row groups


def test_csv_and_parquet_files_together_and_unknown_matched(tmp_path):
    obs = simulate_observations(PerceptionModel.thesis(), 1_000, np.random.default_rng(1), name="y")
    write_landmarks(tmp_path / "a.csv", obs)  # matched None: empty cells
    write_landmarks(tmp_path / "b.parquet", obs)
    assert ",," not in (tmp_path / "a.csv").read_text() and (tmp_path / "a.csv").read_text().count(",\n") == 1000
    both = read_landmarks_files([tmp_path / "a.csv", tmp_path / "b.parquet"])
    assert len(both) == 2000 and both.matched is None
    assert [s.count for s in both.sources] == [1000, 1000]
    groups = both.frame_groups()
    assert groups[0] != groups[1000] and groups.max() + 1 == 2 * (1000 // 500)


def _lines(tmp_path, name, lines):
    path = tmp_path / name
    path.write_text("\n".join(lines) + "\n")
    return path


HEADER = ",".join(LANDMARK_COLUMNS)


def test_lenient_spellings_fall_back_to_the_strict_reader(tmp_path):
    path = _lines(tmp_path, "x.csv", [HEADER, " 1 ,1,1,1, TrUe ,2.0,10,", "", ",,,,,,,", "2,1,1,1,No,2.5,11,nan"])
    obs = read_landmarks(path)
    assert obs.t_ns.tolist() == [1, 2] and obs.inlier.tolist() == [True, False]
    assert obs.alpha[1] == pytest.approx(math.radians(2.5)) and np.isnan(obs.range_m).all()


@pytest.mark.parametrize(
    "lines, match",
    [
        ([HEADER] + ["1,1,1,1,1,2.0,30,10"] * 5 + ["2,1,1,1,0,nan,30,10"], r"line 7: column parallax_deg is 'nan'"),
        ([HEADER, "1,1,1,1,1,2.0,30,10", "2,1,1,1,1,2.0,30"], r"line 3: 7 fields, header has 8"),
        ([HEADER, "1,1,1,1,2,2.0,30,10"], r"line 2: column inlier: expected 0/1, got '2'"),
        ([HEADER, "1,1,1,1,1,2.0,30,10", "x,1,1,1,1,2.0,30,10"], r"line 3: column t_ns: not an integer: 'x'"),
        ([HEADER, "1,1,1,1,1,2.0,30,far"], r"line 2: column range_m: not a number: 'far'"),
        ([HEADER, "1,1,1,1,1,2.0,180.5,1"], r"line 2: column view_deg = 180.5 outside \[0, 180\] deg"),
    ],
)
def test_malformed_csv_one_line_errors(tmp_path, lines, match):
    path = _lines(tmp_path, "bad.csv", lines)
    with pytest.raises(InputDataError, match=match) as info:
        read_landmarks(path, FIT_FIELDS if "range_m" not in match else None)
    assert str(info.value).startswith(str(path)) and "\n" not in str(info.value)


def _parquet(path, **cols):
    base = {
        "t_ns": pa.array([1, 1, 2], pa.int64()),
        "leaf_id": pa.array([1, 1, 2], pa.int64()),
        "trunk_id": pa.array([1, 1, 2], pa.int64()),
        "landmark_id": pa.array([0, 1, 0], pa.int64()),
        "inlier": pa.array([True, False, True]),
        "parallax_deg": pa.array([1.0, 2.0, 3.0]),
        "view_deg": pa.array([10.0, 20.0, 30.0]),
        "range_m": pa.array([5.0, None, 7.0]),
    }
    base.update(cols)
    pq.write_table(pa.table({k: v for k, v in base.items() if v is not None}), path)
    return path


def test_parquet_typed_input_and_errors(tmp_path):
    obs = read_landmarks(_parquet(tmp_path / "ok.parquet", inlier=pa.array([1, 0, 1], pa.int8())))
    assert obs.inlier.tolist() == [True, False, True] and np.isnan(obs.range_m[1])
    cases = [
        (dict(view_deg=pa.array([10.0, float("nan"), 30.0])), r"row 2: column view_deg is 'nan'"),
        (dict(parallax_deg=pa.array([1.0, 2.0, None])), r"row 3: column parallax_deg is empty"),
        (dict(parallax_deg=pa.array([1.0, 200.0, 3.0])), r"row 2: column parallax_deg = 200.0 outside"),
        (dict(inlier=pa.array([0, 3, 1], pa.int64())), r"row 2: column inlier: expected 0/1, got 3"),
        (dict(view_deg=pa.array(["a", "b", "c"])), r"column view_deg has type string"),
        (dict(trunk_id=None), r"missing column\(s\) trunk_id"),
    ]
    for k, (cols, match) in enumerate(cases):
        path = _parquet(tmp_path / f"bad{k}.parquet", **cols)
        with pytest.raises(InputDataError, match=match) as info:
            read_landmarks(path)
        assert str(info.value).startswith(str(path))
    not_parquet = tmp_path / "text.parquet"
    not_parquet.write_text("t_ns\n1\n")
    with pytest.raises(InputDataError, match="not a Parquet file"):
        read_landmarks(not_parquet)
    with pytest.raises(InputDataError, match="cannot read"):
        read_landmarks(tmp_path / "missing.parquet")


def test_fit_command_on_parquet_equals_csv(tmp_path):
    obs = simulate_observations(PerceptionModel.thesis(), 20_000, np.random.default_rng(5), name="z")
    write_landmarks(tmp_path / "lm.csv", obs)
    write_landmarks(tmp_path / "lm.parquet", obs)
    models = []
    for name in ("lm.csv", "lm.parquet"):
        res = CliRunner().invoke(main, ["fit", str(tmp_path / name), "--out", str(tmp_path / f"{name}.json")])
        assert res.exit_code == 0, res.output
        assert "c1 =" in res.output
        models.append(PerceptionModel.load(tmp_path / f"{name}.json").constants)
    assert np.allclose(models[0], models[1], rtol=1e-9)
