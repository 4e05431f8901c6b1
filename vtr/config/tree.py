"""The whole configuration (:class:`Config`, one field per section), loading it from YAML or TOML, the keys of
older versions (:data:`MOVED_KEYS`) and the helpers of ``vtr config`` (docs/configuration.md)."""

from __future__ import annotations

import dataclasses
import tomllib
import warnings
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, cast

import yaml

from ..errors import ConfigError
from .domains import Choice, Range, Section, SectionError, domain_of
from .files import DuplicateKeyError, UniqueKeyLoader, toml_duplicate_key
from .sections import (
    ControlConfig,
    EstimationConfig,
    ExperienceConfig,
    FeatureConfig,
    LocalizationConfig,
    MapConfig,
    OdometryConfig,
    PlaceConfig,
    RunConfig,
    SmoothingConfig,
    StereoConfig,
)


@dataclass(frozen=True)
class Config:
    """The whole pipeline configuration."""

    run: RunConfig = field(default_factory=RunConfig)
    features: FeatureConfig = field(default_factory=FeatureConfig)
    stereo: StereoConfig = field(default_factory=StereoConfig)
    odometry: OdometryConfig = field(default_factory=OdometryConfig)
    estimation: EstimationConfig = field(default_factory=EstimationConfig)
    localization: LocalizationConfig = field(default_factory=LocalizationConfig)
    place: PlaceConfig = field(default_factory=PlaceConfig)
    smoothing: SmoothingConfig = field(default_factory=SmoothingConfig)
    map: MapConfig = field(default_factory=MapConfig)
    control: ControlConfig = field(default_factory=ControlConfig)
    experiences: ExperienceConfig = field(default_factory=ExperienceConfig)

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)

    def to_yaml(self, comments: bool = False) -> str:
        """The configuration as YAML; with ``comments``, every section and key preceded by its comment in
        :mod:`vtr.config.sections` (units, measurements) and its domain (what ``vtr config`` prints; still loadable)."""
        if not comments:
            return yaml.safe_dump(self.to_dict(), sort_keys=False)
        lines = [
            "# vtr configuration: every key with its default, its comment (vtr/config/sections.py), its domain.",
            "# Keep only the keys you change; load with --config FILE.",
            "",
        ]
        for section in dataclasses.fields(self):
            part = getattr(self, section.name)
            doc = (type(part).__doc__ or "").strip().splitlines()[0]
            lines.append(f"{section.name}:  # {doc}")
            notes = field_comments(type(part))
            for f in dataclasses.fields(part):
                for text in notes.get(f.name, []):
                    lines.append(f"  # {text}")
                lines.append(f"  # domain: {domain_of(f).describe()}")
                value = yaml.safe_dump({f.name: getattr(part, f.name)}, default_flow_style=True).strip()
                lines.append(f"  {value.removeprefix('{').removesuffix('}')}")
            lines.append("")
        return "\n".join(lines)

    def replace(self, section: str, **changes: Any) -> Config:
        """A copy with ``changes`` to the keys of ``section`` (checked against their domains, as when built)."""
        return dataclasses.replace(self, **{section: dataclasses.replace(getattr(self, section), **changes)})

    @classmethod
    def from_dict(cls, data: Any, where: str = "config", warn: Callable[[str], None] | None = None) -> Config:
        """The config of a file's ``data`` (``where`` names it in errors). A key of an older version
        (:data:`MOVED_KEYS`) loads under its new name, and ``warn`` (else :func:`warnings.warn`, a
        ``FutureWarning``) is told in one line."""
        if not isinstance(data, dict):
            raise ConfigError(f"{where}: expected a mapping of sections, got {type(data).__name__}")
        data = _moved_keys(data, where, warn)
        types = {f.name: f.default_factory for f in dataclasses.fields(cls)}
        sections: dict[str, Section] = {}
        for section, values in data.items():
            if section not in types:
                hint = _did_you_mean(cls, None, section)
                raise ConfigError(
                    f"{where}: unknown section {section!r}{hint or ''} (sections: {', '.join(sorted(types))})"
                )
            if not isinstance(values, dict):
                raise ConfigError(f"{where}: section {section!r} must be a mapping of keys")
            kind = cast(type[Section], types[section])
            known = {f.name: f for f in dataclasses.fields(kind)}
            for key, value in values.items():  # in the file's order: the first bad key is the one named
                if key not in known:
                    raise ConfigError(f"{where}: unknown key {section}.{key}{_did_you_mean(cls, section, key)}")
                try:
                    domain_of(known[key]).check(value)
                except ValueError as err:
                    raise ConfigError(f"{where}: {section}.{key} {err}") from None
            try:
                sections[section] = kind(**values)
            except SectionError as err:  # a cross-field rule of the section
                raise ConfigError(f"{where}: {err.detail}") from None
        return cls(**sections)  # type: ignore[arg-type]

    @classmethod
    def load(cls, path: str | Path, warn: Callable[[str], None] | None = None) -> Config:
        """The config of a YAML or TOML file (``warn``: as in :meth:`from_dict`)."""
        from perception_model.inputs import input_problem

        path = Path(path)
        if not path.exists():
            raise ConfigError(f"{path}: no such config file")
        problem = input_problem(path)  # a folder, a named pipe or a device: never opened
        if problem is not None:
            raise ConfigError(f"{path}: {problem}")
        try:
            text = path.read_bytes().decode("utf-8")
        except OSError as err:
            raise ConfigError(f"{path}: cannot read config file ({err.strerror or err})") from None
        except UnicodeDecodeError:
            raise ConfigError(f"{path}: not a text config file (not UTF-8; expected YAML or TOML)") from None
        try:
            if path.suffix == ".toml":
                duplicate = toml_duplicate_key(text)
                if duplicate is not None:
                    raise ConfigError(f"{path}: {duplicate}")
                data = tomllib.loads(text)
            else:
                data = yaml.load(text, Loader=UniqueKeyLoader)  # noqa: S506 - a SafeLoader
        except DuplicateKeyError as err:
            raise ConfigError(f"{path}: {err}") from None
        except (yaml.YAMLError, tomllib.TOMLDecodeError) as err:
            reason = " ".join(str(err).split())
            raise ConfigError(f"{path}: cannot parse ({reason})") from None
        except RecursionError:
            raise ConfigError(f"{path}: nested too deeply to read (a config is two levels: section, key)") from None
        return cls.from_dict({} if data is None else data, str(path), warn)


