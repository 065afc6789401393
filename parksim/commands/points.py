"""``parksim points``: a sparse point cloud for a dataset from its known poses (SIFT, matching, triangulation)."""

from __future__ import annotations

import argparse
import time
from pathlib import Path

from .argtypes import integer

__all__ = ["add_parser", "run"]


def add_parser(sub: argparse._SubParsersAction) -> argparse.ArgumentParser:
    """Register ``points`` (cheap: no heavy imports)."""
    from ..importers.points_sfm import MAX_ERROR_PX, MAX_FEATURES, MIN_PARALLAX_DEG, MIN_POINTS

    p = sub.add_parser(
        "points", help="triangulate a dataset's points3d.ply from its known poses",
        description="For a dataset with poses but no point cloud (a rig log, a nerfstudio capture without a PLY): "
                    "SIFT features in every training image, matched between images that see the same part of the "
                    "scene (a camera with itself a few frames on, neighbouring cameras at one frame; ratio test and "
                    "mutual check), each keypoint unprojected through its own camera model (fisheye rays, no "
                    "undistortion) and triangulated with the poses held fixed. Points that reproject within "
                    f"{MAX_ERROR_PX:g} px in every image that sees them, lie ahead of every camera and span "
                    f"{MIN_PARALLAX_DEG:g} deg of parallax are written as DATA/points3d.ply, coloured from their "
                    f"images; fewer than {MIN_POINTS} is an error and writes nothing. Prints the points and their "
                    "mean reprojection error.")
    p.add_argument("data", type=Path, help="dataset directory")
    p.add_argument("--max-features", type=integer(1), default=MAX_FEATURES, metavar="N",
                   help="most SIFT features per image")
    p.add_argument("--overwrite", action="store_true", help="replace an existing points3d.ply")
    p.add_argument("--quiet", action="store_true", help="no progress bars")
    return p


def run(args: argparse.Namespace) -> int:
    """Triangulate, write DATA/points3d.ply atomically and print one summary line."""
    from ..data import DatasetLayout
    from ..importers.points_sfm import write_sfm_points
    from .outputs import check_output_file

    target = DatasetLayout(args.data).points
    check_output_file(target)
    start = time.perf_counter()
    points = write_sfm_points(args.data, args.max_features, args.overwrite, progress=not args.quiet)
    print(f"wrote {target}: {len(points.xyz)} points from {points.images} images ({points.matches} matches in "
          f"{points.pairs} pairs), mean reprojection error {points.mean_error_px:.2f} px, in "
          f"{time.perf_counter() - start:.1f} s")
    return 0
