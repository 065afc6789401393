"""The plug-in contract importers and benchmark suites share, and their registries' one lookup.

A plug-in is a ``Plugin`` subclass in its own module: a ``name`` (its sub-command), a one-line ``help``, a
``description`` and an ``Options`` dataclass (checked on construction, ``parksim.checked_options``; the command
line is built from it by ``parksim.commands.options``), plus the one method its kind defines (``Importer.load``,
``Suite.run``). A registry maps names to ``"module:Class"`` so that listing the plug-ins imports only the
light modules, never what they run.
"""

from __future__ import annotations

import importlib
from abc import ABC
from collections.abc import Mapping
from typing import Any, ClassVar

__all__ = ["Plugin", "instantiate"]


class Plugin(ABC):
    """A named, typed extension (see the module docstring)."""

    name: ClassVar[str]
    help: ClassVar[str]
    description: ClassVar[str]
    Options: ClassVar[type]


def instantiate(registry: Mapping[str, str], name: str, package: str, kind: type, what: str) -> Any:
    """The plug-in registered as ``name``, instantiated (its module imported now).

    Args:
        registry: name -> ``"module:Class"``, modules relative to ``package``.
        name: the plug-in's name.
        package: the package its modules live in (``parksim.importers``, ``parksim.bench.suites``).
        kind: the base class it must subclass (the caller's return type).
        what: how to name the kind in an error (``"importer"``, ``"benchmark suite"``).

    Returns:
        An instance of the registered class.

    Raises:
        ValueError: ``name`` is not registered (the message lists the names that are).
        TypeError: the registered class does not subclass ``kind`` (a registry bug).
    """
    if name not in registry:
        raise ValueError(f"unknown {what} {name!r}; known: {', '.join(sorted(registry))}")
    module, cls_name = registry[name].split(":")
    cls = getattr(importlib.import_module(f"{package}.{module}"), cls_name)
    if not (isinstance(cls, type) and issubclass(cls, kind)):
        raise TypeError(f"{registry[name]} is registered as the {what} {name!r} but is not a {kind.__name__}")
    return cls()
