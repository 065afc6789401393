"""``parksim compact``: a smaller, faster-to-serve copy of a scene bundle (pruned, SH lowered, per-cell visibility)."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import TYPE_CHECKING

from ..device import DEVICE_HELP
from .argtypes import integer, number

if TYPE_CHECKING:
    from ..data import DatasetReader

__all__ = ["add_parser", "run"]


def add_parser(sub: argparse._SubParsersAction) -> argparse.ArgumentParser:
    """Register ``compact`` (cheap: no heavy imports)."""
    p = sub.add_parser(
        "compact", help="prune a scene bundle to the Gaussians that show, for faster serving",
        description="Sample drivable ego poses in each cell of a grid over the bundle's garage (map.json), render "
                    "the four cameras there and record each Gaussian's largest blending weight (alpha x "
                    "transmittance at any pixel) and the Gaussian-pixel pairs it makes the compositor evaluate. Then "
                    "keep the Gaussians that show (weight above --min-weight; those never seen are always dropped), "
                    "at most --budget of them, ranked by --ranking; fine-tune the kept ones for --finetune "
                    "photometric steps on the bundle's training views (no densification, low learning rates); zero "
                    "the SH bands whose view-dependent colour change stays below --sh-tolerance (the scene's SH "
                    "degree drops when no Gaussian needs it); and store per cell the Gaussians seen from it "
                    "(visibility.npz; at most --cell-budget of them, the most visible from the cell first), so "
                    "that serving renders only those at poses in that cell. OUTPUT is written only once complete.")
    p.add_argument("bundle", type=Path, help="scene bundle folder (parksim reconstruct output) with a map.json")
    p.add_argument("-o", "--output", type=Path, required=True, help="compact bundle folder to write")
    p.add_argument("--budget", type=number(0, open_low=True), default=1.0,
                   help="Gaussians to keep: a fraction of the scene when <= 1 (0.5 = half), else a count (40000)")
    p.add_argument("--ranking", choices=("weight", "benefit-cost"), default="weight",
                   help="how --budget ranks Gaussians: weight (largest blending weight at the measured poses; with "
                        "fine-tuning it lost the least PSNR at every budget measured) or benefit-cost (blending "
                        "weight summed over the training views, per Gaussian-pixel pair at the measured poses; "
                        "needs the dataset)")
    p.add_argument("--finetune", type=integer(0), default=None, metavar="N",
                   help="photometric steps on the bundle's training views after pruning, Gaussian count fixed "
                        "(default 300, parksim.recon.finetune.FINETUNE_ITERATIONS; 0: none, no dataset needed)")
    p.add_argument("--dataset", type=Path,
                   help="the training dataset folder (default: the one bundle.json records); read by the "
                        "benefit-cost ranking and --finetune")
    p.add_argument("--cell-budget", type=number(0, open_low=True), default=1.0,
                   help="Gaussians each visibility cell serves, as a fraction (<= 1) or count (> 1) of the kept ones: "
                        "the most visible from the cell's poses first")
    p.add_argument("--min-weight", type=number(0, 1, open_high=True), default=0.0,
                   help="a Gaussian (and a cell's visibility entry) needs a blending weight above this somewhere; "
                        "in [0, 1)")
    p.add_argument("--sh-tolerance", type=number(0), default=0.01,
                   help="largest colour change (0-1 scale, any direction) allowed when dropping a Gaussian's SH bands")
    p.add_argument("--cell", type=number(0, open_low=True), default=4.0, help="visibility cell size (m)")
    p.add_argument("--poses-per-cell", type=integer(1), default=16, help="drivable poses measured per cell")
    p.add_argument("--margin", type=number(0), default=1.0,
                   help="a cell's poses are drawn from the cell grown by this (m), to cover its borders")
    p.add_argument("--no-visibility", action="store_true", help="do not store per-cell visibility")
    p.add_argument("--seed", type=int, default=0, help="pose sampling seed")
    p.add_argument("--device", default="auto", help=DEVICE_HELP)
    p.add_argument("--overwrite", action="store_true", help="replace OUTPUT if it exists")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    return p


def run(args: argparse.Namespace) -> int:
    """Check the arguments, compact, write OUTPUT atomically and print a summary."""
    from parksim.recon.finetune import FINETUNE_ITERATIONS, bundle_config, finetune

    from ..bundle import load, save
    from ..compact import CompactOptions, compact_bundle
    from ..compact.poses import garage_extent
    from ..device import describe_device, resolve_device
    from ..fileio import atomic_directory
    from .outputs import check_output_folder

    device = resolve_device(args.device)
    check_output_folder(args.output, overwrite=args.overwrite)
    options = CompactOptions(args.budget, args.cell_budget, args.min_weight, args.sh_tolerance, args.cell,
                             args.poses_per_cell, args.margin, args.seed, not args.no_visibility, args.ranking)
    steps = FINETUNE_ITERATIONS if args.finetune is None else args.finetune
    bundle = load(args.bundle)
    bundle.scene = bundle.scene.to(device=device)   # compaction runs where the Gaussians are
    garage_extent(bundle.map)   # a bundle that cannot be compacted says so before the dataset is looked for
    reader = _dataset(args.dataset, bundle.meta) if steps or args.ranking == "benefit-cost" else None
    config = bundle_config(args.bundle, bundle.meta)
    tune = ((lambda b: finetune(b, reader, steps, config, progress=not args.quiet))
            if steps and reader is not None else None)
    compact = compact_bundle(bundle, options, progress=not args.quiet, reader=reader, tune=tune)
    with atomic_directory(args.output) as tmp:
        save(tmp, compact)
    r = compact.meta["compaction"]
    cells = (f", {r['cells']} visibility cells of {r['cell_gaussians_mean']:.0f} Gaussians on average"
             if "cells" in r else "")
    tuned = compact.meta.get("finetune") if steps else None
    note = (f"; fine-tuned {tuned['iterations']} steps, loss {tuned['loss_first_tenth']:.4f} -> "
            f"{tuned['loss_last_tenth']:.4f}" if tuned else "")
    print(f"{args.output}: {r['gaussians']} of {r['source_gaussians']} Gaussians ({r['ranking']} ranking), SH degree "
          f"{r['sh_degree']} (per Gaussian: {r['sh_degree_counts']}), measured from {r['poses']} poses on "
          f"{describe_device(device)}{cells}{note}")
    return 0


def _dataset(path: Path | None, meta: dict) -> DatasetReader:
    """The training dataset: ``path``, else the folder bundle.json records; ValueError naming what is missing."""
    from ..data import DatasetReader

    if path is None:
        if not meta.get("dataset"):
            raise ValueError("bundle.json records no dataset: pass --dataset DATA (or --ranking weight --finetune 0)")
        path = Path(meta["dataset"])
    if not path.is_dir():
        raise ValueError(f"{path}: training dataset folder not found: pass --dataset DATA "
                         "(or --ranking weight --finetune 0)")
    return DatasetReader(path)
