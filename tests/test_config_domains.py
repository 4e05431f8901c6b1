"""Every config field has a declared domain: wrong types, out-of-range and NaN values are refused
with a one-line ConfigError naming ``section.key``; any in-domain value loads."""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import pytest
import yaml
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from vtr.config import MOVED_KEYS, Choice, Config, Range, config_keys
from vtr.errors import ConfigError

KEYS = config_keys()
IDS = [f"{s}.{k}" for s, k, _ in KEYS]


def _one_line(err: pytest.ExceptionInfo, key: str) -> str:
    msg = str(err.value)
    assert "\n" not in msg
    assert key in msg
    return msg


def _wrong_type(domain) -> object:
    return "7" if isinstance(domain, Range) else 7


def _out_of_range(domain) -> object:
    if isinstance(domain, Choice):
        return "no-such-choice"
    return domain.lo - 1 if domain.integer else domain.lo - abs(domain.lo) - 1.0


@pytest.mark.parametrize(("section", "key", "domain"), KEYS, ids=IDS)
def test_wrong_type_names_the_key(section, key, domain):
    with pytest.raises(ConfigError) as err:
        Config.from_dict({section: {key: _wrong_type(domain)}}, "my.yaml")
    msg = _one_line(err, f"{section}.{key}")
    assert msg.startswith("my.yaml: ")


@pytest.mark.parametrize(("section", "key", "domain"), KEYS, ids=IDS)
def test_out_of_range_names_the_key_and_the_range(section, key, domain):
    with pytest.raises(ConfigError) as err:
        Config.from_dict({section: {key: _out_of_range(domain)}})
    msg = _one_line(err, f"{section}.{key}")
    assert domain.describe() in msg


@pytest.mark.parametrize(("section", "key", "domain"), KEYS, ids=IDS)
def test_nan_and_infinity_refused(section, key, domain):
    for bad in (math.nan, math.inf, -math.inf):
        with pytest.raises(ConfigError) as err:
            Config.from_dict({section: {key: bad}})
        _one_line(err, f"{section}.{key}")


@pytest.mark.parametrize(
    ("section", "key", "domain"),
    [k for k in KEYS if isinstance(k[2], Range)],
    ids=[i for i, k in zip(IDS, KEYS, strict=True) if isinstance(k[2], Range)],
)
def test_bool_is_not_a_number(section, key, domain):
    with pytest.raises(ConfigError) as err:
        Config.from_dict({section: {key: True}})
    assert "bool" in _one_line(err, f"{section}.{key}")


@pytest.mark.parametrize(("section", "key", "domain"), KEYS, ids=IDS)
def test_constructed_in_code_is_validated_too(section, key, domain):
    kind = type(getattr(Config(), section))
    with pytest.raises(ConfigError) as err:
        kind(**{key: _out_of_range(domain)})
    assert _one_line(err, f"{section}.{key}").startswith(f"config: {section}.{key} ")
    with pytest.raises(ConfigError) as err:  # a changed copy is checked the same way
        Config().replace(section, **{key: _wrong_type(domain)})
    _one_line(err, f"{section}.{key}")


@pytest.mark.parametrize(("section", "key", "domain"), KEYS, ids=IDS)
def test_sections_are_frozen(section, key, domain):
    part = getattr(Config(), section)
    with pytest.raises(dataclasses.FrozenInstanceError):
        setattr(part, key, getattr(part, key))


def test_defaults_are_inside_their_domains():
    cfg = Config()
    for section in dataclasses.fields(cfg):
        part = getattr(cfg, section.name)
        assert type(part)(**dataclasses.asdict(part)) == part
    assert len(KEYS) >= 60


def test_integer_valued_float_is_an_integer_and_fractions_are_refused():
    cfg = Config.from_dict({"features": {"n_features": 1500.0}})
    assert cfg.features.n_features == 1500 and isinstance(cfg.features.n_features, int)
    with pytest.raises(ConfigError, match=r"features\.n_features must be an integer"):
        Config.from_dict({"features": {"n_features": 1500.5}})


