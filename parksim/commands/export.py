"""``parksim export FORMAT``: write a dataset in another tool's format (nerfstudio), all-or-nothing."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

__all__ = ["add_parser", "run"]


def add_parser(sub: argparse._SubParsersAction) -> argparse.ArgumentParser:
    """Register ``export nerfstudio`` (cheap: no heavy imports)."""
    p = sub.add_parser("export", help="write a dataset in another tool's format (nerfstudio)",
                       description="Write a dataset so another tool trains on the same data; the output folder "
                                   "appears only when complete.")
    formats = p.add_subparsers(dest="format", metavar="FORMAT", required=True)
    ns = formats.add_parser(
        "nerfstudio", help="transforms.json and images for nerfstudio (ns-train) or gsplat",
        description="Write transforms.json (OPENCV_FISHEYE for opencv_fisheye cameras, PINHOLE for pinhole ones; "
                    "intrinsics at the top level when all cameras share them, else per frame; each image's "
                    "camera-to-world pose in OpenGL camera axes; time in seconds; the dataset's split as "
                    "train/val/test_filenames), the images copied as images/<camera>/<frame>.png and the sparse "
                    "points as sparse_pc.ply. `parksim import nerfstudio` reads it back. See "
                    "docs/import_nerfstudio.md.", formatter_class=p.formatter_class)
    ns.add_argument("data", type=Path, help="dataset directory")
    ns.add_argument("-o", "--output", type=Path, required=True,
                    help="folder to write (must not exist unless --overwrite)")
    ns.add_argument("--overwrite", action="store_true", help="replace an existing output folder")
    return p


def run(args: argparse.Namespace) -> int:
    """Export and print a short JSON report."""
    from ..importers.nerfstudio import export
    from .outputs import check_output_folder

    check_output_folder(args.output, overwrite=args.overwrite)
    print(json.dumps(export(args.data, args.output, overwrite=args.overwrite), indent=1))
    return 0
