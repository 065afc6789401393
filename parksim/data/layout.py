"""The dataset directory layout: every path and file name, defined once for writer and reader.

```
rig.json                      Rig.save: cameras (intrinsics, T_vehicle_camera) and the BEV spec
poses.json                    {"frames": [{"frame", "timestamp", "T_world_vehicle" (4x4) and/or
                                            "T_world_camera" ({camera: 4x4}, a pose per image)}]}
images/<camera>/<frame>.png   uint8 RGB fisheye images
ipm/<frame>.png               uint8 RGB ground-truth BEV (IPM of the ground-truth images), optional
labels/<frame>.json           DMPR-PS slot labels in BEV pixels, optional
depth/<camera>/<frame>.png    uint16 distance along the ray in mm (0 = none), optional
map.json                      world-frame slots, marking points and obstacles, optional
points3d.ply                  sparse initial point cloud (x, y, z, normals, RGB), optional
split.json                    {"train": [frames], "test": [frames]}, optional
meta.json                     generator, preset, seed, version, resolution, optional
```
Frames are named by their integer id, zero-padded to six digits.
"""

from __future__ import annotations

from pathlib import Path

__all__ = ["DatasetLayout", "DatasetError", "frame_name", "DEPTH_SCALE", "LAYOUT_VERSION"]

LAYOUT_VERSION = 1
"""Bumped when the layout changes incompatibly; written to meta.json."""
DEPTH_SCALE = 1000.0
"""Depth PNG units per metre (millimetres)."""


class DatasetError(ValueError):
    """A dataset file is missing, unreadable or inconsistent; ``path`` names the file."""

    def __init__(self, path: str | Path, message: str) -> None:
        """The error, its message ``"{path}: {message}"``.

        Args:
            path: the offending file or directory (kept as ``self.path``).
            message: what is wrong with it.
        """
        self.path = Path(path)
        super().__init__(f"{path}: {message}")


def frame_name(frame: int) -> str:
    """File stem of a frame id: ``7 -> "000007"``.

    Args:
        frame: the frame id, >= 0.

    Returns:
        The id zero-padded to six digits (more digits past 999999).

    Raises:
        ValueError: a negative id.

    Example:
        >>> frame_name(7)
        '000007'
    """
    if frame < 0:
        raise ValueError(f"frame ids are non-negative, got {frame}")
    return f"{frame:06d}"


class DatasetLayout:
    """Paths inside one dataset directory (nothing is read or created).

    Example:
        >>> DatasetLayout("/data/run").image("front", 7).as_posix()
        '/data/run/images/front/000007.png'
    """

    def __init__(self, root: str | Path) -> None:
        """Paths under ``root``.

        Args:
            root: the dataset directory.
        """
        self.root = Path(root)

    @property
    def rig(self) -> Path:
        """``rig.json``: the cameras and the BEV spec."""
        return self.root / "rig.json"

    @property
    def poses(self) -> Path:
        """``poses.json``: per-frame timestamps, ego poses and/or per-image camera poses."""
        return self.root / "poses.json"

    @property
    def split(self) -> Path:
        """``split.json``: train and test frame ids."""
        return self.root / "split.json"

    @property
    def meta(self) -> Path:
        """``meta.json``: generator, preset, seed, layout version, resolution."""
        return self.root / "meta.json"

    @property
    def map(self) -> Path:
        """``map.json``: world-frame slots, marking points and obstacles."""
        return self.root / "map.json"

    @property
    def points(self) -> Path:
        """``points3d.ply``: the sparse initial point cloud."""
        return self.root / "points3d.ply"

    def image_dir(self, camera: str) -> Path:
        """The folder of one camera's images.

        Args:
            camera: the camera's name in the rig.

        Returns:
            ``images/<camera>``.
        """
        return self.root / "images" / camera

    def image(self, camera: str, frame: int) -> Path:
        """One camera image.

        Args:
            camera: the camera's name in the rig.
            frame: the frame id.

        Returns:
            ``images/<camera>/<frame>.png``.
        """
        return self.image_dir(camera) / f"{frame_name(frame)}.png"

    @property
    def ipm_dir(self) -> Path:
        """``ipm/``: the ground-truth BEV images."""
        return self.root / "ipm"

    def ipm(self, frame: int) -> Path:
        """One ground-truth BEV image.

        Args:
            frame: the frame id.

        Returns:
            ``ipm/<frame>.png``.
        """
        return self.ipm_dir / f"{frame_name(frame)}.png"

    @property
    def labels_dir(self) -> Path:
        """``labels/``: the DMPR-PS slot labels."""
        return self.root / "labels"

    def labels(self, frame: int) -> Path:
        """One frame's slot labels.

        Args:
            frame: the frame id.

        Returns:
            ``labels/<frame>.json``.
        """
        return self.labels_dir / f"{frame_name(frame)}.json"

    def depth_dir(self, camera: str) -> Path:
        """The folder of one camera's depth maps.

        Args:
            camera: the camera's name in the rig.

        Returns:
            ``depth/<camera>``.
        """
        return self.root / "depth" / camera

    def depth(self, camera: str, frame: int) -> Path:
        """One depth map (uint16 millimetres along the ray).

        Args:
            camera: the camera's name in the rig.
            frame: the frame id.

        Returns:
            ``depth/<camera>/<frame>.png``.
        """
        return self.depth_dir(camera) / f"{frame_name(frame)}.png"
