"""``parksim ipm``: stitch surround-view fisheye images into one bird's-eye view PNG."""

from __future__ import annotations

import argparse
from pathlib import Path

from .argtypes import number

__all__ = ["add_parser", "run"]


def add_parser(sub: argparse._SubParsersAction) -> argparse.ArgumentParser:
    p = sub.add_parser(
        "ipm", help="stitch four fisheye images into a bird's-eye view (IPM)",
        description="Stitch surround-view fisheye images into one bird's-eye-view PNG with the "
                    "differentiable IPM. Either give a folder in the surround-view sample's layout "
                    "(yaml/{front,back,left,right}.yaml with ground homographies, images/*.png): the "
                    "camera poses are recovered from the homographies; or give --rig and one --image "
                    "per camera.")
    p.add_argument("source", nargs="?", type=Path,
                   help="surround-view sample folder (omit when using --rig)")
    p.add_argument("-o", "--output", type=Path, required=True, help="BEV PNG to write")
    p.add_argument("--rig", type=Path, help="rig file (JSON/YAML) instead of a sample folder")
    p.add_argument("--image", action="append", default=[], metavar="CAMERA=PATH",
                   help="with --rig: the image of one camera (repeat for each)")
    p.add_argument("--m-per-px", type=number(0, open_low=True), default=0.02,
                   help="BEV ground sampling distance for a sample folder (the sample's own is 0.01)")
    p.add_argument("--save-rig", type=Path, help="also write the rig recovered from a sample folder")
    return p


def run(args: argparse.Namespace) -> int:
    from ..imageio import read_image, write_image
    from ..ipm import IPM
    from .outputs import check_output_file

    for path in (args.output, args.save_rig):
        if path is not None:
            check_output_file(path)

    if args.rig is not None:
        from ..rig import Rig

        rig = Rig.load(args.rig)
        images = {}
        for item in args.image:
            name, sep, path = item.partition("=")
            if not sep or name not in rig.cameras:
                raise ValueError(f"--image expects CAMERA=PATH with CAMERA in {rig.names}, got {item!r}")
            m = rig.cameras[name].model
            images[name] = read_image(path, expect_size=(m.width, m.height))
    elif args.source is not None:
        from ..calib.sample_rig import load_sample_images, sample_rig

        rig, report = sample_rig(args.source, m_per_px=args.m_per_px)
        for name, r in report.items():
            print(f"{name:>5}: pose fitted to the homography over {int(r['points'])} pattern points, "
                  f"residual median {r['median_px']:.2f} px, max {r['max_px']:.2f} px")
        if args.save_rig:
            rig.save(args.save_rig)
        images = load_sample_images(args.source, rig)
    else:
        raise ValueError("give a sample folder or --rig with --image CAMERA=PATH")
    bev = IPM(rig)(images)
    write_image(args.output, bev)
    print(f"wrote {args.output} ({rig.bev.width}x{rig.bev.height} px, {rig.bev.m_per_px * 100:.1f} cm/px)")
    return 0
