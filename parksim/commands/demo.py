"""``parksim demo``: the main job end to end on built-in data (what ``make demo`` runs).

Each step is an ordinary ``parksim`` command line, so the demo shows exactly what a user would type.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from ..assets import SAMPLE_DIR
from .argtypes import integer

__all__ = ["add_parser", "run"]


def add_parser(sub: argparse._SubParsersAction) -> argparse.ArgumentParser:
    p = sub.add_parser(
        "demo", help="run the main job end to end on built-in data",
        description="Run ParkSim's main job on built-in data and write everything to OUTPUT: build a small "
                    "synthetic garage (parksim synth), reconstruct it (parksim reconstruct), score it on the "
                    "test frames (parksim eval), render it at a new pose with its BEV (parksim render), and "
                    "stitch the real surround-view sample into a BEV (parksim ipm).")
    p.add_argument("--sample", type=Path, default=SAMPLE_DIR,
                   help="a surround-view sample folder (images/ + yaml/); the default is the one shipped with ParkSim")
    p.add_argument("--config", default="demo", help="training config: a packaged preset name or a YAML path")
    p.add_argument("--frames", type=integer(2), default=30,
                   help="frames of the synthetic garage (every 10th, from the first, is a test frame)")
    p.add_argument("-o", "--output", type=Path, default=Path("out/demo"), help="output folder")
    return p


def _test_pose(data: Path) -> str:
    """'x,y,yaw' of the dataset's first test frame nudged 0.3 m sideways: a view no camera recorded."""
    from ..data import DatasetReader
    from ..geometry import xy_yaw_from_pose

    reader = DatasetReader(data)
    x, y, yaw = (float(v) for v in xy_yaw_from_pose(reader.pose(reader.split["test"][0])))
    return f"{x:.3f},{y + 0.3:.3f},{yaw:.4f}"


def run(args: argparse.Namespace) -> int:
    from .dispatch import main

    out = args.output
    data, scene = out / "data", out / "scenes" / "garage"
    steps: list[tuple[str, list[str | None]]] = [
        ("synthetic garage", ["synth", "scene1", "-o", str(data), "--resolution", "320x240",
                              "--frames", str(args.frames), "--overwrite"]),
        ("reconstruct", ["reconstruct", str(data), "-o", str(scene), "--config", str(args.config)]),
        ("evaluate on the test frames", ["eval", str(scene), str(data), "-o", str(out / "eval")]),
        ("render a new pose with its BEV", ["render", str(scene), "--pose", None, "--bev", "-o", str(out / "render")]),
        ("IPM of the real surround-view sample", ["ipm", str(args.sample), "-o", str(out / "sample_bev.png"),
                                                  "--save-rig", str(out / "sample_rig.json")]),
    ]
    if scene.exists():
        import shutil

        shutil.rmtree(scene)
    for i, (what, argv) in enumerate(steps, 1):
        line = [_test_pose(data) if a is None else a for a in argv]
        print(f"\n[{i}/{len(steps)}] {what}: parksim {' '.join(line)}", flush=True)
        rc = main(line)
        if rc:
            return rc
    print(f"\ndone: results in {out}/ (eval/eval.md holds the metrics table).\n"
          f"serve the scene to planners: parksim serve --scenes {scene.parent}")
    return 0
