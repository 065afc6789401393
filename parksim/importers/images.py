"""Image sources shared by the importers: a file decoded to uint8 RGB when the dataset is written, resampled to a
pinhole when its lens has radial-tangential (Brown-Conrady) distortion."""

from __future__ import annotations

import functools
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .recording import ImageSource, RecordingError

__all__ = ["Distortion", "undistortion_maps", "image_source", "frame_number"]


def frame_number(name: str, where: str) -> int:
    """The frame an image file belongs to: the last integer in its stem (``frame_00012.png``, ``000012.png`` -> 12).
    ``where`` names the entry at fault when there is none."""
    digits = re.findall(r"\d+", Path(name).stem)
    if not digits:
        raise RecordingError(f"{where}: no frame number in the file name {Path(name).name!r}")
    return int(digits[-1])


@dataclass(frozen=True)
class Distortion:
    """A perspective lens with radial ``1 + k1 r^2 + k2 r^4 + k3 r^6 + k4 r^8`` and tangential p1, p2 distortion,
    centre in ParkSim's convention (first pixel centre at 0). The k1 k2 p1 p2 (k3) of COLMAP and OpenCV are the
    same terms; nerfstudio's k4 is the r^8 term."""

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    k: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 0.0)
    p: tuple[float, float] = (0.0, 0.0)


@functools.lru_cache(maxsize=16)
def undistortion_maps(lens: Distortion) -> tuple[np.ndarray, np.ndarray]:
    """``cv2.remap`` maps: the source pixel of every pixel of the undistorted pinhole (same fx, fy, cx, cy).
    Made once per lens (cached) and shared by all of its images."""
    k1, k2, k3, k4 = lens.k
    p1, p2 = lens.p
    v, u = np.mgrid[0:lens.height, 0:lens.width].astype(np.float64)
    x, y = (u - lens.cx) / lens.fx, (v - lens.cy) / lens.fy
    r = x * x + y * y
    d = 1.0 + r * (k1 + r * (k2 + r * (k3 + r * k4)))
    xd = x * d + 2.0 * p1 * x * y + p2 * (r + 2.0 * x * x)
    yd = y * d + 2.0 * p2 * x * y + p1 * (r + 2.0 * y * y)
    return (lens.fx * xd + lens.cx).astype(np.float32), (lens.fy * yd + lens.cy).astype(np.float32)


def image_source(path: Path, lens: Distortion | None = None) -> ImageSource:
    """Decode ``path`` as uint8 RGB when called (EXIF orientation ignored, as nerfstudio and COLMAP do),
    undistorted to a pinhole when ``lens`` is given: bilinear, black where the source has no pixel."""
    def read() -> np.ndarray:
        import cv2

        img = cv2.imread(str(path), cv2.IMREAD_COLOR | cv2.IMREAD_IGNORE_ORIENTATION)
        if img is None:
            raise RecordingError(f"{path}: cannot decode the image (missing, corrupt or unsupported)")
        rgb = cv2.cvtColor(img, cv2.COLOR_BGR2RGB)
        if lens is None:
            return rgb
        mx, my = undistortion_maps(lens)
        return cv2.remap(rgb, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)

    return read
