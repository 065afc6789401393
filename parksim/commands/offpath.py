"""``parksim offpath``: add the off-path test split (ground truth beside and across the recorded path) to a
synthetic dataset."""

from __future__ import annotations

import argparse
from pathlib import Path

from .argtypes import integer

__all__ = ["add_parser", "run"]


def add_parser(subparsers: argparse._SubParsersAction) -> argparse.ArgumentParser:
    """Register ``offpath`` (cheap: no heavy imports)."""
    p = subparsers.add_parser(
        "offpath", help="add an off-path test split (poses beside the recorded path and into slots) to a synthetic "
                        "dataset",
        description="Ray-cast ground truth at ego poses the recording never visited: at every test frame the ego "
                    "moved 0.25, 0.5, 1 and 2 m to either side and turned by +-10 and +-20 deg, and forward-in "
                    "parking manoeuvres into free slots beside the path. Poses whose body overlaps a car, pillar or "
                    "wall are skipped. Writes DATA/offpath/ (a dataset of the same layout, every frame a test frame, "
                    "plus offpath.json describing each frame); `parksim eval` scores it when present. Only for "
                    "`parksim synth` datasets (the scene is rebuilt from DATA/meta.json). See docs/offpath.md.")
    p.add_argument("data", type=Path, help="synthetic dataset directory (parksim synth output)")
    p.add_argument("--workers", type=integer(1), help="render processes (default: all usable cores)")
    p.add_argument("--overwrite", action="store_true", help="replace an existing DATA/offpath/")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    return p


def run(args: argparse.Namespace) -> int:
    """Write the split; prints where, how many poses and how many were skipped."""
    import json
    import time

    from tqdm import tqdm

    from ..data import DatasetReader
    from ..synth.offpath import OFFPATH_FILE, plan_offpath, write_offpath

    start = time.perf_counter()
    with tqdm(desc="offpath", unit="frame", disable=args.quiet) as bar:
        def progress(n: int) -> None:
            if bar.total is None:   # the pose count is known only once the checks have passed
                bar.reset(total=len(plan_offpath(DatasetReader(args.data)).descriptors))
            bar.update(n)
        out = write_offpath(args.data, workers=args.workers, progress=progress, overwrite=args.overwrite)
    info = json.loads((out / OFFPATH_FILE).read_text())
    skipped = ", ".join(f"{k} {v}" for k, v in sorted(info["skipped"].items())) or "none"
    print(f"wrote {out} ({len(info['frames'])} off-path frames; skipped: {skipped}) "
          f"in {time.perf_counter() - start:.1f} s")
    return 0

