"""The run files, each from its one module (vtr/app/runfiles/): what a writer writes its reader reads back, and a
damaged file is a one-line DataError naming the file, the line and the column."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from vtr.app.runfiles import envelope_csv, frames_csv, localization_csv, state_csv, summary_csv
from vtr.errors import DataError
from vtr.geometry import exp_se3
from vtr.navigation.localization import Localization, LocalizationStatus
from vtr.navigation.repeat_state import StateTable
from vtr.types import FrameKind, FrameRecord

finite = st.floats(-1e3, 1e3, allow_nan=False)
ids = st.integers(-1, 2**40)


@st.composite
def localizations(draw) -> Localization:
    xi = np.array(draw(st.lists(st.floats(-1.0, 1.0), min_size=6, max_size=6)))
    var = np.array(draw(st.lists(st.floats(1e-12, 1e2), min_size=6, max_size=6)))
    return Localization(
        t_ns=draw(st.integers(0, 2**62)),
        leaf_id=draw(ids),
        trunk_id=draw(ids),
        twig_id=draw(ids),
        branch_id=draw(ids),
        success=draw(st.booleans()),
        matches=draw(st.integers(0, 10**5)),
        inliers=draw(st.integers(0, 10**5)),
        T_leaf_trunk=exp_se3(xi),
        covariance=np.diag(var),
        consecutive_failures=draw(st.integers(0, 100)),
        distance_since_success_m=draw(st.floats(0.0, 1e4)),
        status=draw(st.sampled_from(list(LocalizationStatus))),
        direction=draw(st.sampled_from([1, -1])),
        experiences=tuple(draw(st.lists(st.integers(1, 2**31 - 1), max_size=3, unique=True))),
    )


@settings(max_examples=25, deadline=None)
@given(st.lists(localizations(), max_size=5))
def test_localization_csv_reads_back_what_it_wrote(tmp_path_factory, locs):
    path = tmp_path_factory.mktemp("loc") / "localization.csv"
    with open(path, "w", newline="") as f:
        w = localization_csv.LocalizationWriter(f)
        for loc in locs:
            w.write(loc)
    back = localization_csv.read_localization_csv(path)
    assert len(back) == len(locs)
    for a, b in zip(locs, back, strict=True):
        for name in (
            "t_ns",
            "leaf_id",
            "trunk_id",
            "twig_id",
            "branch_id",
            "success",
            "matches",
            "inliers",
            "consecutive_failures",
            "status",
            "direction",
            "experiences",
        ):
            assert getattr(a, name) == getattr(b, name), name
        assert b.distance_since_success_m == pytest.approx(a.distance_since_success_m, abs=5e-4)
        np.testing.assert_allclose(b.T_leaf_trunk, a.T_leaf_trunk, atol=1e-8)  # 9 decimals
        np.testing.assert_allclose(np.diag(b.covariance), np.diag(a.covariance), rtol=1e-6)  # 7 significant digits


@settings(max_examples=25, deadline=None)
@given(st.integers(0, 6), st.data())
def test_state_csv_reads_back_what_it_wrote(tmp_path_factory, n, data):
    def arr(*shape: int) -> np.ndarray:
        size = int(np.prod(shape))
        return np.array(data.draw(st.lists(finite, min_size=size, max_size=size))).reshape(shape)

    table = StateTable(
        t_ns=np.sort(np.array(data.draw(st.lists(st.integers(0, 2**62), min_size=n, max_size=n)), np.int64)),
        position=arr(n, 3),
        velocity=arr(n, 3),
        acceleration=arr(n, 3),
        yaw=arr(n),
        trunk_id=np.array(data.draw(st.lists(ids, min_size=n, max_size=n)), np.int64),
        lateral=np.where(np.arange(n) % 2, np.nan, arr(n)),
        vertical=arr(n),
        along_track=arr(n),
        localized=np.arange(n) % 2 == 0,
    )
    path = tmp_path_factory.mktemp("state") / "state.csv"
    state_csv.write_state_csv(path, table)
    back = state_csv.read_state_csv(path)
    np.testing.assert_array_equal(back.t_ns, table.t_ns)
    np.testing.assert_array_equal(back.trunk_id, table.trunk_id)
    np.testing.assert_array_equal(back.localized, table.localized)
    for name in ("position", "velocity", "acceleration", "lateral", "vertical", "along_track"):
        np.testing.assert_allclose(getattr(back, name), getattr(table, name), atol=5e-7, err_msg=name)
    np.testing.assert_allclose(back.yaw, table.yaw, atol=5e-9)


def test_frames_csv_columns(tmp_path):
    records = [
        FrameRecord(t_ns=10 * i, kind=kind, matches=100 + i, inliers=50 + i, vertex_id=i // 2, new_vertex=i % 2 == 0)
        for i, kind in enumerate([FrameKind.CREATE_VERTEX, FrameKind.DO_NOTHING, FrameKind.FAILURE])
    ]
    frames_csv.write_frames_csv(tmp_path / "frames.csv", records)
    c = frames_csv.read_frames_csv(tmp_path / "frames.csv")
    assert list(c["result"]) == ["CREATE_VERTEX", "DO_NOTHING", "FAILURE"]
    np.testing.assert_array_equal(c["t_ns"], [0, 10, 20])
    np.testing.assert_array_equal(c["keyframe_id"], [0, 0, 1])


@pytest.mark.parametrize(
    "damage, named",
    [
        (lambda text: text.replace("t_ns,", "time,", 1), "not a state.csv"),
        (lambda text: text.rsplit(",", 1)[0] + "\n", ":3: 23 cells"),
        (lambda text: text.replace("\n1", "\nx1", 1), ":2: column t_ns: 'x1"),
        (lambda text: text.replace(",0,0,unknown,", ",2,0,unknown,"), ":3: column localized: '2' is not 0 or 1"),
    ],
)
def test_a_damaged_state_csv_is_one_line_naming_it(tmp_path, damage, named):
    table = StateTable(
        t_ns=np.array([1, 2], np.int64),
        position=np.zeros((2, 3)),
        velocity=np.zeros((2, 3)),
        acceleration=np.zeros((2, 3)),
        yaw=np.zeros(2),
        trunk_id=np.array([5, 6]),
        lateral=np.zeros(2),
        vertical=np.zeros(2),
        along_track=np.zeros(2),
        localized=np.array([True, False]),
    )
    path = tmp_path / "state.csv"
    state_csv.write_state_csv(path, table)
    path.write_text(damage(path.read_text()))
    with pytest.raises(DataError) as err:
        state_csv.read_state_csv(path)
    message = str(err.value)
    assert "\n" not in message and str(path) in message and named in message, message


def test_summary_csv_reads_back_what_it_wrote(tmp_path):
    from vtr.app.batch import RunOutcome

    rows = [
        RunOutcome("r", "teach", "teach", "finished", frames=9, vertices=5, seconds=1.25),
        RunOutcome("r", "rep", "repeat", "finished", 7, 5, 4, 33.5, 2.0, None, "rerun: config, frames changed"),
        RunOutcome("r", "bad", "repeat", "failed", error='DataError: x, "y"\nline two'),
    ]
    summary_csv.write_summary_csv(tmp_path / "summary.csv", rows)
    back = summary_csv.read_summary_csv(tmp_path / "summary.csv")
    assert [b["name"] for b in back] == ["teach", "rep", "bad"]
    assert back[1] == {
        "route": "r",
        "name": "rep",
        "kind": "repeat",
        "status": "finished",
        "frames": 7,
        "vertices": 5,
        "localized": 4,
        "median_inliers": 33.5,
        "seconds": 2.0,
        "error": None,
        "changed": "rerun: config, frames changed",
        "localized_pct": 80.0,
    }
    assert back[2]["error"] == 'DataError: x, "y"\nline two' and back[2]["frames"] is None
    (tmp_path / "summary.csv").write_text((tmp_path / "summary.csv").read_text().replace(",9,5,", ",nine,5,"))
    with pytest.raises(DataError, match=r"summary.csv:2: column frames: 'nine' is not an integer"):
        summary_csv.read_summary_csv(tmp_path / "summary.csv")


def test_envelope_csv_reads_back_what_it_wrote(tmp_path):
    directions = envelope_csv.DIRECTIONS
    rows = [
        envelope_csv.envelope_row(
            7,
            np.array([1.23456, -2.0, 0.5]),
            0.25,
            4.56789,
            dict(zip(directions, [1.0, 2.5, 0.25, 3.0], strict=True)),
            dict(zip(directions, [True, False, False, True], strict=True)),
            {"up": True},
        )
    ]
    with open(tmp_path / "envelope.csv", "w", newline="") as fh:
        envelope_csv.write_envelope_rows(fh, rows)
    c = envelope_csv.read_envelope_csv(tmp_path / "envelope.csv")
    assert c["vertex_id"].tolist() == [7] and c["x_m"].tolist() == [1.2346] and c["bound_taught"].tolist() == [4.568]
    assert c["heading_deg"][0] == pytest.approx(np.degrees(0.25), abs=1e-3)
    assert c["right_m"].tolist() == [2.5] and c["down_capped"].tolist() == [True]
    assert c["up_extrapolated"].tolist() == [True] and c["left_extrapolated"].tolist() == [False]
