"""The ``parksim`` dispatcher: the command names, the parser built from their modules, and ``main``, which runs
one command line and turns an expected error into one line and exit status 2.

Each command module defines ``add_parser(subparsers)`` (cheap: no heavy imports) and ``run(args) -> int``; heavy
work is imported inside ``run`` so ``parksim --help`` is fast and planners that only render never import training
code. Commands are found by name (``parksim.commands.NAME``), so a command that runs others (``demo``) calls
``main`` here without an import cycle; ``parksim.cli`` is only the installed entry point.
"""

from __future__ import annotations

import argparse
import errno
import importlib
import sys

from .parser import Parser, UsageError

__all__ = ["COMMANDS", "build_parser", "describe", "main"]

# Order is the order shown in --help.
COMMANDS = ["demo", "synth", "offpath", "import", "points", "export", "reconstruct", "batch", "eval", "colmap",
            "detector", "render", "ipm", "serve", "bench", "compact", "bundle", "asset",
            "scenarios"]

_MODULES = {"import": "imports"}
"""Commands whose module has another name (``import`` is a Python keyword)."""

_OS_ERRORS = (FileNotFoundError, FileExistsError, PermissionError, IsADirectoryError, NotADirectoryError)
_OS_ERRNOS = {errno.ENOSPC, errno.EDQUOT, errno.EFBIG, errno.EROFS, errno.ENAMETOOLONG, errno.ENOTEMPTY,
              errno.EADDRINUSE, errno.EADDRNOTAVAIL}
"""OSErrors that mean bad input or a full, read-only, forbidden or busy place: reported, not a traceback."""


def build_parser() -> argparse.ArgumentParser:
    """The ``parksim`` parser: one subcommand per name in ``COMMANDS``, each set to run its module's ``run``."""
    parser = Parser(
        prog="parksim",
        description="ParkSim: reconstruct parking garages from surround-view fisheye cameras "
                    "with 3D Gaussian Splatting and render them at any ego pose.")
    parser.add_argument("--version", action="version", version=f"%(prog)s {__import__('parksim').__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    sub.required = True
    for name in COMMANDS:
        module = importlib.import_module(f"parksim.commands.{_MODULES.get(name, name)}")
        p = module.add_parser(sub)
        p.set_defaults(_run=module.run)
    return parser


def _pydantic_errors(error: ValueError) -> str | None:
    """A pydantic ``ValidationError`` as ``field: message; ...`` (its own text spans lines and links docs)."""
    pydantic = sys.modules.get("pydantic")
    if pydantic is None or not isinstance(error, pydantic.ValidationError):
        return None
    return "; ".join(f"{'.'.join(map(str, e['loc'])) or 'value'}: {e['msg']}" for e in error.errors())


def describe(error: BaseException) -> str | None:
    """The one line to print for an expected error (bad input, a missing, full, read-only or busy resource, no
    memory for the size asked), or None for anything else: a bug, whose traceback must show."""
    if isinstance(error, _OS_ERRORS) or (isinstance(error, OSError) and error.errno in _OS_ERRNOS):
        text = str(error)
        if error.strerror:
            names = " -> ".join(str(n) for n in (error.filename, error.filename2) if n is not None)
            text = f"{names}: {error.strerror}" if names else error.strerror
    elif isinstance(error, MemoryError):
        text = f"out of memory: {error}" if str(error) else "out of memory"
    elif isinstance(error, ValueError):
        text = _pydantic_errors(error) or str(error)
    else:
        return None
    return " ".join(text.split())


def main(argv: list[str] | None = None) -> int:
    """Run one ``parksim`` command; every expected error is one line on stderr and exit status 2."""
    argv = sys.argv[1:] if argv is None else list(argv)
    try:
        args = build_parser().parse_args(argv)
    except UsageError as e:
        print(e, file=sys.stderr)
        return 2
    args.argv = argv   # the command line as typed, for the records that must say how they were made
    try:
        return int(args._run(args) or 0)
    except Exception as e:
        line = describe(e)
        if line is None:
            raise
        print(f"parksim {args.command}: error: {line}", file=sys.stderr)
        return 2
