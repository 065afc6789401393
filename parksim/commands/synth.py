"""``parksim synth``: generate a synthetic garage scene (ParkRecon3D-style dataset directory)."""

from __future__ import annotations

import argparse
from pathlib import Path

from .argtypes import integer, number, resolution

__all__ = ["add_parser", "run"]

PRESET_NAMES = ["scene1", "scene2", "scene3", "scene4", "worn", "busy", "tiny"]
MAX_SIDE = 2048
"""Largest fisheye image side and BEV side (px): 2048x2048 needs about 6 GiB while ray casting (~1.4 KiB/px)."""
MAX_POINTS = 10_000_000
"""Largest sparse point cloud."""


def add_parser(subparsers: argparse._SubParsersAction) -> argparse.ArgumentParser:
    """Register ``synth`` (cheap: no heavy imports)."""
    p = subparsers.add_parser(
        "synth", help="generate a synthetic underground-garage scene (four fisheyes, BEV, labels, depth)",
        description="Ray-cast a procedurally generated underground garage through a four-camera 190 deg "
                    "fisheye AVM rig and write a dataset directory: rig.json, poses.json, images/<camera>/, "
                    "ipm/ (ground-truth BEV by parksim.ipm), labels/ (DMPR-PS slots in BEV pixels), depth/ "
                    "(uint16 mm along the ray), map.json, points3d.ply, split.json (every 10th frame is test), "
                    "meta.json. The output appears only when complete (written to a temp dir, then renamed).")
    p.add_argument("preset", choices=PRESET_NAMES,
                   help="scene1..scene4: clean benchmark garages (layouts, lighting, seeds differ); worn: dim, "
                        "faded and dirty markings, stains, wet patches; busy: nearly full of varied cars, clutter, "
                        "glossy floor, uneven exposure, motion blur (docs/synth.md); tiny: 12 frames at 160x120 "
                        "for tests")
    p.add_argument("-o", "--output", type=Path, required=True,
                   help="output dataset directory (must not exist unless --overwrite)")
    p.add_argument("--frames", type=integer(1), help="number of frames at 10 Hz (preset default: 100; tiny: 12)")
    p.add_argument("--resolution", metavar="WxH", type=resolution(MAX_SIDE),
                   help=f"fisheye image size, e.g. 640x480 (default) or 1280x960; each side at most {MAX_SIDE}")
    p.add_argument("--bev-px", type=integer(1, MAX_SIDE),
                   help="BEV side in pixels over 10 m x 10 m (default 600, DMPR-PS scale)")
    p.add_argument("--length", type=number(0, open_low=True),
                   help="garage length in metres, at least 22 (preset default)")
    p.add_argument("--seed", type=int, help="layout seed (preset default)")
    p.add_argument("--points", type=integer(1, MAX_POINTS),
                   help="points in the sparse initial point cloud (preset default: 30000; tiny: 3000)")
    p.add_argument("--no-exposure", action="store_true", help="same exposure in every camera and frame")
    p.add_argument("--no-vignetting", action="store_true", help="no lens vignetting")
    p.add_argument("--no-noise", action="store_true", help="no sensor noise")
    p.add_argument("--motion-blur", metavar="SECONDS", type=number(0, 0.1),
                   help="shutter time for motion blur, 0 to 0.1 s (preset default: 0; busy: 1/60 s); 0 = none")
    p.add_argument("--workers", type=integer(1),
                   help="processes rendering frames in parallel (default: all usable cores, at most one per 8 "
                        "frames at 640x480, so small jobs run serially; 1 = serial, in this process); the output "
                        "is byte-identical whatever the count")
    p.add_argument("--overwrite", action="store_true", help="replace an existing output directory")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    return p


def run(args: argparse.Namespace) -> int:
    """Build the preset with the overrides given and write it; prints where and how long it took."""
    import dataclasses
    import time

    from tqdm import tqdm

    from ..synth import generate, get_preset
    from .outputs import check_output_folder

    check_output_folder(args.output, overwrite=args.overwrite)
    preset = get_preset(args.preset)
    changes: dict = {}
    if args.frames is not None:
        changes["frames"] = args.frames
    if args.resolution:
        changes["width"], changes["height"] = args.resolution
    if args.bev_px is not None:
        changes["bev_px"] = args.bev_px
    if args.points is not None:
        changes["points"] = args.points
    layout = {k: v for k, v in (("length", args.length), ("seed", args.seed)) if v is not None}
    if layout:
        changes["layout"] = dataclasses.replace(preset.layout, **layout)
    sensor = {"exposure": not args.no_exposure, "vignetting": not args.no_vignetting, "noise": not args.no_noise}
    if args.motion_blur is not None:
        sensor["motion_blur"] = args.motion_blur
    changes["sensor"] = dataclasses.replace(preset.sensor, **sensor)
    preset = dataclasses.replace(preset, **changes)
    start = time.perf_counter()
    with tqdm(total=preset.frames, desc=f"synth {preset.name}", unit="frame", disable=args.quiet) as bar:
        out = generate(preset, args.output, overwrite=args.overwrite, progress=bar.update, workers=args.workers)
    print(f"wrote {out} ({preset.frames} frames x 4 cameras at {preset.width}x{preset.height}) "
          f"in {time.perf_counter() - start:.1f} s")
    return 0
