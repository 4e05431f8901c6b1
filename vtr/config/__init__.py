"""One typed configuration for the whole pipeline: ``domains`` (``Range``, ``Choice``, ``setting``, the frozen
``Section`` base), ``sections`` (every section, each default with its domain and comment), ``tree`` (``Config``,
loading, the keys of older versions), ``files`` (YAML/TOML readers refusing a key given twice).

Defaults follow the open-source VT&R3 stack (docs/README.md); benchmarks decide changes. A config
loads from YAML (or TOML) holding any subset of the sections below; unknown keys, a key given twice and
nesting deeper than a config has are one-line errors.
Dump the resolved defaults with ``vtr config``.

Every field declares its domain beside its default (``setting(default, Range(...))`` or
``Choice(...)``): type, integer-ness, finiteness and bounds. Each section is a frozen :class:`Section`
that checks its fields and its cross-field rules when built, in code or from a file, naming
``section.key`` and the allowed values in a one-line ``ConfigError``: an invalid section cannot exist,
so no value reaches OpenCV or numba unchecked and the classes handed a section never check it again
(docs/configuration.md).
"""

from __future__ import annotations

from .domains import Choice, Range, Section, SectionError, domain_of, setting
from .files import DuplicateKeyError, UniqueKeyLoader, toml_duplicate_key
from .sections import (
    DESCRIPTOR_DISTANCE,
    MAX_PYRAMID_SCALE,
    RADIUS_PX,
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
from .tree import MOVED_KEYS, Config, check_setting, config_keys, field_comments

__all__ = [
    "DESCRIPTOR_DISTANCE",
    "MAX_PYRAMID_SCALE",
    "MOVED_KEYS",
    "RADIUS_PX",
    "Choice",
    "Config",
    "ControlConfig",
    "DuplicateKeyError",
    "EstimationConfig",
    "ExperienceConfig",
    "FeatureConfig",
    "LocalizationConfig",
    "MapConfig",
    "OdometryConfig",
    "PlaceConfig",
    "Range",
    "RunConfig",
    "Section",
    "SectionError",
    "SmoothingConfig",
    "StereoConfig",
    "UniqueKeyLoader",
    "check_setting",
    "config_keys",
    "domain_of",
    "field_comments",
    "setting",
    "toml_duplicate_key",
]
