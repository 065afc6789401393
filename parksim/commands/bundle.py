"""``parksim bundle from-ply``: a servable scene bundle from a third-party INRIA 3DGS PLY and a ParkSim rig."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

__all__ = ["add_parser", "run", "read_transform"]


def add_parser(sub: argparse._SubParsersAction) -> argparse.ArgumentParser:
    """Register ``bundle from-ply`` (cheap: no heavy imports)."""
    p = sub.add_parser("bundle", help="make a scene bundle from a third-party 3DGS PLY",
                       description="Build scene bundles from Gaussians trained elsewhere.")
    modes = p.add_subparsers(dest="mode", metavar="MODE", required=True)
    ply = modes.add_parser(
        "from-ply", help="bundle an INRIA 3DGS PLY (graphdeco, gsplat, nerfstudio exports) with a rig",
        description="Read an INRIA 3DGS PLY (SH degree 0-3), move it into ParkSim's world frame (z up, floor at "
                    "z = 0: --dataparser-transforms undoes nerfstudio's normalisation, --frame names the axis "
                    "convention of the world left, --transform is a similarity applied after it) "
                    "and write OUTPUT as a scene bundle: gaussians.ply, rig.json, bundle.json, and map.json "
                    "with --map. OUTPUT appears only when complete. See docs/bundle.md.")
    ply.add_argument("ply", type=Path, help="the 3DGS PLY (graphdeco point_cloud.ply, a gsplat or splatfacto export)")
    ply.add_argument("--rig", type=Path, required=True, help="rig.json/.yaml, or a dataset folder (its rig.json)")
    ply.add_argument("-o", "--output", type=Path, required=True, help="bundle folder to write")
    add_placement_arguments(ply, "world")
    ply.add_argument("--dataparser-transforms", type=Path, metavar="JSON",
                     help="nerfstudio's dataparser_transforms.json of the run that trained the PLY: undone first, "
                          "so --frame describes the world nerfstudio was given")
    ply.add_argument("--map", type=Path, help="map.json (or a dataset folder's) in the same world frame")
    ply.add_argument("--overwrite", action="store_true", help="replace OUTPUT if it exists")
    return p


def add_placement_arguments(parser: argparse.ArgumentParser, what: str) -> None:
    """``--frame`` and ``--transform``, which place a third-party 3DGS PLY in ParkSim's axes (``read_transform``
    parses the second); ``what`` names what the PLY holds ("world", "object")."""
    parser.add_argument("--frame", choices=["parksim", "opencv", "colmap", "opengl"], default="parksim",
                        help=f"the PLY {what}'s axes: parksim x forward, y left, z up; opencv and colmap x right, "
                             "y down, z forward; opengl x right, y up, z backward")
    parser.add_argument("--transform", nargs="+", metavar="T",
                        help="4x4 similarity applied after --frame: a .json/.txt/.npy file or 16 numbers, row-major "
                             "(a rotation within 1e-3 of one, as printed with 6 decimals, is projected to it)")


def _numbers(text: str) -> Any:
    """The numbers in ``text`` (separated by spaces, commas or newlines) as a float64 array."""
    import numpy as np

    return np.array([float(v) for v in text.replace(",", " ").split()], dtype=np.float64)


def read_transform(tokens: list[str]) -> Any:
    """A 4x4 float64 array from ``--transform``'s tokens: one file (.json, .txt, .npy) or 16 numbers (separated by
    spaces or commas, in one token or several)."""
    import json

    import numpy as np

    path = Path(tokens[0])
    kind = path.suffix.lower() if len(tokens) == 1 else ""
    try:
        if kind == ".json":
            values = np.asarray(json.loads(path.read_text()), dtype=np.float64)
        elif kind == ".txt":
            values = _numbers(path.read_text())
        elif kind == ".npy":
            values = np.load(path, allow_pickle=False).astype(np.float64)
        else:
            values = _numbers(" ".join(tokens))
    except (OSError, ValueError, TypeError) as e:
        what = f"{path}: cannot read a 4x4 matrix" if kind else "takes a .json/.txt/.npy file or 16 numbers"
        raise ValueError(f"--transform {what} ({' '.join(str(e).split())})") from None
    if values.size != 16:
        where = f"--transform {path}" if kind else "--transform"
        raise ValueError(f"{where}: a 4x4 transform has 16 numbers, got {values.size}")
    return values.reshape(4, 4)


def run(args: argparse.Namespace) -> int:
    """Check OUTPUT, convert the Gaussians into a bundle written atomically (``parksim.ply_3dgs.bundle_from_ply``),
    print a summary."""
    import numpy as np

    from ..ply_3dgs import bundle_from_ply
    from .outputs import check_output_folder

    transform = read_transform(args.transform) if args.transform else None
    check_output_folder(args.output, overwrite=args.overwrite)
    bundle = bundle_from_ply(args.ply, args.rig, args.output, args.frame, transform, args.dataparser_transforms,
                             args.map, overwrite=args.overwrite)
    scene = bundle.scene
    lo, hi = np.percentile(scene.means.double().numpy(), [1, 99], axis=0)
    span = ", ".join(f"{a} [{lo[i]:.2f}, {hi[i]:.2f}]" for i, a in enumerate("xyz"))
    print(f"wrote {args.output}: {len(scene)} Gaussians, SH degree {scene.sh_degree}, frame {args.frame}; "
          f"1st-99th percentile of the means (m): {span}")
    correction = bundle.meta["ply_import"]["transform_correction"]
    if correction:
        print(f"--transform: rotation projected to the nearest proper rotation (largest correction {correction:.2g})")
    if bundle.map is None:
        print("no map.json (pass --map): render, serve and the viewer work; the gym env and parksim compact "
              "need a map with a garage and slots")
    return 0
