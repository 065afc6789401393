"""Data shipped with ParkSim, found from any working folder.

``SAMPLE_DIR`` is the real surround-view sample (four 960x640 fisheye images with OpenCV-YAML intrinsics
and ground homographies; MIT licence, ``surround-view-sample/LICENSE``) that ``parksim demo`` stitches.
"""

from __future__ import annotations

from pathlib import Path

__all__ = ["SAMPLE_DIR"]

SAMPLE_DIR = Path(__file__).resolve().parent / "surround-view-sample"