def _in_domain(domain) -> st.SearchStrategy:
    if isinstance(domain, Choice):
        return st.sampled_from(domain.values)
    if domain.integer:
        lo = int(domain.lo) + (1 if domain.lo_open else 0)
        hi = int(domain.hi) - (1 if domain.hi_open else 0)
        return st.integers(lo, hi)
    return st.floats(
        domain.lo,
        domain.hi,
        exclude_min=domain.lo_open,
        exclude_max=domain.hi_open,
        allow_nan=False,
        allow_infinity=False,
    )


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.data())
def test_any_in_domain_value_loads(data):
    section, key, domain = data.draw(st.sampled_from(KEYS))
    value = data.draw(_in_domain(domain))
    try:
        cfg = Config.from_dict({section: {key: value}})
    except ConfigError as err:
        # only a cross-field rule may refuse a single in-domain value; it names both keys
        assert "must be" in str(err) and str(err).count(".") >= 2 and key in str(err)
        return
    assert getattr(getattr(cfg, section), key) == value


# ------------------------------------------------------------------ the reported cases


@pytest.mark.parametrize(
    ("yaml_text", "key"),
    [
        ("features:\n  n_levels: 0\n", "features.n_levels"),  # was a segfault in OpenCV's ORB
        ("features:\n  grid_rows: 0\n", "features.grid_rows"),  # was ZeroDivisionError
        ("odometry:\n  window_keyframes: 0\n", "odometry.window_keyframes"),
        ("stereo:\n  refine_half_window: -2\n", "stereo.refine_half_window"),
        ("estimation:\n  ransac_confidence: 5\n", "estimation.ransac_confidence"),
        ("odometry:\n  keyframe_translation_m: .nan\n", "odometry.keyframe_translation_m"),  # was accepted
        ("features:\n  n_features: true\n", "features.n_features"),  # was accepted as 1
        ("odometry:\n  ransac_threshold_px: -1\n", "odometry.ransac_threshold_px"),
        ("stereo:\n  pixel_sigma: -1.0\n", "stereo.pixel_sigma"),
        ("smoothing:\n  rate_hz: 1e9\n", "smoothing.rate_hz"),
        ("features:\n  n_features: '2000'\n", "features.n_features"),
    ],
)
def test_reported_config_cases(tmp_path: Path, yaml_text, key):
    f = tmp_path / "bad.yaml"
    f.write_text(yaml_text)
    with pytest.raises(ConfigError) as err:
        Config.load(f)
    msg = _one_line(err, key)
    assert str(f) in msg


@pytest.mark.parametrize(
    ("content", "expect"),
    [
        (bytes(range(256)) * 4, "not UTF-8"),
        (b"- a\n- b\n", "expected a mapping"),
        (b"42\n", "expected a mapping"),
        (b"features: [1, 2]\n", "must be a mapping"),
        (b"features:\n  n_features: [\n", "cannot parse"),
        (b"nosuch:\n  a: 1\n", "unknown section"),
    ],
)
def test_unreadable_config_files(tmp_path: Path, content, expect):
    f = tmp_path / "c.yaml"
    f.write_bytes(content)
    with pytest.raises(ConfigError, match=expect) as err:
        Config.load(f)
    assert "\n" not in str(err.value) and str(f) in str(err.value)


def test_toml_binary_and_folder(tmp_path: Path):
    t = tmp_path / "c.toml"
    t.write_bytes(b"\xff\xfe[features]\n")
    with pytest.raises(ConfigError, match="not UTF-8"):
        Config.load(t)
    with pytest.raises(ConfigError, match="is a folder, not a file"):
        Config.load(tmp_path)
    with pytest.raises(ConfigError, match="no such config file"):
        Config.load(tmp_path / "absent.toml")


def test_cross_field_rules_name_both_keys():
    # was a raw cv2.error from OpenCV's pyramid (4 ** 5 = 1024: the top level of a 370 px image is empty)
    with pytest.raises(ConfigError, match=r"features\.scale_factor.*features\.n_levels.*1024"):
        Config.from_dict({"features": {"n_levels": 6, "scale_factor": 4.0}})
    assert Config.from_dict({"features": {"n_levels": 4, "scale_factor": 4.0}}).features.n_levels == 4
    with pytest.raises(ConfigError, match=r"stereo\.min_disparity_px.*stereo\.max_disparity_px"):
        Config.from_dict({"stereo": {"min_disparity_px": 200.0}})
    with pytest.raises(ConfigError, match=r"odometry\.keyframe_min_inliers.*odometry\.min_inliers"):
        Config.from_dict({"odometry": {"min_inliers": 100}})


