"""Trained bundles the suites measure on: a synthetic garage reconstructed with a packaged config, made once under
the work folder and reused.

The package never looks for a checkout: a suite is given a bundle (``--bundle`` / ``--run``) or makes one here with
``parksim reconstruct``, in a child process so the trainer's heap settings (``parksim.recon.heap``) and memory stay
out of the process that measures. Under ``--quick`` it is the tiny garage with the ``tiny`` config (seconds).
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

from .datasets import ensure_dataset
from .suite import Context

__all__ = ["ensure_bundle", "finished", "QUICK_CONFIG"]

QUICK_CONFIG = "tiny"
"""The packaged config every suite trains with under ``--quick`` (20 iterations: seconds)."""


def finished(run: Path) -> bool:
    """Whether ``run`` holds a finished ``parksim reconstruct`` output (its bundle written)."""
    return (run / "bundle.json").is_file()


def ensure_bundle(context: Context, scene: str, resolution: str | None, config: str) -> tuple[Path, Path]:
    """The suite's default trained bundle: ``scene`` at ``resolution`` reconstructed with the packaged ``config``
    under ``context.work/bundles``, or the tiny garage with the ``tiny`` config under ``--quick``.

    Args:
        context: the run's context (work folder, quick, quiet).
        scene: synth preset of a full run (``parksim.bench.datasets.ensure_dataset``).
        resolution: its ``WxH`` (None: the preset's own).
        config: packaged config name of a full run (``cpu_fast``, ``cpu_30min``, ...).

    Returns:
        (run folder, dataset): the run folder is the bundle, with its config and last checkpoint. A run left
        unfinished (a checkpoint, no bundle) is resumed.
    """
    from ..recon.checkpoint import checkpoint_path

    dataset = ensure_dataset(context, scene, resolution)
    config = QUICK_CONFIG if context.quick else config
    run = context.work / "bundles" / f"{dataset.name}_{config}"
    if not finished(run):
        cmd = [sys.executable, "-m", "parksim.cli", "reconstruct", str(dataset), "-o", str(run), "--config", config]
        resume = checkpoint_path(run).is_file()
        subprocess.run(cmd + (["--resume"] if resume else []), check=True,
                       stdout=subprocess.DEVNULL if context.quiet else None)
    return run, dataset
