"""``parksim colmap``: recover poses and sparse points with COLMAP (pycolmap), or import an existing model."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from .argtypes import integer

__all__ = ["add_parser", "run"]


def add_parser(sub: argparse._SubParsersAction) -> argparse.ArgumentParser:
    """Register ``colmap sfm`` and ``colmap import`` (cheap: no heavy imports)."""
    p = sub.add_parser("colmap", help="COLMAP SfM on a dataset's images, or import a COLMAP model",
                       description="sfm: SIFT features per camera (OPENCV_FISHEYE, rig intrinsics fixed), exhaustive "
                                   "matching and incremental mapping; when the dataset has poses, prints the pose "
                                   "error after similarity alignment. import: write a model's points (aligned to the "
                                   "dataset's poses, or with its recovered poses when the dataset has none).")
    modes = p.add_subparsers(dest="mode", metavar="MODE", required=True)
    sfm = modes.add_parser(
        "sfm", help="run SfM on DATA's images",
        description="Structure from motion with pycolmap on a dataset's fisheye images: SIFT features per camera "
                    "(OPENCV_FISHEYE with the rig's intrinsics, held fixed), exhaustive matching, incremental "
                    "mapping. WORK receives database.db (remade each run) and the models under sparse/; the "
                    "largest model's registered images and points are printed as JSON, with the pose error "
                    "after a similarity alignment when the dataset has poses. Needs pycolmap (the colmap extra).")
    sfm.add_argument("data", type=Path, help="dataset directory")
    sfm.add_argument("--work", type=Path, required=True, help="folder for database.db and the sparse/ model")
    sfm.add_argument("--cameras", nargs="+", help="cameras to use (default: all of the rig)")
    sfm.add_argument("--frame-stride", type=integer(1), default=1, help="use every n-th frame")
    imp = modes.add_parser(
        "import", help="add a COLMAP model's points (and poses) to an existing dataset DATA",
        description="Read a COLMAP sparse model (cameras, images, points3D; binary or text) made from DATA's "
                    "images and write its points as DATA/points3d.ply, the initial point cloud of parksim "
                    "reconstruct: aligned to the dataset's poses by a similarity transform when it has them, "
                    "else with the model's recovered vehicle poses written too. Prints a JSON report. To bring "
                    "a COLMAP model and its images in as a new dataset, use `parksim import colmap`.")
    imp.add_argument("model", type=Path, help="COLMAP sparse model folder (cameras/images/points3D)")
    imp.add_argument("data", type=Path, help="dataset directory whose images the model was made from")
    imp.add_argument("--overwrite", action="store_true", help="replace an existing points3d.ply")
    return p


def run(args: argparse.Namespace) -> int:
    """Run the chosen mode and print its report as JSON."""
    from parksim.data import DatasetLayout, DatasetReader
    from parksim.recon.colmap import import_model, pose_errors, run_sfm, vehicle_poses

    from .outputs import check_output_folder

    if args.mode == "import":
        points = DatasetLayout(args.data).points
        if points.exists() and not args.overwrite:
            raise FileExistsError(f"{points} exists; pass --overwrite to replace it")
        check_output_folder(args.data)
        report = import_model(args.model, args.data, overwrite=args.overwrite)
    else:
        reader = DatasetReader(args.data)
        check_output_folder(args.work)
        model = run_sfm(args.data, args.work, args.cameras, args.frame_stride)
        report = {"registered_images": len(model.images), "points": len(model.xyz),
                  "model": str(args.work / "sparse"), **pose_errors(vehicle_poses(model, reader), reader)}
    print(json.dumps(report, indent=1))
    return 0
