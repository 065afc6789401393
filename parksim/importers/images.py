"""Image sources shared by the importers: a file checked (present, whole, readable, of its camera's size) before
anything is written and decoded to uint8 RGB when the dataset is written, resampled to a pinhole when its lens has
radial-tangential (Brown-Conrady) distortion. A file that fails a check raises ``ImageDefect`` (its frame is
dropped, see ``recording``)."""

from __future__ import annotations

import functools
import os
import re
import sys
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .recording import MISSING_IMAGE, TRUNCATED, UNREADABLE_IMAGE, WRONG_SIZE, ImageDefect, ImageSource, RecordingError

__all__ = ["Distortion", "undistortion_maps", "image_source", "image_defect", "header_size", "frame_number",
           "TRUNCATED", "FileImage"]

_JPEG, _JPEG_END = b"\xff\xd8\xff", b"\xff\xd9"
_PNG, _PNG_END = b"\x89PNG\r\n\x1a\n", b"\x00\x00\x00\x00IEND\xaeB`\x82"
_TAIL = 4096


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


def image_defect(path: Path) -> str | None:
    """Why the file at ``path`` cannot be imported whole, from its first and last bytes only (no decode), or None.

    A JPEG must end with its end-of-image marker FFD9 and a PNG with its IEND chunk (after the zero padding some
    writers add); one that does not was cut short (a JPEG decoder fills the missing rows grey and only warns).
    Other formats, and a file that cannot be opened, are left to the decoder (whose error names the file).
    """
    try:
        with open(path, "rb") as f:
            head = f.read(len(_PNG))
            end = f.seek(0, os.SEEK_END)
            tail = b""
            while end > 0 and not tail.rstrip(b"\0"):
                start = max(0, end - _TAIL)
                f.seek(start)
                tail = f.read(end - start) + tail
                end = start
    except OSError:
        return None
    end_marker = _JPEG_END if head.startswith(_JPEG) else _PNG_END if head.startswith(_PNG) else None
    if end_marker is None or tail.rstrip(b"\0").endswith(end_marker):
        return None
    return TRUNCATED


def header_size(path: Path) -> tuple[int, int]:
    """(width, height) of the image at ``path`` from its header, without decoding the pixels.

    Raises:
        ImageDefect: the file is absent (``MISSING_IMAGE``) or its header is not an image's (``UNREADABLE_IMAGE``).
    """
    from PIL import Image, UnidentifiedImageError

    if not path.is_file():
        raise ImageDefect(MISSING_IMAGE, f"{path}: image file not found")
    try:
        with Image.open(path) as img:
            return img.size
    except (UnidentifiedImageError, OSError) as e:
        raise ImageDefect(UNREADABLE_IMAGE, f"{path}: not a readable image: {e}") from None


@contextmanager
def _decoder_messages() -> Iterator[list[str]]:
    """Catch what C decoders (libjpeg, libpng, OpenCV) print on the process's stderr (file descriptor 2) inside the
    block: the list holds its lines once the block ends, so a failure can say it in one line of its own."""
    lines: list[str] = []
    sys.stderr.flush()
    with tempfile.TemporaryFile() as catch:
        saved = os.dup(2)
        os.dup2(catch.fileno(), 2)
        try:
            yield lines
        finally:
            os.dup2(saved, 2)
            os.close(saved)
            catch.seek(0)
            lines += [ln.strip() for ln in catch.read().decode(errors="replace").splitlines() if ln.strip()]


@dataclass(frozen=True)
class FileImage:
    """An ``ImageSource`` read from a file (a ``CheckedSource``): calling it decodes the file as uint8 RGB (EXIF
    orientation ignored, as nerfstudio and COLMAP do), undistorted to a pinhole when ``lens`` is given (bilinear,
    black where the source has no pixel). ``check`` runs for every image before any is written."""

    path: Path
    lens: Distortion | None = None

    def check(self, size: tuple[int, int]) -> None:
        """Check the file from its header and last bytes only (no decode).

        Args:
            size: its camera's (width, height).

        Raises:
            ImageDefect: the file is absent, cut short (``image_defect``), has no image header, or is not ``size``.
        """
        found = header_size(self.path)
        if image_defect(self.path) is not None:
            raise ImageDefect(TRUNCATED, f"{self.path}: truncated image file (its end marker is missing)")
        if found != size:
            raise ImageDefect(WRONG_SIZE, f"{self.path}: image is {found[0]}x{found[1]} but its camera is "
                                          f"{size[0]}x{size[1]}")

    def __call__(self) -> np.ndarray:
        """The image, decoded (and undistorted when ``lens`` is given).

        Returns:
            ``[H, W, 3]`` uint8 RGB.

        Raises:
            ImageDefect: the file does not decode (the decoder's own message joins the line), or is not the lens's
                size.
        """
        import cv2

        level = cv2.utils.logging.getLogLevel()   # OpenCV's own warning repeats the path: the decoder's says why
        cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_ERROR)
        try:
            with _decoder_messages() as said:
                img = cv2.imread(str(self.path), cv2.IMREAD_COLOR | cv2.IMREAD_IGNORE_ORIENTATION)
        finally:
            cv2.utils.logging.setLogLevel(level)
        if img is None:
            why = f" ({said[-1]})" if said else ""
            raise ImageDefect(UNREADABLE_IMAGE, f"{self.path}: cannot decode the image (missing, corrupt or "
                                                f"unsupported){why}")
        for line in said:   # a warning on an image that decoded (e.g. extraneous bytes): one line naming the file
            print(f"{self.path}: {line}", file=sys.stderr)
        rgb = cv2.cvtColor(img, cv2.COLOR_BGR2RGB)
        if self.lens is None:
            return rgb
        if rgb.shape[:2] != (self.lens.height, self.lens.width):   # the maps are the lens's size, whatever the input
            raise ImageDefect(WRONG_SIZE, f"{self.path}: image is {rgb.shape[1]}x{rgb.shape[0]} but its camera is "
                                          f"{self.lens.width}x{self.lens.height}")
        mx, my = undistortion_maps(self.lens)
        return cv2.remap(rgb, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)


def image_source(path: Path, lens: Distortion | None = None) -> ImageSource:
    """The ``ImageSource`` of ``path`` (a ``FileImage``): decoded when called, undistorted when ``lens`` is given."""
    return FileImage(path, lens)
