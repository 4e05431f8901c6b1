"""What users read: `vtr config` shows each key's comment and domain from vtr/config/sections.py (and loads back),
a mistyped key gets "did you mean", and records holding arrays print short."""

from __future__ import annotations

import numpy as np
import pytest
from click.testing import CliRunner

from perception_model.landmarks_file import Observations
from vtr.cli import main
from vtr.config import Config, field_comments
from vtr.errors import ConfigError
from vtr.types import StereoImages


def test_vtr_config_prints_comments_and_domains_and_loads_back(tmp_path):
    r = CliRunner().invoke(main, ["config"])
    assert r.exit_code == 0, r.output
    text = r.stdout
    assert "  # features kept per image after grid bucketing" in text  # comment above a field
    assert "  # ORB detects this many times n_features before bucketing" in text  # comment at its end
    assert "  # domain: an integer in [1, 100000]\n  n_features: 2000\n" in text
    assert text.count("# domain:") == sum(len(v) for v in Config().to_dict().values())  # every key
    (tmp_path / "c.yaml").write_text(text)
    assert Config.load(tmp_path / "c.yaml") == Config()


def test_field_comments_come_from_the_source():
    from vtr.config import FeatureConfig

    notes = field_comments(FeatureConfig)
    assert any("Linux niceness" in line for line in notes["worker_niceness"])


@pytest.mark.parametrize(
    "doc, hint",
    [
        ({"features": {"n_feature": 10}}, "did you mean features.n_features?"),
        ({"odometry": {"threads": 1}}, "did you mean features.threads?"),  # right key, wrong section
        ({"feature": {"threads": 1}}, "did you mean features?"),
    ],
)
def test_a_mistyped_key_gets_did_you_mean(doc, hint):
    with pytest.raises(ConfigError, match=hint.replace("?", r"\?")):
        Config.from_dict(doc, "my.yaml")


def test_records_with_arrays_print_short():
    img = StereoImages(t_ns=1, left=np.zeros((370, 1226), np.uint8), right=np.zeros((370, 1226), np.uint8), index=0)
    assert "<uint8 (370, 1226)>" in repr(img) and len(repr(img)) < 200
    n = 5000
    obs = Observations(np.zeros(n), np.zeros(n), np.zeros(n, bool), np.zeros(n, np.int64))
    assert len(repr(obs)) < 400 and "<float64 (5000,)>" in repr(obs)


def test_a_localization_prints_short():
    """repeat.latest (README): the landmarks record inside is summarized, not dumped (was ~64 kB)."""
    from vtr.navigation.localization import Localization

    n = 800
    obs = Observations(
        np.zeros(n),
        np.zeros(n),
        np.zeros(n, bool),
        np.zeros(n, np.int64),
        np.zeros(n, np.int64),
        np.zeros(n, np.int64),
        np.arange(n),
        np.ones(n),
    )
    loc = Localization(
        t_ns=0,
        leaf_id=1,
        trunk_id=2,
        twig_id=-1,
        branch_id=-1,
        success=True,
        matches=300,
        inliers=250,
        T_leaf_trunk=np.eye(4),
        covariance=np.eye(6) * 1e-4,
        consecutive_failures=0,
        distance_since_success_m=0.0,
        landmarks=obs,
    )
    assert len(repr(loc)) < 2500, len(repr(loc))
