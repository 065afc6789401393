"""The argument parser every ``parksim`` command uses: usage errors are one line, defaults shown once."""

from __future__ import annotations

import argparse
from typing import Any, NoReturn

__all__ = ["Parser", "HelpFormatter", "UsageError"]


class UsageError(Exception):
    """A command line the parser rejects; the message is the one line to print."""


class HelpFormatter(argparse.HelpFormatter):
    """Appends ``(default: X)`` to an option's help only when X says something and the help does not already."""

    def _get_help_string(self, action: argparse.Action) -> str:
        text = action.help or ""
        default = action.default
        silent = default is None or default is False or default is argparse.SUPPRESS or default == []
        optional = bool(action.option_strings) or action.nargs in (argparse.OPTIONAL, argparse.ZERO_OR_MORE)
        if silent or not optional or "default" in text.lower():
            return text
        return f"{text} (default: %(default)s)"


class Parser(argparse.ArgumentParser):
    """``ArgumentParser`` with :class:`HelpFormatter` and errors raised as :class:`UsageError` (no usage dump)."""

    def __init__(self, **kwargs: Any) -> None:
        kwargs.setdefault("formatter_class", HelpFormatter)
        super().__init__(**kwargs)

    def error(self, message: str) -> NoReturn:
        """Raise instead of printing the usage and exiting: ``dispatch.main`` prints one line, exit 2."""
        raise UsageError(f"{self.prog}: error: {' '.join(message.split())}")
