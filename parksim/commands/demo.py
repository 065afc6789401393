"""``parksim demo``: the main job end to end on built-in data (what ``make demo`` runs).

Each step is an ordinary ``parksim`` command line, so the demo shows exactly what a user would type.
"""

from __future__ import annotations

import argparse
from pathlib import Path

# Pieces of the main job that later steps will run once they exist.
NOT_BUILT_YET = ["reconstruct (train Gaussians on the synthetic garage)", "render/serve the trained scene"]


def add_parser(sub: argparse._SubParsersAction) -> argparse.ArgumentParser:
    p = sub.add_parser(
        "demo", help="run the main job end to end on built-in data",
        description="Run ParkSim's main job on built-in data and write everything to OUTPUT: a small "
                    "synthetic garage (parksim synth), and the IPM of the real surround-view sample.",
        formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    p.add_argument("--sample", type=Path, default=Path("../shared/data/surround-view-sample"),
                   help="the real surround-view sample folder")
    p.add_argument("--preset", default="tiny", help="synthetic garage preset to build")
    p.add_argument("-o", "--output", type=Path, default=Path("out/demo"), help="output folder")
    return p


def run(args: argparse.Namespace) -> int:
    from ..cli import main

    out = args.output
    out.mkdir(parents=True, exist_ok=True)
    steps = [
        ("synthetic garage", ["synth", args.preset, "-o", str(out / "data"), "--overwrite"]),
        ("IPM of the real surround-view sample", ["ipm", str(args.sample), "-o", str(out / "sample_bev.png"),
                                                  "--save-rig", str(out / "sample_rig.json")]),
    ]
    for i, (what, argv) in enumerate(steps, 1):
        print(f"[{i}/{len(steps)}] {what}: parksim {' '.join(argv)}", flush=True)
        rc = main(argv)
        if rc:
            return rc
    print(f"done: results in {out}/")
    if NOT_BUILT_YET:
        print("not built yet: " + "; ".join(NOT_BUILT_YET))
    return 0
