"""``parksim eval``: PSNR/SSIM (and LPIPS when weights are given) of scene bundles on a dataset's test frames,
and the paper's tables (slot detection on rendered vs ground-truth BEVs, ablation) when detectors are given."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import TYPE_CHECKING

from ..device import DEVICE_HELP
from .argtypes import integer, number

if TYPE_CHECKING:
    import torch

__all__ = ["add_parser", "run"]


def _run_arg(text: str) -> tuple[Path, str | None]:
    """``DIR`` or ``LABEL=DIR``."""
    label, sep, path = text.rpartition("=")
    return (Path(path), label) if sep and label else (Path(text), None)


def parse_detector(text: str) -> tuple[str, Path]:
    """``KIND=PATH`` with KIND dmpr or gcn (an argparse type; the benchmarks parse detectors with it too)."""
    kind, sep, path = text.partition("=")
    if not sep or kind not in ("dmpr", "gcn") or not path:
        raise argparse.ArgumentTypeError(f"expected dmpr=PATH or gcn=PATH, got {text!r}")
    return kind, Path(path)


def add_parser(sub: argparse._SubParsersAction) -> argparse.ArgumentParser:
    """Register ``eval`` (cheap: no heavy imports)."""
    p = sub.add_parser(
        "eval", help="score trained scenes on the test frames (PSNR, SSIM, slot regions, BEV slot detection)",
        description="Render every test frame (split.json; every 10th frame) from all cameras and score PSNR and "
                    "SSIM over each camera's valid pixels and over slot regions (floor within 0.5 m of a slot line). "
                    "One SCENE without --detector: eval.json, eval.md and side-by-side PNGs (render | ground truth) "
                    "in OUTPUT; LPIPS only from weights given by path. With --detector (or several SCENEs): the "
                    "paper's tables in OUTPUT/tables.md (+ tables.json): novel-view PSNR/SSIM, each detector's "
                    "marking-point and slot precision/recall on the ground-truth BEVs (IPM of the dataset's "
                    "images: the GT- rows) and on each scene's rendered BEVs, the ablation table, and "
                    "panel_<detector>.png (ground-truth vs rendered BEVs; labels green, detections red). Files "
                    "already in OUTPUT stay; the new ones appear only once all are written. When DATA has an "
                    "off-path split (DATA/offpath/, `parksim offpath`), its views are scored too, grouped by "
                    "lateral and yaw offset and along parking manoeuvres: a table in eval.md and offpath.png, or "
                    "with --detector per-group detection in tables.md (docs/offpath.md).")
    p.add_argument("scenes", nargs="+", type=_run_arg, metavar="SCENE",
                   help="scene bundle folder (parksim reconstruct output), or LABEL=FOLDER to name its table row")
    p.add_argument("data", type=Path, help="dataset directory with the test frames and slot labels")
    p.add_argument("-o", "--output", type=Path, help="report folder (default: SCENE/eval; required for several)")
    p.add_argument("--detector", action="append", type=parse_detector, default=[], metavar="KIND=PATH",
                   help="trained detector (dmpr=detectors/dmpr, gcn=detectors/gcn/model.pt); repeat for both")
    p.add_argument("--threshold", type=number(0, 1, open_low=True, open_high=True), default=0.5,
                   help="detectors' marking-point confidence threshold, in (0, 1)")
    p.add_argument("--protocol", choices=["parksim", "dmpr-ps"], default="parksim",
                   help="detection scoring rules: ParkSim's (metric, slot-angle check) or DMPR-PS' published ones "
                        "(shape check, label-first matching, 11-point AP, 5 %% border); docs/detection_protocol.md")
    p.add_argument("--no-offpath", action="store_true",
                   help="skip the off-path split (DATA/offpath/) even when the dataset has one")
    p.add_argument("--panel-frames", type=integer(0), default=3, help="test frames shown in each detection panel")
    p.add_argument("--backend", default="auto", choices=["auto", "torch", "numba"], help="rasterizer backend")
    p.add_argument("--device", default="auto", help=f"{DEVICE_HELP}; renders, scores and LPIPS run there, the "
                   "detectors on the CPU")
    p.add_argument("--projection", choices=["ut", "ewa"],
                   help="render with this projection instead of the one the scene was trained with (which is what "
                        "`parksim serve` renders with); one SCENE without --detector only")
    p.add_argument("--image-scale", type=number(0, 1, open_low=True),
                   help="score at this image scale, in (0, 1] (default: the one the scene was trained at, its "
                        "config's data.image_scale); one SCENE without --detector only")
    p.add_argument("--lpips-net", choices=["alex", "vgg"], default="alex", help="LPIPS backbone")
    p.add_argument("--lpips-backbone", type=Path, help="torchvision AlexNet/VGG16 ImageNet state dict (.pth)")
    p.add_argument("--lpips-weights", type=Path, help="LPIPS v0.1 linear-head weights (alex.pth / vgg.pth)")
    return p


def _announce(device: torch.device) -> None:
    """The one stderr line saying where the scenes render, once the arguments are checked and before any work."""
    import sys

    from ..device import describe_device

    print(f"evaluating on {describe_device(device)}", file=sys.stderr)


def _tables(args: argparse.Namespace, out: Path, device: torch.device) -> int:
    from parksim.recon.detectors import DecodeOptions
    from parksim.recon.detectors.protocols import get_protocol
    from parksim.recon.paper_eval import evaluate_runs
    from parksim.recon.slot_aware import DetectorRef

    from ..fileio import atomic_files

    if args.lpips_backbone is not None:
        raise ValueError("LPIPS is computed for a single SCENE without --detector")
    if len({kind for kind, _ in args.detector}) != len(args.detector):
        raise ValueError("give each detector kind once")
    detectors = {kind: DetectorRef(kind=kind, path=str(path)).load() for kind, path in args.detector}
    _announce(device)
    atomic_files(out, lambda tmp: evaluate_runs(args.scenes, args.data, detectors, tmp, args.backend,
                                                args.panel_frames, DecodeOptions(threshold=args.threshold),
                                                get_protocol(args.protocol), offpath=not args.no_offpath,
                                                device=device))
    print((out / "tables.md").read_text(), end="")
    print(f"report: {out}/tables.json, panels: " + (", ".join(f"{out}/panel_{k}.png" for k in detectors) or "none"))
    return 0


def run(args: argparse.Namespace) -> int:
    """Evaluate and print the table(s)."""
    from ..device import resolve_device
    from .outputs import check_output_folder

    device = resolve_device(args.device)
    if len(args.scenes) > 1 and args.output is None:
        raise ValueError("several SCENEs need -o/--output")
    out = args.output or args.scenes[0][0] / "eval"
    check_output_folder(out)
    if args.detector or len(args.scenes) > 1:
        if args.projection is not None or args.image_scale is not None:
            raise ValueError("--projection and --image-scale apply to one SCENE without --detector")
        return _tables(args, out, device)
    from parksim.recon.evaluate import evaluate_bundle

    from ..fileio import atomic_files

    lpips = None
    if (args.lpips_backbone is None) != (args.lpips_weights is None):
        raise ValueError("LPIPS needs both --lpips-backbone and --lpips-weights")
    if args.lpips_backbone is not None:
        from parksim.recon.lpips import LPIPS

        lpips = LPIPS(args.lpips_net, args.lpips_backbone, args.lpips_weights, device)
    scene = args.scenes[0][0]
    result: dict = {}
    _announce(device)
    atomic_files(out, lambda tmp: result.update(evaluate_bundle(scene, args.data, tmp, args.backend, lpips,
                                                                offpath=not args.no_offpath,
                                                                projection=args.projection, device=device,
                                                                image_scale=args.image_scale)))
    print((out / "eval.md").read_text(), end="")
    plot = f", off-path plot: {out}/offpath.png" if "offpath" in result else ""
    print(f"report: {out}/eval.json, side-by-sides: {out}/renders/{plot}")
    return 0
