"""Typed plug-in options, checked on construction the way the command line checks them while parsing.

Importers and benchmark suites declare their options as frozen dataclasses whose fields carry ``metadata``
(``help``, and ``low``/``high``/``open_low`` ranges among others; ``parksim.commands.options`` builds the command
line from the same metadata). ``check_options`` applies the ranges and ``Literal`` choices to an instance, so a
Python caller gets the one-line ``ValueError`` the CLI gives.
"""

from __future__ import annotations

import dataclasses
import math
import typing
from typing import Any, Literal

__all__ = ["CheckedOptions", "check_options"]


def _span(meta: dict[str, Any]) -> str:
    """The range of a field's ``low``/``high``/``open_low`` metadata, as ``> 0`` or ``in (0, 360]``."""
    low, high = meta.get("low"), meta.get("high")
    left = ">" if meta.get("open_low") else ">="
    if high is None:
        return f"{left} {low:g}"
    if low is None:
        return f"<= {high:g}"
    return f"in {'(' if meta.get('open_low') else '['}{low:g}, {high:g}]"


def _inside(value: float, meta: dict[str, Any]) -> bool:
    """``value`` within the field's ``low``/``high``/``open_low`` range (either end may be absent)."""
    low, high = meta.get("low"), meta.get("high")
    above = low is None or (value > low if meta.get("open_low") else value >= low)
    return above and (high is None or value <= high)


def check_options(options: Any) -> None:
    """Check an options dataclass the way its command line is checked: every number it holds (a field, or an item
    of a list, tuple or dict field) is finite and, where the field has ``low``/``high`` metadata, in range; a
    ``Literal`` field holds one of its choices.

    Args:
        options: a dataclass instance (an importer's ``Options``, ``ImportSettings``).

    Raises:
        ValueError: one line naming the field, the rule and the value.
    """
    hints = typing.get_type_hints(type(options))
    for f in dataclasses.fields(options):
        value = getattr(options, f.name)
        if value is None:
            continue
        meta = dict(f.metadata)
        tp = hints[f.name]
        literal = next((a for a in (tp, *typing.get_args(tp)) if typing.get_origin(a) is Literal), None)
        if literal is not None and value not in typing.get_args(literal):
            raise ValueError(f"{f.name} must be one of {', '.join(map(str, typing.get_args(literal)))}, "
                             f"got {value!r}")
        items = value.values() if isinstance(value, dict) else value if isinstance(value, (list, tuple)) else [value]
        ranged = "low" in meta or "high" in meta
        for item in items:
            if isinstance(item, bool) or not isinstance(item, (int, float)):
                if ranged:
                    raise ValueError(f"{f.name} must be a number {_span(meta)}, got {item!r}")
                continue
            if not math.isfinite(item):
                raise ValueError(f"{f.name} must be finite, got {item!r}")
            if ranged and not _inside(item, meta):
                raise ValueError(f"{f.name} must be {_span(meta)}, got {item!r}")


class CheckedOptions:
    """Base of options dataclasses whose construction runs ``check_options``: a Python caller gets the one-line
    ``ValueError`` that the command line gives while parsing. A subclass with checks of its own defines
    ``__post_init__`` and calls ``super().__post_init__()`` first."""

    def __post_init__(self) -> None:
        check_options(self)
