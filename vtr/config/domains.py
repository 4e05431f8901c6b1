"""The domains config fields declare beside their defaults (``setting(default, Range(...) | Choice(...))``) and
:class:`Section`, the frozen base every config section derives from: built only valid (docs/configuration.md)."""

from __future__ import annotations

import dataclasses
import math
import numbers
from dataclasses import dataclass, field
from typing import Any, ClassVar, SupportsInt, cast

from ..errors import ConfigError


@dataclass(frozen=True)
class Range:
    """Numeric domain: ``lo <= x <= hi`` (``lo_open``/``hi_open`` make a bound strict), finite;
    ``integer`` demands an integer (bool is refused either way)."""

    lo: float
    hi: float
    integer: bool = False
    lo_open: bool = False
    hi_open: bool = False

    def describe(self) -> str:
        kind = "an integer" if self.integer else "a finite number"
        return f"{kind} in {'(' if self.lo_open else '['}{self.lo:g}, {self.hi:g}{')' if self.hi_open else ']'}"

    def check(self, value: Any) -> int | float:
        """The value as int/float when inside the domain; ``ValueError`` (the reason) otherwise."""
        if isinstance(value, bool) or not isinstance(value, numbers.Real):
            raise ValueError(f"must be {self.describe()}, got {type(value).__name__}")
        if not math.isfinite(float(value)):
            raise ValueError(f"must be {self.describe()}, got {value!r}")
        if self.integer:
            if not float(value).is_integer():
                raise ValueError(f"must be {self.describe()}, got {value!r}")
            out: int | float = int(cast(SupportsInt, value))
        else:
            out = float(value)
        below = out <= self.lo if self.lo_open else out < self.lo
        above = out >= self.hi if self.hi_open else out > self.hi
        if below or above:
            raise ValueError(f"must be {self.describe()}, got {value!r}")
        return out


@dataclass(frozen=True)
class Choice:
    """Domain of a string field: one of ``values``."""

    values: tuple[str, ...]

    def __init__(self, *values: str) -> None:
        object.__setattr__(self, "values", tuple(values))

    def describe(self) -> str:
        return "one of " + ", ".join(repr(v) for v in self.values)

    def check(self, value: Any) -> str:
        if not isinstance(value, str) or value not in self.values:
            raise ValueError(f"must be {self.describe()}, got {value!r}")
        return value


def setting(default: Any, domain: Range | Choice) -> Any:
    """A config field with its default and its domain (checked when its :class:`Section` is built)."""
    return field(default=default, metadata={"domain": domain})


def domain_of(f: dataclasses.Field) -> Range | Choice:
    if "domain" not in f.metadata:
        raise TypeError(f"config field {f.name} declares no domain: declare it as setting(default, Range(...))")
    return f.metadata["domain"]


class SectionError(ConfigError):
    """A section built with a value outside its domain (or breaking one of its cross-field rules): ``detail``
    names ``section.key``; the message is ``config: <detail>`` (a file's loader re-raises it with the file)."""

    def __init__(self, detail: str) -> None:
        self.detail = detail
        super().__init__(f"config: {detail}")

    def __reduce__(self) -> tuple[type, tuple[str]]:
        return type(self), (self.detail,)


@dataclass(frozen=True)
class Section:
    """Base of every config section: a frozen dataclass whose fields are declared with ``setting(default,
    domain)``. Building one checks every field against its domain (storing it as the field's type: ``1500.0``
    becomes ``1500``), then the section's cross-field :meth:`rules`; an invalid section cannot exist. A changed
    copy is ``dataclasses.replace(section, key=value)`` (checked the same way)."""

    SECTION: ClassVar[str] = ""  # the section's key in a config file (``features``): errors name it

    def __post_init__(self) -> None:
        for f in dataclasses.fields(self):
            try:
                value = domain_of(f).check(getattr(self, f.name))
            except ValueError as err:
                raise SectionError(f"{self.SECTION}.{f.name} {err}") from None
            object.__setattr__(self, f.name, value)
        for ok, message in self.rules():
            if not ok:
                raise SectionError(message)

    def rules(self) -> list[tuple[bool, str]]:
        """The cross-field rules: ``(holds, message naming both keys)`` pairs (none by default)."""
        return []
