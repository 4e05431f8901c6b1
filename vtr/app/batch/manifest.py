"""The batch manifest (YAML): routes, each a teach source and any number of repeat sources, read and checked.

A run given as a mapping takes ``source`` and optionally ``name`` (its output folder), ``frames``, ``config`` and
``format``; a route (or the top level) may set ``frames``, ``config`` and ``format`` for its own runs. A route with
``experiences: true`` flies its repeats in the order listed, each on the map the earlier ones grew (every finished
repeat an experience for the next: docs/map.md "Experiences"); without it they run side by side, each against the
teach's map alone. Relative paths
are relative to the manifest's folder; errors name the file and the field. See the README's "Batches" section and
``docs/outputs.md``.
"""

from __future__ import annotations

import dataclasses
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import yaml

from perception_model.inputs import input_problem

from ...config import Config, DuplicateKeyError, UniqueKeyLoader
from ...errors import ConfigError, DataError
from .layout import RESERVED_NAMES, TEACH_FOLDER

NAME_PATTERN = re.compile(r"[A-Za-z0-9][A-Za-z0-9._-]{0,99}")  # route and run names are folder names (fullmatch)
RUN_KEYS = {"source", "name", "frames", "config", "format"}
ROUTE_KEYS = {"name", "teach", "repeats", "frames", "config", "format", "experiences"}
TOP_KEYS = {"routes", "frames", "config", "format"}


@dataclass(frozen=True)
class RunSpec:
    """One teach or repeat of a manifest: where its data is and where it writes."""

    route: str
    name: str  # output folder inside OUT/<route>/ ("teach" for the teach)
    source: Path
    frames: str | None = None
    config: Path | None = None
    fmt: str | None = None
    # the route's earlier repeats, in the order flown, whose experiences this one builds on (``experiences: true``)
    after: tuple[str, ...] = ()

    @property
    def is_teach(self) -> bool:
        return self.name == TEACH_FOLDER

    @property
    def kind(self) -> str:
        return "teach" if self.is_teach else "repeat"

    def folder(self, out: Path) -> Path:
        return Path(out) / self.route / self.name


@dataclass(frozen=True)
class RouteSpec:
    name: str
    teach: RunSpec
    repeats: tuple[RunSpec, ...]
    experiences: bool = False


@dataclass(frozen=True)
class Manifest:
    path: Path
    routes: tuple[RouteSpec, ...]

    def runs(self) -> list[RunSpec]:
        """Every run, each route's teach before its repeats."""
        return [r for route in self.routes for r in (route.teach, *route.repeats)]


class _ManifestLoader(UniqueKeyLoader):
    """YAML as written: no YAML 1.1 base-60 numbers (an unquoted ``frames: 1:10`` is the string "1:10", not 70),
    and no key given twice (:class:`vtr.config.UniqueKeyLoader`)."""


_ManifestLoader.yaml_implicit_resolvers = {
    first: [
        (tag, regexp) for tag, regexp in resolvers if tag not in ("tag:yaml.org,2002:int", "tag:yaml.org,2002:float")
    ]
    for first, resolvers in yaml.SafeLoader.yaml_implicit_resolvers.items()
}
for _tag, _pattern, _first in (
    (
        "tag:yaml.org,2002:int",
        r"^(?:[-+]?0b[0-1_]+|[-+]?0[0-7_]+|[-+]?(?:0|[1-9][0-9_]*)|[-+]?0x[0-9a-fA-F_]+)$",
        "-+0123456789",
    ),
    (
        "tag:yaml.org,2002:float",
        r"^(?:[-+]?(?:[0-9][0-9_]*)\.[0-9_]*(?:[eE][-+][0-9]+)?"
        r"|\.[0-9][0-9_]*(?:[eE][-+][0-9]+)?|[-+]?\.(?:inf|Inf|INF)|\.(?:nan|NaN|NAN))$",
        "-+0123456789.",
    ),
):
    _ManifestLoader.add_implicit_resolver(_tag, re.compile(_pattern), list(_first))


