"""A short ``repr`` for frozen records holding arrays (one helper for ``vtr`` and ``perception_model``).

``print(record)`` of a dataclass with image or landmark arrays would dump every element (tens of kB);
:func:`short_repr` shows small arrays (at most ``SMALL_ARRAY`` elements) as values and larger ones as
``<float64 (4, 4)>``, long sequences by their length, and nested records by their own repr. A record uses it
with ``__repr__ = short_repr`` in its class body (``dataclass`` then keeps it).
"""

from __future__ import annotations

import dataclasses
from typing import Any

SMALL_ARRAY = 6  # arrays up to this many elements are printed with their values
LONG_SEQUENCE = 8  # tuples/lists longer than this are shown by their length


def summarize(value: Any) -> str:
    """One short text for a field value."""
    shape = getattr(value, "shape", None)
    dtype = getattr(value, "dtype", None)
    if shape is not None and dtype is not None:  # an ndarray (numpy not imported for the check)
        if getattr(value, "size", SMALL_ARRAY + 1) <= SMALL_ARRAY:
            return " ".join(repr(value.tolist()).split())
        return f"<{dtype} {tuple(shape)}>"
    if isinstance(value, tuple | list) and len(value) > LONG_SEQUENCE:
        return f"<{type(value).__name__} of {len(value)}>"
    if isinstance(value, bytes) and len(value) > 32:
        return f"<{len(value)} bytes>"
    return repr(value)


def short_repr(record: Any) -> str:
    """``Name(field=value, ...)`` with array fields summarized (see the module docstring)."""
    parts = [f"{f.name}={summarize(getattr(record, f.name))}" for f in dataclasses.fields(record) if f.repr]
    return f"{type(record).__name__}({', '.join(parts)})"