#: keys that moved, ``old: new``: a config file of an older version still loads (``Config.from_dict`` warns in one
#: line naming the new key; both given is an error). The estimation settings odometry and localization share left
#: ``odometry`` for ``estimation``; the run's seed is ``run.seed``.
MOVED_KEYS: dict[str, str] = {
    **{
        f"odometry.{key}": f"estimation.{key}"
        for key in (
            "ratio_test",
            "ransac_confidence",
            "refine_iterations",
            "huber_px",
            "far_point_baselines",
            "far_disparity_weight",
            "min_near_observations",
        )
    },
    "odometry.seed": "run.seed",
}


def _moved_keys(data: dict[Any, Any], where: str, warn: Callable[[str], None] | None) -> dict[Any, Any]:
    """``data`` with the old keys of :data:`MOVED_KEYS` under their new names (a copy; ``data`` is unchanged)."""
    out = {section: dict(values) if isinstance(values, dict) else values for section, values in data.items()}
    for old, new in MOVED_KEYS.items():
        (section, key), (new_section, new_key) = old.split("."), new.split(".")
        values = out.get(section)
        if not isinstance(values, dict) or key not in values:
            continue
        target = out.setdefault(new_section, {})
        if not isinstance(target, dict):
            continue  # the malformed section is named when it is read
        if new_key in target:
            raise ConfigError(f"{where}: {old} and {new} both given; {old} is the old name of {new}: keep {new}")
        target[new_key] = values.pop(key)
        message = f"{where}: {old} is now {new} (loaded as {new}; rename it in the file)"
        if warn is None:
            warnings.warn(message, FutureWarning, stacklevel=4)
        else:
            warn(message)
    return out


def check_setting(section: str, key: str, value: Any, where: str = "config") -> Any:
    """``value`` checked against the domain of ``section.key`` (for a command-line override such as
    ``--rate``); returns it as the field's type."""
    kind = {f.name: f.default_factory for f in dataclasses.fields(Config)}[section]
    f = {f.name: f for f in dataclasses.fields(kind)}[key]  # type: ignore[arg-type]
    try:
        return domain_of(f).check(value)
    except ValueError as err:
        raise ConfigError(f"{where}: {section}.{key} {err}") from None


def config_keys() -> list[tuple[str, str, Range | Choice]]:
    """Every ``(section, key, domain)`` of the configuration, in declaration order."""
    return [
        (section.name, f.name, domain_of(f))
        for section in dataclasses.fields(Config)
        for f in dataclasses.fields(section.default_factory)  # type: ignore[arg-type]
    ]


def _did_you_mean(cls: type, section: str | None, key: str) -> str:
    """``" (did you mean features.n_features?)"`` for a mistyped key (also one put in the wrong section) or
    section; empty when nothing is close."""
    import difflib

    sections = {f.name: f.type for f in dataclasses.fields(cls)}
    keys = {f"{s}.{k.name}": k.name for s in sections for k in dataclasses.fields(getattr(cls(), s))}
    if section is None:
        close = difflib.get_close_matches(key, list(sections), n=1, cutoff=0.6)
    else:
        close = [k for k, name in keys.items() if name == key][:1]  # the right key in the wrong section
        if not close:
            close = difflib.get_close_matches(f"{section}.{key}", list(keys), n=1, cutoff=0.75)
    return f" (did you mean {close[0]}?)" if close else ""


def field_comments(section_cls: type) -> dict[str, list[str]]:
    """Comment lines of each field of a config section class, as written in this module: the comment
    lines right above the field and the comment at its end (read from the source, not hand-copied)."""
    import ast
    import inspect
    import io
    import tokenize

    source = Path(inspect.getsourcefile(section_cls) or __file__).read_text()
    comments: dict[int, str] = {}
    for tok in tokenize.generate_tokens(io.StringIO(source).readline):
        if tok.type == tokenize.COMMENT:
            comments[tok.start[0]] = tok.string.lstrip("#").strip()
    lines = source.splitlines()
    out: dict[str, list[str]] = {}
    for node in ast.walk(ast.parse(source)):
        if not (isinstance(node, ast.ClassDef) and node.name == section_cls.__name__):
            continue
        for item in node.body:
            if not (isinstance(item, ast.AnnAssign) and isinstance(item.target, ast.Name)):
                continue
            above: list[str] = []
            n = item.lineno - 1
            while n >= 1 and lines[n - 1].strip().startswith("#"):
                above.insert(0, comments.get(n, ""))
                n -= 1
            trailing = [
                comments[k]
                for k in range(item.lineno, (item.end_lineno or item.lineno) + 1)
                if k in comments and not lines[k - 1].strip().startswith("#")
            ]
            out[item.target.id] = [t for t in above + trailing if t]
    return out
