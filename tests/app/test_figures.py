"""Figures stand on their own: a title, every axis labelled with its unit; the envelope marks capped values
and draws heading arrows long enough to see; fit.png shows the observations per bin."""

from __future__ import annotations

import re

import matplotlib
import numpy as np
import pytest

matplotlib.use("Agg")
from matplotlib.figure import Figure  # noqa: E402

UNIT = re.compile(r"\[[^\]]+\]")


@pytest.fixture
def saved(monkeypatch):
    figures: list[Figure] = []
    real = Figure.savefig

    def keep(self, *args, **kwargs):
        figures.append(self)
        return real(self, *args, **kwargs)

    monkeypatch.setattr(Figure, "savefig", keep)
    return figures


def check_labels(fig: Figure) -> None:
    assert fig._suptitle is not None and fig._suptitle.get_text()
    for ax in fig.axes:
        if ax.get_label() == "<colorbar>":
            assert UNIT.search(ax.get_ylabel() or ax.get_xlabel()), "colorbar without a unit"
            continue
        assert ax.get_title(), ax
        assert UNIT.search(ax.get_xlabel()), ax.get_xlabel()
        assert UNIT.search(ax.get_ylabel()) or ax.get_ylabel() == "" and ax.get_shared_y_axes().get_siblings(ax), ax


def test_envelope_figure_marks_capped_values_and_shows_headings(saved, tmp_path):
    from vtr.app.perception import EnvelopeRow, plot_envelope

    rows = [
        EnvelopeRow(
            i,
            np.array([2.0 * i, 0.0, 10.0]),
            0.0,
            40.0,
            {"left": 20.0 if i % 2 else 8.0, "right": 6.0, "up": 5.0, "down": 3.0},
            {"left": bool(i % 2), "right": False, "up": False, "down": False},
        )
        for i in range(20)
    ]
    plot_envelope(rows, tmp_path / "e.png", l_min=30.0, title="test route")
    (fig,) = saved
    check_labels(fig)
    plan, offsets = fig.axes
    quiver = next(c for c in plan.collections if type(c).__name__ == "Quiver")
    assert np.hypot(quiver.U, quiver.V).min() > 0.05 * 38.0  # arrows of a visible length in metres
    labels = [line.get_label() for line in offsets.get_lines()]
    assert "left: capped (10 of 20)" in labels
    capped = next(line for line in offsets.get_lines() if line.get_label() == "left: capped (10 of 20)")
    assert len(capped.get_xdata()) == 10 and np.all(capped.get_ydata() == 20.0)


def test_fit_figure_shows_counts(saved, tmp_path):
    from perception_model.fit import FitSettings, fit_observations
    from perception_model.model import PerceptionModel
    from perception_model.plots import plot_fit
    from perception_model.synthetic import simulate_observations

    obs = simulate_observations(PerceptionModel.thesis(), 20_000, np.random.default_rng(0), name="r")
    result = fit_observations(obs, FitSettings(method="binned", holdout_fraction=0.0))
    plot_fit(result, tmp_path / "fit.png", 10)
    (fig,) = saved
    check_labels(fig)
    assert any("observations per bin" in ax.get_title() for ax in fig.axes)
