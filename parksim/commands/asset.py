"""``parksim asset``: Gaussian actor assets (a folder: the actor's Gaussians, footprint box, name) from the synth
garage's cars and a pedestrian (``bake``), a box of a scene bundle (``crop``) or a third-party 3DGS PLY
(``from-ply``)."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from .argtypes import integer
from .bundle import add_placement_arguments, read_transform

__all__ = ["add_parser", "run"]

_KINDS = ("car", "sedan", "hatchback", "suv", "van", "pickup", "pedestrian")   # actor_sources.BAKE_KINDS, unimported


def add_parser(sub: argparse._SubParsersAction) -> argparse.ArgumentParser:
    """Register ``asset bake``, ``asset crop`` and ``asset from-ply`` (cheap: no heavy imports)."""
    p = sub.add_parser("asset", help="make Gaussian actor assets (cars, pedestrians, crops, PLYs)",
                       description="Write actor assets: a folder with the actor's Gaussians in its own frame (x "
                                   "forward, y left, z up, origin on the floor under its centre), its footprint box "
                                   "and a name (asset.json + gaussians.ply). render(..., actors=[...]) places them "
                                   "in a scene. OUTPUT appears only when complete.")
    modes = p.add_subparsers(dest="mode", metavar="MODE", required=True)
    bake = modes.add_parser("bake", help="bake a synth garage car or a pedestrian to Gaussians",
                            description="Sample the surfaces of the boxes the synthetic garage draws a car with (the "
                                        "classic car of scene1-4, or a body type with proportions drawn by --seed) "
                                        "or of a simple pedestrian with flat Gaussian discs (SH degree 0).")
    bake.add_argument("kind", choices=_KINDS, help="what to bake: " + ", ".join(_KINDS))
    bake.add_argument("--count", type=integer(1, 10_000_000),
                      help="Gaussians to sample (default: 2000 for a car, 600 for a pedestrian)")
    bake.add_argument("--seed", type=integer(0), default=0, help="seed of the proportions, colours and samples")
    bake.add_argument("--color", metavar="R,G,B", help="a car's body colour, linear RGB in [0, 1] (default: drawn "
                                                        "from the garage's palette)")
    crop = modes.add_parser("crop", help="cut a box out of a scene bundle as an asset",
                            description="Keep the bundle's Gaussians whose means lie in an oriented box (given, or "
                                        "an obstacle of the bundle's map.json, such as a parked car) and store them "
                                        "in the box's frame: placed at the box's pose X,Y,YAW the asset stands "
                                        "where it was cut from.")
    crop.add_argument("bundle", type=Path, help="scene bundle folder")
    where = crop.add_mutually_exclusive_group(required=True)
    where.add_argument("--box", metavar="X,Y,YAW,LENGTH,WIDTH,Z0,Z1",
                       help="the box: centre (m), heading (rad), length along the heading, width, height range (m); "
                            "write --box=-1,... when the first number is negative")
    where.add_argument("--obstacle", type=integer(0), metavar="INDEX",
                       help="the box of map.json's obstacle INDEX (0-based), its z range as stored (from the "
                            "floor: pass --box with Z0 above the floor to leave the floor's Gaussians behind)")
    crop.add_argument("--name", help="the asset's name (default: OUTPUT's folder name)")
    ply = modes.add_parser("from-ply", help="make an asset of a third-party INRIA 3DGS PLY",
                           description="Read an INRIA 3DGS PLY (SH degree 0-3) of one object, move it into the asset "
                                       "frame (--frame names the PLY's axes, --transform is a similarity applied "
                                       "after it: put the object's floor point at the origin, facing +x); its box "
                                       "spans the 0.5th to 99.5th percentile of the means.")
    ply.add_argument("ply", type=Path, help="the 3DGS PLY")
    add_placement_arguments(ply, "object")
    ply.add_argument("--name", help="the asset's name (default: the PLY's file name without .ply)")
    for mode in (bake, crop, ply):
        mode.add_argument("-o", "--output", type=Path, required=True, help="asset folder to write")
        mode.add_argument("--overwrite", action="store_true", help="replace OUTPUT if it exists")
    return p


def _numbers(text: str, option: str, count: int) -> list[float]:
    """``count`` comma-separated numbers; ``ValueError`` naming ``option`` otherwise."""
    try:
        values = [float(v) for v in text.split(",")]
    except ValueError:
        values = []
    if len(values) != count:
        raise ValueError(f"{option} takes {count} comma-separated numbers, got {text!r}")
    return values


def _crop_box(args: argparse.Namespace, bundle: Any) -> Any:
    """The crop box from ``--box`` or from the bundle map's obstacle ``--obstacle``."""
    from ..actor_sources import CropBox

    if args.box is not None:
        return CropBox(*_numbers(args.box, "--box", 7))
    obstacles = (bundle.map or {}).get("obstacles") or []
    if args.obstacle >= len(obstacles):
        raise ValueError(f"--obstacle {args.obstacle}: {args.bundle} has {len(obstacles)} obstacle(s) in its map")
    return CropBox.from_obstacle(obstacles[args.obstacle])


def run(args: argparse.Namespace) -> int:
    """Check OUTPUT, make the asset (``parksim.actor_sources``), write it (``save_asset``), print a summary."""
    from ..actor_asset import save_asset
    from ..actor_sources import asset_from_ply, bake, crop_asset
    from .outputs import check_output_folder

    color = _numbers(args.color, "--color", 3) if args.mode == "bake" and args.color else None
    transform = read_transform(args.transform) if args.mode == "from-ply" and args.transform else None
    check_output_folder(args.output, overwrite=args.overwrite)
    if args.mode == "bake":
        asset = bake(args.kind, args.count, args.seed, color)
    elif args.mode == "crop":
        from ..bundle import load

        bundle = load(args.bundle)
        asset = crop_asset(bundle.scene, _crop_box(args, bundle), args.name or args.output.name)
    else:
        asset = asset_from_ply(args.ply, args.name, args.frame, transform)
    save_asset(args.output, asset, overwrite=args.overwrite)
    (x0, y0, z0), (x1, y1, z1) = asset.box
    print(f"wrote {args.output}: asset {asset.name!r}, {len(asset.scene)} Gaussians, SH degree "
          f"{asset.scene.sh_degree}, box x [{x0:.2f}, {x1:.2f}] y [{y0:.2f}, {y1:.2f}] z [{z0:.2f}, {z1:.2f}] m")
    return 0
