"""``parksim colmap``: recover poses and sparse points with COLMAP (pycolmap), or import an existing model."""

from __future__ import annotations

import argparse
import json
from pathlib import Path


def add_parser(sub: argparse._SubParsersAction) -> argparse.ArgumentParser:
    """Register ``colmap sfm`` and ``colmap import`` (cheap: no heavy imports)."""
    p = sub.add_parser("colmap", help="COLMAP SfM on a dataset's images, or import a COLMAP model",
                       description="sfm: SIFT features per camera (OPENCV_FISHEYE, rig intrinsics fixed), exhaustive "
                                   "matching and incremental mapping; when the dataset has poses, prints the pose "
                                   "error after similarity alignment. import: write a model's points (aligned to the "
                                   "dataset's poses, or with its recovered poses when the dataset has none).")
    modes = p.add_subparsers(dest="mode", metavar="MODE", required=True)
    sfm = modes.add_parser("sfm", help="run SfM on DATA's images", formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    sfm.add_argument("data", type=Path, help="dataset directory")
    sfm.add_argument("--work", type=Path, required=True, help="folder for database.db and the sparse/ model")
    sfm.add_argument("--cameras", nargs="+", help="cameras to use (default: all of the rig)")
    sfm.add_argument("--frame-stride", type=int, default=1, help="use every n-th frame")
    imp = modes.add_parser("import", help="import a COLMAP model into DATA")
    imp.add_argument("model", type=Path, help="COLMAP sparse model folder (cameras/images/points3D)")
    imp.add_argument("data", type=Path, help="dataset directory whose images the model was made from")
    imp.add_argument("--overwrite", action="store_true", help="replace an existing points3d.ply")
    return p


def run(args: argparse.Namespace) -> int:
    """Run the chosen mode and print its report as JSON."""
    from parksim.data import DatasetReader
    from recon.colmap import import_model, pose_errors, run_sfm, vehicle_poses

    if args.mode == "import":
        report = import_model(args.model, args.data, overwrite=args.overwrite)
    else:
        if args.frame_stride < 1:
            raise ValueError(f"--frame-stride must be at least 1, got {args.frame_stride}")
        model = run_sfm(args.data, args.work, args.cameras, args.frame_stride)
        reader = DatasetReader(args.data)
        report = {"registered_images": model.num_reg_images(), "points": model.num_points3D(),
                  "model": str(args.work / "sparse"), **pose_errors(vehicle_poses(model, reader), reader)}
    print(json.dumps(report, indent=1))
    return 0