def load_manifest(path: str | Path) -> Manifest:
    """Read and check a batch manifest; errors name the file and the field."""

    path = Path(path)
    if not path.exists():
        raise DataError(f"{path}: no such manifest file")
    problem = input_problem(path)  # a folder, a named pipe or a device: never opened
    if problem is not None:
        raise DataError(f"{path}: {problem}")
    try:
        doc = yaml.load(path.read_text(encoding="utf-8-sig"), Loader=_ManifestLoader)  # noqa: S506 - a SafeLoader
    except DuplicateKeyError as err:
        raise ConfigError(f"{path}: {err}") from None
    except yaml.YAMLError as err:
        raise ConfigError(f"{path}: cannot parse YAML ({str(err).splitlines()[0]})") from err
    except RecursionError:
        raise ConfigError(f"{path}: nested too deeply to read (a manifest is routes, runs and their keys)") from None
    except (UnicodeDecodeError, OSError) as err:
        raise ConfigError(f"{path}: cannot read the manifest ({err})") from err
    if not isinstance(doc, dict) or not isinstance(doc.get("routes"), list) or not doc["routes"]:
        raise ConfigError(f"{path}: expected a mapping with a non-empty list 'routes'")
    _check_keys(doc, TOP_KEYS, f"{path}")
    base = path.parent
    defaults = _defaults(doc, {}, base, f"{path}")
    routes: list[RouteSpec] = []
    seen: set[str] = set()
    for i, entry in enumerate(doc["routes"]):
        where = f"{path}: routes[{i}]"
        if not isinstance(entry, dict):
            raise ConfigError(f"{where}: expected a mapping with name, teach, repeats")
        _check_keys(entry, ROUTE_KEYS, where)
        name = _name(entry.get("name"), f"{where}.name")
        where = f"{path}: route {name!r}"
        if name.casefold() in seen:
            raise ConfigError(f"{where}: route name used twice (names differing only in case count as one folder)")
        if name in RESERVED_NAMES or name.casefold() in {n.casefold() for n in RESERVED_NAMES}:
            raise ConfigError(
                f"{where}: {name!r} is the name of the batch's own output "
                f"({', '.join(sorted(RESERVED_NAMES))}); rename the route"
            )
        seen.add(name.casefold())
        if "teach" not in entry:
            raise ConfigError(f"{where}: no 'teach' source")
        route_defaults = _defaults(entry, defaults, base, where)
        teach = _run(entry["teach"], name, route_defaults, base, f"{where}.teach", TEACH_FOLDER)
        repeats_doc = entry.get("repeats") or []
        if not isinstance(repeats_doc, list):
            raise ConfigError(f"{where}.repeats: expected a list")
        chained = entry.get("experiences", False)
        if not isinstance(chained, bool):
            raise ConfigError(f"{where}.experiences: expected true or false, got {chained!r}")
        repeats: list[RunSpec] = []
        names = {TEACH_FOLDER}
        for j, rep in enumerate(repeats_doc):
            run = _run(rep, name, route_defaults, base, f"{where}.repeats[{j}]", None)
            if run.name.casefold() in names:
                raise ConfigError(
                    f"{where}.repeats[{j}]: output folder {run.name!r} is used twice in the route "
                    f"(give the repeat a distinct 'name')"
                )
            names.add(run.name.casefold())
            if chained:
                run = dataclasses.replace(run, after=tuple(r.name for r in repeats))
            repeats.append(run)
        routes.append(RouteSpec(name, teach, tuple(repeats), chained))
    return Manifest(path, tuple(routes))


def _check_keys(doc: dict, allowed: set[str], where: str) -> None:
    unknown = sorted(set(doc) - allowed)
    if unknown:
        raise ConfigError(f"{where}: unknown key {unknown[0]!r} (allowed: {', '.join(sorted(allowed))})")


def _name(value: Any, where: str) -> str:
    if not isinstance(value, str) or not NAME_PATTERN.fullmatch(value):
        raise ConfigError(
            f"{where}: {value!r} is not a usable folder name (1-100 letters, digits, '.', '_', '-', "
            "starting with a letter or digit)"
        )
    return value


def _path(value: Any, base: Path, where: str) -> Path:
    if not isinstance(value, str) or not value:
        raise ConfigError(f"{where}: expected a path, got {value!r}")
    p = Path(value).expanduser()
    return p if p.is_absolute() else base / p


def _defaults(doc: dict, inherited: dict, base: Path, where: str) -> dict:
    out = dict(inherited)
    if doc.get("frames") is not None:
        frames = doc["frames"]
        if not isinstance(frames, str) or any(not c.isprintable() for c in frames):
            raise ConfigError(
                f'{where}.frames: {frames!r} is not a frame range (write START:STOP:STEP, e.g. "0:100:2")'
            )
        out["frames"] = frames
    if doc.get("config") is not None:
        out["config"] = _path(doc["config"], base, f"{where}.config")
    if doc.get("format") is not None:
        if not isinstance(doc["format"], str):
            raise ConfigError(f"{where}.format: {doc['format']!r} is not a format name")
        out["fmt"] = doc["format"]
    return out


def _run(entry: Any, route: str, defaults: dict, base: Path, where: str, name: str | None) -> RunSpec:
    if isinstance(entry, str):
        entry = {"source": entry}
    if not isinstance(entry, dict) or "source" not in entry:
        raise ConfigError(f"{where}: expected a source path or a mapping with 'source'")
    _check_keys(entry, RUN_KEYS, where)
    source = _path(entry["source"], base, f"{where}.source")
    own = _defaults(entry, defaults, base, where)
    if name is None:
        name = _name(entry.get("name", source.stem), f"{where}.name")
        if name == TEACH_FOLDER:
            raise ConfigError(f"{where}.name: {name!r} is the route's teach folder; give the repeat another 'name'")
    elif "name" in entry:
        raise ConfigError(f"{where}: a teach has no 'name' (it writes OUT/<route>/teach)")
    return RunSpec(route, name, source, own.get("frames"), own.get("config"), own.get("fmt"))


def run_config(spec: RunSpec, threads: int | None) -> Config:
    config = Config.load(spec.config) if spec.config is not None else Config()
    return config if threads is None else config.replace("features", threads=threads)
