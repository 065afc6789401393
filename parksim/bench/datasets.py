"""Datasets the suites measure on: synthetic garages made once under the work folder and reused.

The package never looks for a checkout: a suite is given a dataset (``--dataset``) or makes one here with
``parksim synth``, in a child process so its worker pool and memory go away with it.
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

from .suite import Context

__all__ = ["ensure_dataset", "synth_dataset", "QUICK_SCENE"]

QUICK_SCENE = "tiny"
"""The synth preset every suite uses under ``--quick`` (160x120, 12 frames: seconds)."""


def synth_dataset(scene: str, data_root: Path, resolution: str | None) -> Path:
    """``data_root/<scene>_<width>`` (``<scene>`` without a resolution or with ``native``), made by ``parksim synth``
    if missing.

    Args:
        scene: a synth preset (``scene1`` ... ``scene4``, ``worn``, ``busy``, ``tiny``).
        data_root: the folder datasets are kept in.
        resolution: ``WxH``, or None / ``native`` for the preset's own.

    Returns:
        The dataset folder.
    """
    resolution = None if resolution == "native" else resolution
    data = data_root / (f"{scene}_{resolution.split('x')[0]}" if resolution else scene)
    if not data.is_dir():
        cmd = [sys.executable, "-m", "parksim.cli", "synth", scene, "-o", str(data), "--quiet"]
        subprocess.run(cmd + (["--resolution", resolution] if resolution else []), check=True)
    return data


def ensure_dataset(context: Context, scene: str, resolution: str | None) -> Path:
    """The suite's default dataset: ``scene`` at ``resolution`` under ``context.work/data``, or the tiny garage
    under ``--quick``.

    Args:
        context: the run's context (work folder, quick).
        scene: synth preset of a full run.
        resolution: its ``WxH`` (None: the preset's own).

    Returns:
        The dataset folder (made on first use).
    """
    if context.quick:
        return synth_dataset(QUICK_SCENE, context.work / "data", None)
    return synth_dataset(scene, context.work / "data", resolution)
