"""``parksim demo``: the main job end to end on built-in data (what ``make demo`` runs)."""

from __future__ import annotations

import argparse
from pathlib import Path


def add_parser(sub: argparse._SubParsersAction) -> argparse.ArgumentParser:
    p = sub.add_parser(
        "demo", help="run the main job end to end on built-in data",
        description="Run ParkSim's main job on built-in data and write the results to OUTPUT: "
                    "the differentiable IPM of the real surround-view sample.",
        formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    p.add_argument("--sample", type=Path, default=Path("../shared/data/surround-view-sample"),
                   help="the real surround-view sample folder")
    p.add_argument("-o", "--output", type=Path, default=Path("out/demo"), help="output folder")
    return p


def run(args: argparse.Namespace) -> int:
    from . import ipm

    args.output.mkdir(parents=True, exist_ok=True)
    print("[1/1] IPM of the real surround-view sample")
    ipm.run(argparse.Namespace(source=args.sample, output=args.output / "sample_bev.png", rig=None, image=[],
                               m_per_px=0.02, save_rig=args.output / "sample_rig.json"))
    print(f"done: results in {args.output}/")
    return 0
