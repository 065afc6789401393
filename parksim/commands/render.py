"""``parksim render``: render a trained scene bundle at an ego pose to PNGs (fisheye views, BEV, depth)."""

from __future__ import annotations

import argparse
from pathlib import Path

from ..device import DEVICE_HELP
from .argtypes import number

__all__ = ["add_parser", "run"]


def add_parser(sub: argparse._SubParsersAction) -> argparse.ArgumentParser:
    p = sub.add_parser(
        "render", help="render a scene bundle at an ego pose (fisheye views, BEV, depth)",
        description="Render a trained scene bundle (parksim reconstruct output) at one ego pose and write "
                    "OUTPUT/<camera>.png for each camera asked for, OUTPUT/bev.png with --bev and "
                    "OUTPUT/<camera>_depth.npy (metres along the ray, 0 where nothing is hit) with --depth. "
                    "Files already in OUTPUT stay; the new ones appear only once all are rendered.")
    p.add_argument("bundle", type=Path, help="scene bundle folder")
    p.add_argument("--pose", required=True, metavar="X,Y,YAW",
                   help="ego pose T_world_vehicle: 'x,y,yaw' (m, rad) or 'x,y,z,roll,pitch,yaw'")
    p.add_argument("--cameras", help="comma-separated subset of the rig's cameras (default: all)")
    p.add_argument("--bev", action="store_true", help="also build the bird's-eye view (IPM of the rendered views)")
    p.add_argument("--depth", action="store_true", help="also write each camera's depth map as .npy")
    p.add_argument("--scale", type=number(0, 4, open_low=True), default=1.0,
                   help="resolution factor of the fisheye views, in (0, 4]")
    p.add_argument("--device", default="auto", help=DEVICE_HELP)
    p.add_argument("-o", "--output", type=Path, required=True, help="output folder")
    return p


def _pose(text: str) -> list[float]:
    try:
        return [float(v) for v in text.split(",")]
    except ValueError:
        raise ValueError(f"--pose must be comma-separated numbers like 3.5,-1.2,0.3; got {text!r}") from None


def run(args: argparse.Namespace) -> int:
    import time

    import numpy as np
    import torch

    from ..bundle import load
    from ..device import describe_device, resolve_device
    from ..fileio import atomic_files
    from ..geometry import as_pose
    from ..imageio import write_image
    from ..render import render
    from .outputs import check_output_folder

    device = resolve_device(args.device)
    pose = as_pose(_pose(args.pose))
    check_output_folder(args.output)
    bundle = load(args.bundle)
    cameras = [c.strip() for c in args.cameras.split(",")] if args.cameras else None
    unknown = [c for c in cameras or [] if c not in bundle.rig.cameras]
    if unknown:
        raise ValueError(f"unknown camera(s) {unknown}; the rig has {bundle.rig.names}")
    scene = bundle.scene.to(device=device)
    start = time.perf_counter()
    out = render(scene, bundle.rig, pose, cameras=cameras, bev=args.bev, scale=args.scale)
    if device.type == "cuda":
        torch.cuda.synchronize(device)   # the time of the render, not of queueing its kernels
    took = time.perf_counter() - start

    def write(folder: Path) -> None:
        for name, image in out.images.items():
            write_image(folder / f"{name}.png", image)
            if args.depth:
                np.save(folder / f"{name}_depth.npy", out.depth[name].detach().cpu().numpy())
        if out.bev is not None:
            write_image(folder / "bev.png", out.bev)

    atomic_files(args.output, write)
    what = ", ".join(list(out.images) + (["bev"] if out.bev is not None else []))
    print(f"rendered {what} from {len(scene)} Gaussians on {describe_device(device)} in {took * 1000:.0f} ms "
          f"-> {args.output}/")
    return 0
