"""PNG/JPEG <-> float32 RGB tensors in [0, 1] (HxWx3), with errors that name the file."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from .fileio import atomic_write

__all__ = ["ImageError", "read_image", "write_image", "to_uint8"]


class ImageError(ValueError):
    """An image file is missing, unreadable or of the wrong size."""


def read_image(path: str | Path, expect_size: tuple[int, int] | None = None) -> Tensor:
    """Read an 8-bit image as float32 RGB HxWx3; ``expect_size = (width, height)`` is checked."""
    import cv2

    path = Path(path)
    if not path.is_file():
        raise ImageError(f"image not found: {path}")
    bgr = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if bgr is None:
        raise ImageError(f"cannot decode image (corrupt or not an image): {path}")
    h, w = bgr.shape[:2]
    if expect_size is not None and (w, h) != tuple(expect_size):
        raise ImageError(f"{path} is {w}x{h} but {expect_size[0]}x{expect_size[1]} was expected")
    return torch.from_numpy(np.ascontiguousarray(bgr[..., ::-1])).float().div_(255.0)


def to_uint8(image: Tensor | np.ndarray) -> np.ndarray:
    """Float [0, 1] (any float dtype) -> uint8, rounding; HxW or HxWxC."""
    arr = image.detach().cpu().numpy() if isinstance(image, Tensor) else np.asarray(image)
    if arr.dtype == np.uint8:
        return arr
    return (np.clip(np.nan_to_num(arr, nan=0.0), 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)


def write_image(path: str | Path, image: Tensor | np.ndarray) -> None:
    """Write an RGB (HxWx3) or grey (HxW) image; the file appears whole or not at all."""
    import cv2

    path = Path(path)
    arr = to_uint8(image)
    if arr.ndim == 3:
        arr = np.ascontiguousarray(arr[..., ::-1])

    def encode(tmp: Path) -> None:
        if not cv2.imwrite(str(tmp), arr):
            raise ImageError(f"cannot write image: {path}")

    atomic_write(path, encode)
