"""``parksim reconstruct``: train a Gaussian scene from a dataset directory and write a scene bundle."""

from __future__ import annotations

import argparse
from pathlib import Path

from ..device import DEVICE_HELP

__all__ = ["add_parser", "run"]


def add_parser(sub: argparse._SubParsersAction) -> argparse.ArgumentParser:
    """Register ``reconstruct`` (cheap: no heavy imports)."""
    p = sub.add_parser(
        "reconstruct", help="train a Gaussian scene from surround-view fisheye data (photometric phase)",
        description="Fit 3D Gaussians to a dataset's fisheye images (ParkGaussian's photometric phase: "
                    "(1-0.2) L1 + 0.2 D-SSIM over each camera's valid pixels, Adam with the 3DGS schedule, "
                    "MCMC densification) and write a scene bundle to OUTPUT: gaussians.ply, rig.json, map.json, "
                    "bundle.json, config.yaml, metrics.jsonl/png. Checkpoints go to OUTPUT/checkpoints/; "
                    "--resume continues a killed run exactly; --from RUN continues a finished photometric run's "
                    "checkpoint into this config's slot-aware phase (phase 1 shared by several variants).")
    p.add_argument("data", type=Path, help="dataset directory (parksim synth layout)")
    p.add_argument("-o", "--output", type=Path, required=True, help="scene bundle folder, e.g. scenes/NAME")
    p.add_argument("--config", help="training config: a YAML path or a packaged preset name "
                   "(tiny, demo, cpu_fast, cpu_slot_aware, cpu_real, gpu_fast, gpu_paper, parkgaussian; default: the "
                   "paper's, parkgaussian)")
    p.add_argument("--device", help=f"{DEVICE_HELP}; default: the config's run.device (cpu unless a preset says "
                   "otherwise: gpu_* say cuda); a resumed run may continue on another device")
    p.add_argument("--resume", action="store_true", help="continue the run in OUTPUT from its last checkpoint")
    p.add_argument("--from", dest="start_from", type=Path, metavar="RUN",
                   help="start from the finished photometric run in RUN (its checkpoints/last.pt): train only the "
                        "slot-aware phase; RUN must have used this config's init, lr, photometric and densify")
    return p


def run(args: argparse.Namespace) -> int:
    """Train (or resume) and write the bundle."""
    from parksim.recon.reconstruct import reconstruct

    from ..device import resolve_device
    from .outputs import check_output_folder

    if args.device is not None:
        resolve_device(args.device)   # a bad name or a missing GPU: one line before anything is read or written
    check_output_folder(args.output)
    reconstruct(args.data, args.output, args.config, resume=args.resume, start_from=args.start_from,
                device=args.device)
    return 0
