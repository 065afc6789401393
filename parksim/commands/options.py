"""Command-line options built from a typed options dataclass, the way nerfstudio builds its CLI from configs.

A plug-in of the library (an importer, a benchmark suite) declares its options once, as a dataclass whose
fields carry ``metadata``; it never sees argparse. Keys of a field's ``metadata``:

- ``help`` (required): one line for ``--help``.
- ``flag``: an extra spelling such as ``"-o"``; ``positional``: True for a positional argument.
- ``metavar``; ``low`` / ``high``: a range checked while the command line is parsed (``parksim.commands.argtypes``);
  ``open_low``: True when ``low`` itself is refused (a float that must be positive).
- ``nargs``: ``"+"`` for a ``list``/``tuple`` given as several words after the flag (``--images a b``) instead of
  one comma-separated word.
- ``quick``: the value under ``--quick`` (benchmark suites' small preset), shown in ``--help``.

Types understood: ``bool`` (``--name`` / ``--no-name``), ``int``, ``float``, ``str``, ``Path``, ``Literal[...]``
(choices), ``X | None`` (optional, default None), ``list[X]`` and ``tuple[X, ...]`` (comma-separated), and
``dict[str, X]`` (``NAME=VALUE`` words, X one of the scalar types, after one flag or repeated).
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import types
import typing
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import Any, Literal, TypeVar

from ..plugins import Plugin
from .argtypes import integer, number

__all__ = ["add_options", "add_plugin_parsers", "options_from_args"]

_UNSET = object()
"""The namespace value of an optional positional argument left out (options take ``argparse.SUPPRESS``)."""

T = TypeVar("T")


def _unwrap_optional(tp: Any) -> tuple[Any, bool]:
    """``X | None`` -> (X, True); anything else -> (tp, False)."""
    if typing.get_origin(tp) in (typing.Union, types.UnionType):
        args = [a for a in typing.get_args(tp) if a is not type(None)]
        if len(args) == 1 and len(typing.get_args(tp)) == 2:
            return args[0], True
    return tp, False


def _scalar_parser(tp: Any, meta: dict[str, Any]) -> Callable[[str], Any]:
    """The argparse ``type`` of one value of type ``tp`` (with the field's range, if any)."""
    low, high = meta.get("low"), meta.get("high")
    if tp is int:
        return integer(int(low) if low is not None else -(2**62), None if high is None else int(high))
    if tp is float:
        return number(-math.inf if low is None else float(low), math.inf if high is None else float(high),
                      open_low=bool(meta.get("open_low")))
    if tp is Path:
        return Path
    if tp is str:
        return str
    raise TypeError(f"options: no command-line parser for type {tp!r}")


def _comma_list(item: Callable[[str], Any], tuple_: bool) -> Callable[[str], Any]:
    """Parse ``a,b,c`` with ``item`` per element."""
    def parse(text: str) -> Any:
        values = [item(v) for v in text.split(",") if v.strip()]
        return tuple(values) if tuple_ else values

    return parse


def _named(value: Callable[[str], Any]) -> Callable[[str], tuple[str, Any]]:
    """Parse ``NAME=VALUE`` into ``(NAME, value(VALUE))``."""
    def parse(text: str) -> tuple[str, Any]:
        name, sep, rest = text.partition("=")
        if not sep or not name or not rest:
            raise argparse.ArgumentTypeError(f"expected NAME=VALUE, got {text!r}")
        return name, value(rest)

    return parse


def _shown(value: Any) -> str:
    """A default as the user would type it (``none`` for an empty list)."""
    if isinstance(value, (list, tuple)):
        return ",".join(_shown(v) for v in value) or "none"
    if isinstance(value, float):
        return f"{value:g}"
    return str(value)


def _default_of(f: dataclasses.Field) -> Any:
    if f.default is not dataclasses.MISSING:
        return f.default
    if f.default_factory is not dataclasses.MISSING:
        return f.default_factory()
    return dataclasses.MISSING


def add_options(parser: argparse.ArgumentParser, cls: type) -> None:
    """Add one command-line argument per field of the options dataclass ``cls`` to ``parser``.

    Args:
        parser: the (sub)command's parser.
        cls: a dataclass whose fields carry ``metadata["help"]`` (see the module docstring).

    Unset options stay out of the namespace (``argparse.SUPPRESS``), so ``options_from_args`` can tell a value the
    user typed from a default, and fill in the field's default or its ``quick`` value.
    """
    hints = typing.get_type_hints(cls)
    for f in dataclasses.fields(cls):
        meta = dict(f.metadata)
        if "help" not in meta:
            raise TypeError(f"{cls.__name__}.{f.name}: options need metadata['help']")
        tp = _unwrap_optional(hints[f.name])[0]   # None is a default like any other
        default = _default_of(f)
        text = meta["help"]
        if default not in (dataclasses.MISSING, None, [], (), {}) and tp is not bool:
            text += f" (default {_shown(default)}"
            text += f"; --quick: {_shown(meta['quick'])})" if "quick" in meta else ")"
        kwargs: dict[str, Any] = {"help": text, "default": argparse.SUPPRESS}
        if "metavar" in meta:
            kwargs["metavar"] = meta["metavar"]
        origin = typing.get_origin(tp)
        if tp is bool:
            kwargs["action"] = argparse.BooleanOptionalAction
        elif origin is Literal:
            kwargs["choices"] = list(typing.get_args(tp))
        elif origin in (list, tuple) and meta.get("nargs") == "+":
            kwargs.update(type=_scalar_parser(typing.get_args(tp)[0], meta), nargs="+")
        elif origin in (list, tuple):
            item = typing.get_args(tp)[0]
            kwargs["type"] = _comma_list(_scalar_parser(item, meta), origin is tuple)
            kwargs.setdefault("metavar", "A,B,...")
        elif origin is dict:
            kwargs.update(type=_named(_scalar_parser(typing.get_args(tp)[1], meta)), action="extend", nargs="+",
                          metavar=meta.get("metavar", "NAME=VALUE"))
        else:
            kwargs["type"] = _scalar_parser(tp, meta)
        if meta.get("positional"):
            kwargs.pop("default")
            if default is not dataclasses.MISSING:   # argparse would pass a SUPPRESS default through ``type``
                kwargs["nargs"] = "?"
                kwargs["default"] = _UNSET
            parser.add_argument(f.name, **kwargs)
            continue
        names = [f"--{f.name.replace('_', '-')}"]
        if "flag" in meta:
            names.insert(0, meta["flag"])
        if default is dataclasses.MISSING:
            kwargs["required"] = True
        parser.add_argument(*names, dest=f.name, **kwargs)


def options_from_args(cls: type[T], args: argparse.Namespace, quick: bool = False) -> T:
    """Build the options dataclass ``cls`` from parsed ``args``.

    Args:
        cls: the dataclass given to ``add_options``.
        args: the parsed namespace.
        quick: fill options the user did not give with their ``quick`` value, where a field has one.

    Returns:
        ``cls(**values)``; its own checks (``__post_init__``) run here, before any work starts.
    """
    values: dict[str, Any] = {}
    hints = typing.get_type_hints(cls)
    for f in dataclasses.fields(cls):  # type: ignore[arg-type]  # cls is a dataclass by contract
        if getattr(args, f.name, _UNSET) is not _UNSET:
            value = getattr(args, f.name)
            origin = typing.get_origin(_unwrap_optional(hints[f.name])[0])
            if origin is dict and isinstance(value, list):
                value = dict(value)
            elif origin is tuple and isinstance(value, list):
                value = tuple(value)
            values[f.name] = value
        elif quick and "quick" in f.metadata:
            values[f.name] = f.metadata["quick"]
    return cls(**values)


def add_plugin_parsers(subparsers: argparse._SubParsersAction, plugins: Iterable[Plugin],
                       formatter_class: type[argparse.HelpFormatter]) -> dict[str, argparse.ArgumentParser]:
    """One sub-command per plug-in (an importer, a benchmark suite), its options built from its ``Options``.

    Args:
        subparsers: the command's sub-command group.
        plugins: the plug-ins, in ``--help`` order.
        formatter_class: the help formatter of the command's parser.

    Returns:
        Each plug-in's parser by name, for the options its command adds to every one.
    """
    parsers = {}
    for plugin in plugins:
        q = subparsers.add_parser(plugin.name, help=plugin.help, description=plugin.description,
                                  formatter_class=formatter_class)
        add_options(q, plugin.Options)
        parsers[plugin.name] = q
    return parsers
