"""The aerial mission of `vtr demo` step 4 on a tiny route: teach, offset repeats, model, envelope, report."""

from __future__ import annotations

import csv

from vtr.app.mission import run_aerial_mission
from vtr.config import Config


def test_tiny_aerial_mission(tmp_path):
    rep = run_aerial_mission(tmp_path / "m", Config(), length_m=9.0, lateral_m=(0.0, 3.0), held_out_m=(), ramp_m=2.0)
    assert rep.report_html.is_file() and (rep.envelope_csv.parent / "envelope.png").stat().st_size > 10_000
    rows = list(csv.DictReader(rep.envelope_csv.open()))
    assert len(rows) >= 8
    for r in rows:
        for k in ("left_m", "right_m", "up_m", "down_m"):
            assert float(r[k]) >= 0.0
    on_path = rep.rows[0]
    assert on_path.successes == on_path.localizations > 0  # the on-path repeat localizes everywhere
    # where the envelope says localization holds, the repeats localized
    for r in rep.rows:
        assert r.holds_and_localized == r.envelope_holds, r
    assert "Repeats against the envelope" in rep.report_html.read_text()


def test_the_envelope_predicts_a_failure_and_it_is_seen(tmp_path):
    """A repeat held out from the fit, far outside the envelope: the envelope says it fails, and it does not
    localize; the on-path repeat is predicted to hold and localizes."""
    rep = run_aerial_mission(
        tmp_path / "m", Config(), length_m=9.0, lateral_m=(0.0, 3.0), held_out_m=(30.0,), ramp_m=2.0
    )
    far = rep.rows[-1]
    assert far.fitted == "held out" and far.envelope_fails > 0, far
    assert far.fails_and_not_localized == far.envelope_fails, far
    assert rep.rows[0].holds_and_localized == rep.rows[0].envelope_holds > 0
