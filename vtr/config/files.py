"""Reading config (and batch manifest) files: YAML's safe loader refusing a key given twice, and the same check
for TOML (docs/configuration.md)."""

from __future__ import annotations

from typing import Any

import yaml


class DuplicateKeyError(yaml.YAMLError):
    """A key given twice in one mapping of a YAML or TOML file (the message names the key and both lines)."""


class UniqueKeyLoader(yaml.SafeLoader):
    """YAML's safe loader refusing a key given twice in one mapping (PyYAML keeps the last one silently):
    :class:`DuplicateKeyError` naming the key and both lines. The config and the batch manifest use it."""

    def construct_mapping(self, node: yaml.MappingNode, deep: bool = False) -> dict[Any, Any]:
        seen: dict[Any, int] = {}
        for key_node, _value in node.value:
            if key_node.tag == "tag:yaml.org,2002:merge":
                continue
            key = self.construct_object(key_node, deep=True)
            line = key_node.start_mark.line + 1
            try:
                first = seen.get(key)
            except TypeError:  # an unhashable key: the base class reports it
                continue
            if first is not None:
                raise DuplicateKeyError(f"key {key!r} given twice (lines {first} and {line}); keep one")
            seen[key] = line
        return super().construct_mapping(node, deep)


def toml_duplicate_key(text: str) -> str | None:
    """A key or table given twice in TOML ``text`` (simple ``key = value`` lines and ``[table]`` headers, as a
    config has), as words naming it and both lines; None when there is none (``tomllib`` checks the rest)."""
    table, seen = "", dict[str, int]()
    for lineno, raw in enumerate(text.splitlines(), 1):
        line = raw.strip()
        if not line or line.startswith("#") or line.startswith("[["):
            continue
        if line.startswith("["):
            table = line[1 : line.find("]")].strip() if "]" in line else line[1:]
            name, what = f"[{table}]", "table"
        elif "=" in line:
            key = line.split("=", 1)[0].strip().strip('"').strip("'")
            name, what = f"{table}.{key}" if table else key, "key"
        else:
            continue
        if name in seen:
            return f"{what} {name!r} given twice (lines {seen[name]} and {lineno}); keep one"
        seen[name] = lineno
    return None
