"""``parksim`` command line: one module per subcommand in ``parksim.commands``.

Each command module defines ``add_parser(subparsers)`` (cheap: no heavy imports) and
``run(args) -> int``; heavy work is imported inside ``run`` so ``parksim --help`` is fast
and planners that only render never import training code.
"""

from __future__ import annotations

import argparse
import importlib
import sys

from .omp_env import prefer_sleeping_omp_threads

prefer_sleeping_omp_threads()   # before any subcommand imports torch

# Order is the order shown in --help.
COMMANDS = ["demo", "synth", "reconstruct", "eval", "colmap", "detector", "render", "ipm", "serve", "bench", "compact"]


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="parksim",
        description="ParkSim: reconstruct parking garages from surround-view fisheye cameras "
                    "with 3D Gaussian Splatting and render them at any ego pose.")
    parser.add_argument("--version", action="version", version=f"%(prog)s {__import__('parksim').__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    sub.required = True
    for name in COMMANDS:
        module = importlib.import_module(f"parksim.commands.{name}")
        p = module.add_parser(sub)
        p.set_defaults(_run=module.run)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return int(args._run(args) or 0)
    except (ValueError, FileNotFoundError) as e:
        # Bad input: one clear line, no traceback, non-zero exit.
        print(f"parksim {args.command}: error: {e}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
