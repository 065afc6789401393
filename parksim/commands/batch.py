"""``parksim batch``: reconstruct many datasets as Ray tasks, one scene bundle per dataset under SCENES/."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import TYPE_CHECKING

from ..device import DEVICE_HELP
from .argtypes import integer, number

if TYPE_CHECKING:
    from parksim.recon.batch import Outcome

__all__ = ["add_parser", "run", "summary_table"]


def add_parser(sub: argparse._SubParsersAction) -> argparse.ArgumentParser:
    """Register ``batch`` (cheap: no heavy imports, no Ray)."""
    p = sub.add_parser(
        "batch", help="reconstruct many datasets as Ray tasks (needs parksim[ray])",
        description="Train one scene per dataset as a Ray task, each writing its bundle to SCENES/<dataset folder "
                    "name>/ as `parksim reconstruct` does. Scenes whose bundle is already written are skipped; a scene "
                    "with a checkpoint resumes from it. A failed task is retried (from its last checkpoint) and "
                    "reported; the others still finish. Prints each scene's progress as it trains and a summary "
                    "table; exits 1 if any scene failed. Without --address a local Ray instance is started.")
    p.add_argument("data", type=Path, nargs="+", help="dataset directories (parksim synth layout)")
    p.add_argument("-o", "--output", type=Path, required=True, help="folder of scene bundles, e.g. scenes/")
    p.add_argument("--config", default="parkgaussian",
                   help="training config for every scene: a YAML path or a packaged preset name (tiny, demo, "
                        "cpu_fast, cpu_slot_aware, cpu_real, gpu_fast, gpu_paper, parkgaussian)")
    p.add_argument("--address", help="join the Ray cluster at this address (e.g. auto, or HEAD_IP:6379); datasets "
                   "and SCENES must be on a file system every node sees")
    p.add_argument("--cpus-per-task", type=integer(1),
                   help="Ray CPUs (and torch threads) per scene (default: the cluster's CPUs shared by the scenes "
                        "to train, at most one node's)")
    p.add_argument("--device", help=f"{DEVICE_HELP}; default: the config's run.device. Each task resolves it on its "
                   "node (without --address it is checked here first); a task's GPUs are numbered from cuda:0")
    p.add_argument("--gpus-per-task", type=number(0), default=0.0,
                   help="Ray GPUs each scene reserves, fractions allowed (0.5: two scenes share one GPU); a cuda "
                        "device needs > 0 (default 0)")
    p.add_argument("--retries", type=integer(0, 10), default=1, help="retries of a failed scene")
    p.add_argument("--progress-every", type=number(0), default=10.0, metavar="SECONDS",
                   help="print each scene's iteration and PSNR at most this often")
    return p


def summary_table(outcomes: list[Outcome]) -> str:
    """One row per scene: status, attempts, iterations, Gaussians, training seconds, last train PSNR, error."""
    def cell(value: object, fmt: str = "") -> str:
        return "-" if value is None else format(value, fmt)

    rows = [("scene", "status", "attempts", "iterations", "gaussians", "seconds", "psnr", "detail")]
    rows += [(o.name, o.status, str(o.attempts), cell(o.iterations), cell(o.gaussians), cell(o.seconds, ".1f"),
              cell(o.psnr, ".2f"), o.detail) for o in outcomes]
    widths = [max(len(r[i]) for r in rows) for i in range(len(rows[0]) - 1)]
    return "\n".join("  ".join(c.ljust(w) for c, w in zip(r, widths)) + "  " + r[-1] for r in rows)


def run(args: argparse.Namespace) -> int:
    """Plan, train the scenes as Ray tasks, print the summary; 1 when any scene failed."""
    try:
        import ray  # noqa: F401
    except ImportError:
        raise ValueError("Ray is not installed: install parksim[ray]") from None
    from parksim.recon.batch import plan_scenes, ray_session, run_batch
    from parksim.recon.config import load_config

    from ..device import resolve_device
    from .outputs import check_output_folder

    config = load_config(args.config)
    if args.address is None:   # a local Ray trains here: a bad device name or a missing GPU fails now, in one line
        resolve_device(args.device or config.run.device)
    check_output_folder(args.output)
    scenes = plan_scenes(args.data, args.output)
    with ray_session(args.address):
        outcomes = run_batch(scenes, args.config, args.cpus_per_task, args.retries,
                             report=lambda line: print(line, file=sys.stderr, flush=True),
                             progress_every=args.progress_every, device=args.device,
                             gpus_per_task=args.gpus_per_task)
    print(summary_table(outcomes))
    failed = [o.name for o in outcomes if o.status == "failed"]
    if failed:
        print(f"parksim batch: {len(failed)} of {len(outcomes)} scene(s) failed: {', '.join(failed)}", file=sys.stderr)
    return 1 if failed else 0
