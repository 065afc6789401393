"""Detector classes by checkpoint ``kind`` and loading a trained one.

The one module that imports every model: ``gcn`` builds on ``dmpr`` and ``dmpr`` knows no subclass, so the
package's imports form no cycle.
"""

from __future__ import annotations

from pathlib import Path

import torch

from .dmpr import DMPRDetector
from .gcn import GCNDetector

__all__ = ["DETECTORS", "load_detector"]

DETECTORS: dict[str, type[DMPRDetector]] = {cls.kind: cls for cls in (DMPRDetector, GCNDetector)}
"""Detector class of each checkpoint ``kind``."""


def load_detector(path: str | Path, map_location: str = "cpu") -> DMPRDetector:
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
    model = DETECTORS[ckpt["kind"]](**ckpt["config"])
    model.load_state_dict(ckpt["state_dict"])
    return model.eval()
