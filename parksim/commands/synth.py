"""``parksim synth``: generate a synthetic garage scene (ParkRecon3D-style dataset directory)."""

from __future__ import annotations

import argparse

PRESET_NAMES = ["scene1", "scene2", "scene3", "scene4", "tiny"]


def add_parser(subparsers: argparse._SubParsersAction) -> argparse.ArgumentParser:
    """Register ``synth`` (cheap: no heavy imports)."""
    p = subparsers.add_parser(
        "synth", help="generate a synthetic underground-garage scene (four fisheyes, BEV, labels, depth)",
        description="Ray-cast a procedurally generated underground garage through a four-camera 190 deg "
                    "fisheye AVM rig and write a dataset directory: rig.json, poses.json, images/<camera>/, "
                    "ipm/ (ground-truth BEV by parksim.ipm), labels/ (DMPR-PS slots in BEV pixels), depth/ "
                    "(uint16 mm along the ray), map.json, points3d.ply, split.json (every 10th frame is test), "
                    "meta.json. The output appears only when complete (written to a temp dir, then renamed).",
        formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    p.add_argument("preset", choices=PRESET_NAMES,
                   help="scene1..scene4: benchmark garages (layouts, lighting, seeds differ); tiny: 12 frames at 160x120 for tests")
    p.add_argument("-o", "--output", required=True, help="output dataset directory (must not exist unless --overwrite)")
    p.add_argument("--frames", type=int, help="number of frames at 10 Hz (preset default: 100; tiny: 12)")
    p.add_argument("--resolution", metavar="WxH", help="fisheye image size, e.g. 640x480 (default) or 1280x960")
    p.add_argument("--bev-px", type=int, help="BEV side in pixels over 10 m x 10 m (default 600, DMPR-PS scale)")
    p.add_argument("--length", type=float, help="garage length in metres (preset default)")
    p.add_argument("--seed", type=int, help="layout seed (preset default)")
    p.add_argument("--points", type=int, help="points in the sparse initial point cloud")
    p.add_argument("--no-exposure", action="store_true", help="same exposure in every camera and frame")
    p.add_argument("--no-vignetting", action="store_true", help="no lens vignetting")
    p.add_argument("--no-noise", action="store_true", help="no sensor noise")
    p.add_argument("--overwrite", action="store_true", help="replace an existing output directory")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    return p


def _resolution(text: str) -> tuple[int, int]:
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise ValueError(f"--resolution must look like 640x480, got {text!r}") from None
    if w <= 0 or h <= 0:
        raise ValueError(f"--resolution must be positive, got {text!r}")
    return w, h


def run(args: argparse.Namespace) -> int:
    """Build the preset with the overrides given and write it; prints where and how long it took."""
    import dataclasses
    import time

    from tqdm import tqdm

    from ..synth import generate, get_preset
    from ..synth.shading import SensorOptions

    preset = get_preset(args.preset)
    changes: dict = {}
    if args.frames is not None:
        if args.frames < 1:
            raise ValueError(f"--frames must be at least 1, got {args.frames}")
        changes["frames"] = args.frames
    if args.resolution:
        changes["width"], changes["height"] = _resolution(args.resolution)
    if args.bev_px is not None:
        changes["bev_px"] = args.bev_px
    if args.points is not None:
        changes["points"] = args.points
    layout = {k: v for k, v in (("length", args.length), ("seed", args.seed)) if v is not None}
    if layout:
        changes["layout"] = dataclasses.replace(preset.layout, **layout)
    changes["sensor"] = SensorOptions(exposure=not args.no_exposure, vignetting=not args.no_vignetting,
                                      noise=not args.no_noise)
    preset = dataclasses.replace(preset, **changes)
    start = time.perf_counter()
    with tqdm(total=preset.frames, desc=f"synth {preset.name}", unit="frame", disable=args.quiet) as bar:
        out = generate(preset, args.output, overwrite=args.overwrite, progress=bar.update)
    print(f"wrote {out} ({preset.frames} frames x 4 cameras at {preset.width}x{preset.height}) "
          f"in {time.perf_counter() - start:.1f} s")
    return 0
