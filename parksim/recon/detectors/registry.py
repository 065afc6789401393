"""Detector classes by checkpoint ``kind`` and loading a trained one.

The one module that imports every model: ``dmpr`` and ``gcn`` build on ``base``, which knows no subclass, so
the package's imports form no cycle.
"""

from __future__ import annotations

from pathlib import Path

import torch

from .base import Detector
from .dmpr import DMPRDetector
from .gcn import GCNDetector

__all__ = ["DETECTORS", "load_detector"]

DETECTORS: dict[str, type[Detector]] = {cls.kind: cls for cls in (DMPRDetector, GCNDetector)}
"""Detector class of each checkpoint ``kind``."""


def load_detector(path: str | Path, map_location: str = "cpu") -> Detector:
    """A trained detector in eval mode.

    Args:
        path: ``model.pt`` as written by ``parksim.recon.detectors.train``, or its folder.
        map_location: device the weights are loaded to.

    Returns:
        The checkpoint's ``DMPRDetector`` or ``GCNDetector``.

    Raises:
        FileNotFoundError: no checkpoint at ``path``.
        ValueError: the file is not a detector checkpoint.
    """
    path = Path(path)
    if path.is_dir():
        path = path / "model.pt"
    if not path.is_file():
        raise FileNotFoundError(f"{path}: detector checkpoint not found")
    ckpt = torch.load(path, map_location=map_location, weights_only=True)
    if not isinstance(ckpt, dict) or ckpt.get("kind") not in DETECTORS:
        raise ValueError(f"{path}: not a detector checkpoint (expected kind {' or '.join(map(repr, DETECTORS))})")
    return DETECTORS[ckpt["kind"]].from_checkpoint(ckpt)
