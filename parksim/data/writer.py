"""Writes a dataset directory in the layout of ``parksim.data.layout``.

``fileio.atomic_directory`` around it makes it all-or-nothing.
"""

from __future__ import annotations

import json
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from ..rig import Rig
from .layout import DEPTH_SCALE, DatasetError, DatasetLayout

__all__ = ["DatasetWriter", "to_uint8"]


def to_uint8(image: Any) -> np.ndarray:
    """Float image in [0, 1] (numpy or torch, HxWx3) -> uint8, rounded; a uint8 image is returned as it is.

    Args:
        image: ``[H, W, 3]`` (any shape) float array or tensor in [0, 1], or uint8.

    Returns:
        The uint8 array, values clipped to [0, 255].
    """
    arr = image.detach().cpu().numpy() if hasattr(image, "detach") else np.asarray(image)
    if arr.dtype == np.uint8:
        return arr
    return np.clip(np.rint(arr * 255.0), 0, 255).astype(np.uint8)


def _write_json(path: Path, data: Any) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(data, indent=1))


def _imwrite(path: Path, image: np.ndarray) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    if not cv2.imwrite(str(path), image):
        raise DatasetError(path, "could not write image")


class DatasetWriter:
    """One method per dataset item; paths come from ``DatasetLayout``."""

    def __init__(self, root: str | Path) -> None:
        """Create ``root`` (and its parents) if needed.

        Args:
            root: the dataset directory.
        """
        self.layout = DatasetLayout(root)
        self.layout.root.mkdir(parents=True, exist_ok=True)

    def rig(self, rig: Rig) -> None:
        """Write ``rig.json``.

        Args:
            rig: the cameras and BEV spec.
        """
        rig.save(self.layout.rig)

    def poses(self, poses: np.ndarray | None, timestamps: Sequence[float] | np.ndarray,
              frames: Sequence[int] | None = None,
              camera_poses: Sequence[Mapping[str, np.ndarray]] | None = None) -> None:
        """Write ``poses.json``: ego poses and/or per-image camera poses, with their timestamps.

        Args:
            poses: ``[N, 4, 4]`` ``T_world_vehicle`` per frame, or None.
            timestamps: ``[N]`` seconds.
            frames: ``N`` frame ids (default ``0..N-1``).
            camera_poses: ``N`` mappings ``{camera: [4, 4] T_world_camera}``, or None.

        Raises:
            ValueError: neither ``poses`` nor ``camera_poses``, or lengths that differ.
        """
        if poses is None and camera_poses is None:
            raise ValueError("a dataset needs ego poses, per-image camera poses, or both")
        n = len(timestamps)
        frames = list(range(n)) if frames is None else list(frames)
        sizes = {"timestamps": n, "frame ids": len(frames)}
        if poses is not None:
            sizes["poses"] = len(poses)
        if camera_poses is not None:
            sizes["camera poses"] = len(camera_poses)
        if len(set(sizes.values())) != 1:
            raise ValueError(", ".join(f"{v} {k}" for k, v in sizes.items()) + ": expected one per frame")
        entries = []
        for i, (f, t) in enumerate(zip(frames, timestamps)):
            entry: dict[str, Any] = {"frame": int(f), "timestamp": float(t)}
            if poses is not None:
                entry["T_world_vehicle"] = np.asarray(poses[i], np.float64).tolist()
            if camera_poses is not None:
                entry["T_world_camera"] = {c: np.asarray(T, np.float64).tolist() for c, T in camera_poses[i].items()}
            entries.append(entry)
        _write_json(self.layout.poses, {"frames": entries})

    def image(self, camera: str, frame: int, image: Any) -> None:
        """RGB HxWx3, float in [0, 1] or uint8 -> uint8 PNG.

        Args:
            camera: the camera's name in the rig.
            frame: the frame id.
            image: ``[H, W, 3]`` RGB, float in [0, 1] or uint8 (numpy or torch).

        Raises:
            DatasetError: OpenCV could not write the file.
        """
        _imwrite(self.layout.image(camera, frame), cv2.cvtColor(to_uint8(image), cv2.COLOR_RGB2BGR))

    def ipm(self, frame: int, image: Any) -> None:
        """Ground-truth BEV as a uint8 PNG.

        Args:
            frame: the frame id.
            image: ``[Hb, Wb, 3]`` RGB, float in [0, 1] or uint8.

        Raises:
            DatasetError: OpenCV could not write the file.
        """
        _imwrite(self.layout.ipm(frame), cv2.cvtColor(to_uint8(image), cv2.COLOR_RGB2BGR))

    def depth(self, camera: str, frame: int, depth_m: np.ndarray) -> None:
        """Distance along the ray (m; 0 = none) -> uint16 PNG in millimetres, clipped at 65.535 m.

        Args:
            camera: the camera's name in the rig.
            frame: the frame id.
            depth_m: ``[H, W]`` distances in metres.

        Raises:
            DatasetError: OpenCV could not write the file.
        """
        mm = np.clip(np.rint(np.asarray(depth_m) * DEPTH_SCALE), 0, 65535).astype(np.uint16)
        _imwrite(self.layout.depth(camera, frame), mm)

    def labels(self, frame: int, labels: Mapping[str, Any]) -> None:
        """One frame's slot labels as JSON, with its ``frame`` id added.

        Args:
            frame: the frame id.
            labels: DMPR-PS labels in BEV pixels (``marks``, ``slots``).
        """
        _write_json(self.layout.labels(frame), {"frame": int(frame), **labels})

    def map(self, scene_map: Mapping[str, Any]) -> None:
        """Write ``map.json``.

        Args:
            scene_map: world-frame slots, marking points and obstacles (JSON values).
        """
        _write_json(self.layout.map, scene_map)

    def split(self, train: Sequence[int], test: Sequence[int]) -> None:
        """Write ``split.json``.

        Args:
            train: frame ids to train on.
            test: frame ids held out for evaluation.
        """
        _write_json(self.layout.split, {"train": [int(f) for f in train], "test": [int(f) for f in test]})

    def meta(self, meta: Mapping[str, Any]) -> None:
        """Write ``meta.json``.

        Args:
            meta: generator, preset, seed, layout version, resolution (JSON values).
        """
        _write_json(self.layout.meta, meta)

    def points(self, xyz: np.ndarray, rgb: np.ndarray, normals: np.ndarray) -> None:
        """Sparse point cloud as binary PLY: x, y, z, nx, ny, nz (float32), red, green, blue (uint8).

        Args:
            xyz: ``[P, 3]`` world positions (m).
            rgb: ``[P, 3]`` uint8 colours.
            normals: ``[P, 3]`` normals.
        """
        from plyfile import PlyData, PlyElement

        names = ("x", "y", "z", "nx", "ny", "nz")
        dtype = [(n, "f4") for n in names] + [(c, "u1") for c in ("red", "green", "blue")]
        data = np.empty(len(xyz), dtype=dtype)
        for i, n in enumerate(names):
            data[n] = (xyz if i < 3 else normals)[:, i % 3]
        for i, c in enumerate(("red", "green", "blue")):
            data[c] = rgb[:, i]
        PlyData([PlyElement.describe(data, "vertex")]).write(str(self.layout.points))
