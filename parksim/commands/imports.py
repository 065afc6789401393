"""``parksim import FORMAT``: bring a recording in as a dataset, all-or-nothing.

One sub-command per importer of ``parksim.importers.IMPORTERS``, its options built from the importer's ``Options``
and ``ImportSettings`` (``parksim.commands.options``); the work is ``parksim.importers.import_recording``.
"""

from __future__ import annotations

import argparse
import json
import sys
from typing import Any

from .options import add_options, add_plugin_parsers, options_from_args

__all__ = ["add_parser", "run"]


def add_parser(sub: argparse._SubParsersAction) -> argparse.ArgumentParser:
    """Register ``import`` with one sub-command per importer (cheap: importer modules import lazily)."""
    from ..importers import IMPORTERS, ImportSettings, importer

    p = sub.add_parser(
        "import", help="import a recording (rig log, nerfstudio, instant-ngp, COLMAP) as a dataset",
        description="Read a recording in one of the formats below, check it (poses finite with proper rotations, "
                    "timestamps increasing) and write the dataset that reconstruct, eval and render read, into a "
                    "temp folder renamed at the end, with import_report.json (frames per camera, dropped frames and "
                    "why, time span, path length, scale source). A frame with an image that is absent, cut short, "
                    "unreadable or not its camera's size is dropped and counted (--strict refuses instead). "
                    "Per-image poses of a multi-camera recording are fitted to a fixed rig when they agree "
                    "with one; then the scene serves at ego poses, else at camera poses only.")
    formats = p.add_subparsers(dest="format", metavar="FORMAT", required=True)
    for q in add_plugin_parsers(formats, (importer(name) for name in IMPORTERS), p.formatter_class).values():
        add_options(q, ImportSettings)
    return p


def run(args: argparse.Namespace) -> int:
    """Import with the chosen importer and print the report (without its per-item list of dropped frames), and
    one line to stderr each for what was dropped (counted by reason) and what was corrected (rotations projected,
    quaternions normalised) when anything was."""
    from ..importers import ImportSettings, import_recording, importer
    from ..importers.recording import correction_summary, drop_summary
    from .outputs import check_output_folder

    chosen = importer(args.format)
    options: Any = options_from_args(chosen.Options, args)   # the importer's own Options class
    settings = options_from_args(ImportSettings, args)
    check_output_folder(settings.output, overwrite=settings.overwrite)
    report = import_recording(chosen, options, settings)
    print(json.dumps({k: v for k, v in report.items() if k != "dropped_items"}, indent=1))
    for line in (drop_summary(report), correction_summary(report["corrected"])):
        if line:
            print(line, file=sys.stderr)
    return 0
