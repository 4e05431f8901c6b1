"""perception-model refuses what it cannot use: model files of an unknown version or format,
MLE fits on data that cannot identify the constants, absurd path positions; one line, exit 1."""

from __future__ import annotations

import json

import numpy as np
import pytest
from click.testing import CliRunner

from perception_model.cli import main
from perception_model.errors import FitError, InputDataError, ModelFileError
from perception_model.fit import Samples, fit_mle
from perception_model.io import read_positions
from perception_model.model import FILE_VERSION, PerceptionModel

HEADER = "t_ns,leaf_id,trunk_id,landmark_id,inlier,parallax_deg,view_deg,range_m,matched\n"


def _run(args):
    return CliRunner().invoke(main, [str(a) for a in args])


def _one_line(result, match: str) -> None:
    assert result.exit_code == 1, result.output
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("perception-model: error:") and match in lines[0], result.stderr
    assert "Traceback" not in result.output


@pytest.mark.parametrize("version", [99, 0, "1", True, None])
def test_unknown_model_version_refused(tmp_path, version):
    d = PerceptionModel.thesis().to_dict()
    d["version"] = version
    f = tmp_path / "m.json"
    f.write_text(json.dumps(d))
    with pytest.raises(ModelFileError, match=rf"{f}: model file version .* is not supported"):
        PerceptionModel.load(f)
    _one_line(_run(["evaluate", f, f]), "is not supported")


def test_current_version_and_versionless_files_load(tmp_path):
    d = PerceptionModel.thesis().to_dict()
    assert d["version"] == FILE_VERSION
    f = tmp_path / "m.json"
    f.write_text(json.dumps(d))
    assert PerceptionModel.load(f) == PerceptionModel.thesis()
    del d["version"], d["format"]
    f.write_text(json.dumps(d))
    assert PerceptionModel.load(f) == PerceptionModel.thesis()


def test_other_format_refused(tmp_path):
    d = PerceptionModel.thesis().to_dict()
    d["format"] = "something-else"
    f = tmp_path / "m.json"
    f.write_text(json.dumps(d))
    with pytest.raises(ModelFileError, match="format 'something-else'"):
        PerceptionModel.load(f)


def _landmarks(path, rng, n=600, alpha=None, theta=None, p=0.5):
    a = rng.uniform(0, 40, n) if alpha is None else np.full(n, alpha)
    t = rng.uniform(0, 60, n) if theta is None else np.full(n, theta)
    y = (rng.random(n) < p).astype(int)
    with open(path, "w") as f:
        f.write(HEADER)
        for i in range(n):
            f.write(f"{i // 20},{i // 20},{i // 20},{i},{y[i]},{a[i]:.4f},{t[i]:.4f},10.0,{y[i]}\n")


@pytest.mark.parametrize(
    ("alpha", "theta", "p", "match"),
    [
        (1.0, 1.0, 0.5, "same parallax angle"),  # one bin: was a NaN in model.json and a traceback
        (None, 5.0, 0.5, "same view angle"),
        (None, None, 1.0, "all 600 observations are inliers"),
        (None, None, 0.0, "all 600 observations are outliers"),
    ],
)
def test_mle_on_degenerate_data(tmp_path, alpha, theta, p, match):
    f = tmp_path / "lm.csv"
    _landmarks(f, np.random.default_rng(0), alpha=alpha, theta=theta, p=p)
    r = _run(["fit", f, "--out", tmp_path / "m", "--method", "mle"])
    _one_line(r, match)
    assert not (tmp_path / "m").exists()
    a = np.radians(np.full(10, 1.0))
    with pytest.raises(FitError, match="same parallax angle"):
        fit_mle(Samples(a, np.radians(np.linspace(0, 50, 10)), np.arange(10) % 2))


@pytest.mark.parametrize("bad", ["1e308", "-2e7", "inf", "nan"])
def test_absurd_positions_refused(tmp_path, bad):
    f = tmp_path / "pos.csv"
    f.write_text(f"x,y,z\n0,0,1\n{bad},0,0\n")
    with pytest.raises(InputDataError, match=rf"{f}, line 3"):
        read_positions(f)
    model = tmp_path / "m.json"
    PerceptionModel.thesis().save(model)
    lm = tmp_path / "lm.csv"
    lm.write_text("x,y,z\n0,0,5\n1,0,6\n")
    _one_line(_run(["constraint", model, "--landmarks", lm, "--positions", f]), "line 3")