def test_cross_field_rules_hold_for_sections_built_in_code():
    from vtr.config import FeatureConfig, LocalizationConfig, StereoConfig

    with pytest.raises(ConfigError, match=r"^config: features\.scale_factor.*features\.n_levels.*1024"):
        FeatureConfig(n_levels=6, scale_factor=4.0)
    with pytest.raises(ConfigError, match=r"^config: stereo\.min_disparity_px.*stereo\.max_disparity_px"):
        StereoConfig(min_disparity_px=200.0)
    with pytest.raises(ConfigError, match=r"^config: localization\.min_matches.*localization\.min_inliers"):
        LocalizationConfig(min_inliers=100)


def test_the_whole_config_reaches_only_the_run_roots():
    """Below ``vtr/app`` and ``vtr/cli`` a class is handed its sections, never the whole ``Config``: only the
    run-level roots (and the factories that split a ``Config`` into sections) import it, and nothing checks a
    section again (sections check themselves when built: ``validate``/``check_section`` are gone)."""
    import ast

    root = Path(__file__).resolve().parents[1] / "vtr"
    roots = {
        "navigation/teach.py",
        "navigation/repeat.py",
        "control/online.py",
        "vo/odometry.py",  # OdometrySettings.of(config)
        "navigation/experiences.py",
    }  # single_experience(config) -> Config
    importers, checkers = set(), set()
    for path in root.rglob("*.py"):
        rel = path.relative_to(root).as_posix()
        if rel.startswith(("app/", "cli/")) or rel in ("config.py", "__init__.py"):
            continue
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ImportFrom) and (node.module or "").endswith("config"):
                names = {a.name for a in node.names}
                if "Config" in names:
                    importers.add(rel)
                if names & {"validate", "check_section"}:
                    checkers.add(rel)
            if (
                isinstance(node, ast.Attribute)
                and node.attr in ("validate", "check_section")
                and isinstance(node.value, ast.Name)
                and node.value.id in ("config", "cfg", "self")
            ):
                checkers.add(rel)
    assert importers <= roots, sorted(importers - roots)
    assert not checkers, sorted(checkers)


# ------------------------------------------------------------------ keys of older versions


@pytest.mark.parametrize(("old", "new"), sorted(MOVED_KEYS.items()))
def test_a_moved_key_still_loads_with_a_one_line_warning(tmp_path: Path, old, new):
    section, key = old.split(".")
    new_section, new_key = new.split(".")
    value = getattr(getattr(Config(), new_section), new_key)
    changed = value + 1 if isinstance(value, int) else value / 2
    f = tmp_path / "old.yaml"
    f.write_text(yaml.safe_dump({section: {key: changed}}))
    told: list[str] = []
    cfg = Config.load(f, warn=told.append)
    assert getattr(getattr(cfg, new_section), new_key) == changed
    assert told == [f"{f}: {old} is now {new} (loaded as {new}; rename it in the file)"]
    with pytest.warns(FutureWarning, match=f"{old} is now {new}"):  # without a listener: a FutureWarning
        assert getattr(getattr(Config.load(f), new_section), new_key) == changed


def test_a_moved_key_given_twice_or_out_of_its_domain_names_the_new_key(tmp_path: Path):
    with pytest.raises(ConfigError, match=r"^c\.yaml: odometry\.seed and run\.seed both given.*keep run\.seed$"):
        Config.from_dict({"odometry": {"seed": 3}, "run": {"seed": 4}}, "c.yaml", warn=lambda _line: None)
    with pytest.raises(ConfigError, match=r"^c\.yaml: estimation\.ratio_test must be"):
        Config.from_dict({"odometry": {"ratio_test": 2.0}}, "c.yaml", warn=lambda _line: None)
    with pytest.raises(ConfigError, match=r"localization\.huber_px \(did you mean estimation\.huber_px\?\)"):
        Config.from_dict({"localization": {"huber_px": 2.0}})


def test_the_cli_warns_in_one_line_on_a_moved_key(tmp_path: Path):
    from click.testing import CliRunner

    from vtr.cli.common import load_config

    f = tmp_path / "old.yaml"
    f.write_text("odometry:\n  seed: 3\n  min_inliers: 16\n")
    runner = CliRunner()
    with runner.isolation() as (_out, err, *_rest):
        cfg = load_config(f)
    assert cfg.run.seed == 3 and cfg.odometry.min_inliers == 16
    line = f"warning: {f}: odometry.seed is now run.seed (loaded as run.seed; rename it in the file)\n"
    assert err.getvalue().decode() == line
