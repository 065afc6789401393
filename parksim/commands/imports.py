"""``parksim import FORMAT``: bring a recording in as a dataset (rig log, nerfstudio, COLMAP), all-or-nothing."""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import TYPE_CHECKING

from .argtypes import integer, number

if TYPE_CHECKING:
    from ..rig import Rig

__all__ = ["add_parser", "run"]


def add_parser(sub: argparse._SubParsersAction) -> argparse.ArgumentParser:
    """Register ``import`` with one sub-command per importer (cheap: importer modules import lazily)."""
    from ..importers import IMPORTERS, importer

    p = sub.add_parser(
        "import", help="import a recording (rig log, nerfstudio, COLMAP) as a dataset",
        description="Read a recording in one of the formats below, check it (poses finite with proper rotations, "
                    "timestamps increasing, every image decoding to its camera's size) and write the dataset that "
                    "reconstruct, eval and render read, into a temp folder renamed at the end, with "
                    "import_report.json (frames per camera, dropped frames and why, time span, path length, scale "
                    "source). Per-image poses of a multi-camera recording are fitted to a fixed rig when they agree "
                    "with one; then the scene serves at ego poses, else at camera poses only.")
    formats = p.add_subparsers(dest="format", metavar="FORMAT", required=True)
    for name in IMPORTERS:
        module = importer(name)
        q = formats.add_parser(name, help=module.HELP, description=module.DESCRIPTION,
                               formatter_class=p.formatter_class)
        module.add_arguments(q)
        q.add_argument("-o", "--output", type=Path, required=True,
                       help="dataset folder to write (must not exist unless --overwrite)")
        q.add_argument("--test-every", type=integer(0), default=10,
                       help="every n-th frame is a test frame when the source has no split (0: none)")
        q.add_argument("--scale", type=number(0, open_low=True),
                       help="metric scale for per-image poses (SfM has none); default: from --rig's camera "
                            "baselines, else 1")
        q.add_argument("--rig", type=Path, metavar="RIG",
                       help="a known rig (rig.json/yaml, or a dataset folder holding one): names the vehicle frame "
                            "and gives the scale of per-image poses by its camera baselines")
        q.add_argument("--rig-tolerance", type=_tolerance, default=None, metavar="M,DEG",
                       help="largest spread of a camera's pose relative to the first camera across frames for the "
                            "poses to count as one fixed rig (default: 0.02,0.5)")
        q.add_argument("--camera-height", type=number(0), metavar="M",
                       help="without --rig: how far the ground lies below the cameras' centroid (for the BEV)")
        q.add_argument("--overwrite", action="store_true", help="replace an existing output folder")
        q.add_argument("--quiet", action="store_true", help="no progress bar")
    return p


def _tolerance(text: str) -> tuple[float, float]:
    """``M,DEG`` -> two non-negative floats."""
    try:
        m, deg = (float(v) for v in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected M,DEG (two numbers), got {text!r}") from None
    if not (m >= 0 and deg >= 0):
        raise argparse.ArgumentTypeError(f"tolerances must be non-negative, got {text!r}")
    return m, deg


def _known_rig(path: Path | None) -> Rig | None:
    """The ``--rig`` given as a rig file or a dataset folder, or None."""
    from ..rig import Rig

    if path is None:
        return None
    return Rig.load(path / "rig.json" if path.is_dir() else path)


def run(args: argparse.Namespace) -> int:
    """Load with the chosen importer, fit a rig to per-image poses, write the dataset; print the report."""
    from ..importers import importer, write_recording
    from ..importers.rig_fit import TOLERANCE_DEG, TOLERANCE_M, fit_rig
    from .outputs import check_output_folder

    check_output_folder(args.output, overwrite=args.overwrite)
    known = _known_rig(args.rig)
    rec = importer(args.format).load(args)
    if rec.poses is None and rec.camera_poses is not None:
        tol_m, tol_deg = args.rig_tolerance or (TOLERANCE_M, TOLERANCE_DEG)
        if known is not None and not set(rec.rig.names) <= set(known.names):
            raise ValueError(f"--rig {args.rig} has cameras {known.names}; the recording has {rec.rig.names}")
        fit = fit_rig(rec.camera_poses, rec.rig.names, known, args.scale, tol_m, tol_deg, args.camera_height)
        rec = fit.apply(rec)
    else:
        given = [flag for flag, value in (("--scale", args.scale), ("--rig-tolerance", args.rig_tolerance),
                                          ("--camera-height", args.camera_height)) if value is not None]
        if given:
            raise ValueError(f"{', '.join(given)} apply to per-image (SfM) poses fitted to a rig; this recording "
                             "has ego poses")
    report = write_recording(rec, args.output, args.format, args.test_every, args.overwrite, not args.quiet)
    print(json.dumps({k: v for k, v in report.items() if k != "dropped_items"}, indent=1))
    return 0
