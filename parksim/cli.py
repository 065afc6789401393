"""The installed ``parksim`` entry point (``python -m parksim.cli`` too): sets the process up, then hands the
command line to :func:`parksim.commands.dispatch.main`, whose names it re-exports.
"""

from __future__ import annotations

import sys

from .commands.dispatch import COMMANDS, build_parser, describe, main
from .omp_env import prefer_sleeping_omp_threads

__all__ = ["COMMANDS", "build_parser", "describe", "main"]

prefer_sleeping_omp_threads()   # before any subcommand imports torch

if __name__ == "__main__":
    sys.exit(main())
