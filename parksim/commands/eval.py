"""``parksim eval``: PSNR/SSIM (and LPIPS when weights are given) of a scene bundle on a dataset's test frames."""

from __future__ import annotations

import argparse
from pathlib import Path


def add_parser(sub: argparse._SubParsersAction) -> argparse.ArgumentParser:
    """Register ``eval`` (cheap: no heavy imports)."""
    p = sub.add_parser(
        "eval", help="score a trained scene on the test frames (PSNR, SSIM, slot regions, optional LPIPS)",
        description="Render every test frame (split.json; every 10th frame) from all cameras, score PSNR and SSIM "
                    "over each camera's valid pixels and over slot regions (floor within 0.5 m of a slot line), "
                    "and write eval.json, eval.md and side-by-side PNGs (render | ground truth) to OUTPUT. "
                    "LPIPS is computed only from weights given by path; otherwise the report says so.",
        formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    p.add_argument("scene", type=Path, help="scene bundle folder (parksim reconstruct output)")
    p.add_argument("data", type=Path, help="dataset directory with the test frames")
    p.add_argument("-o", "--output", type=Path, help="report folder (default: SCENE/eval)")
    p.add_argument("--backend", default="auto", choices=["auto", "torch", "numba"], help="rasterizer backend")
    p.add_argument("--lpips-net", choices=["alex", "vgg"], default="alex", help="LPIPS backbone")
    p.add_argument("--lpips-backbone", type=Path, help="torchvision AlexNet/VGG16 ImageNet state dict (.pth)")
    p.add_argument("--lpips-weights", type=Path, help="LPIPS v0.1 linear-head weights (alex.pth / vgg.pth)")
    return p


def run(args: argparse.Namespace) -> int:
    """Evaluate and print the table."""
    from recon.evaluate import evaluate_bundle

    lpips = None
    if (args.lpips_backbone is None) != (args.lpips_weights is None):
        raise ValueError("LPIPS needs both --lpips-backbone and --lpips-weights")
    if args.lpips_backbone is not None:
        from recon.lpips import LPIPS

        lpips = LPIPS(args.lpips_net, args.lpips_backbone, args.lpips_weights)
    out = args.output or args.scene / "eval"
    evaluate_bundle(args.scene, args.data, out, args.backend, lpips)
    print((out / "eval.md").read_text(), end="")
    print(f"report: {out}/eval.json, side-by-sides: {out}/renders/")
    return 0
