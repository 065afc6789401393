"""Reads a dataset directory lazily (images on demand) and checks it, naming the offending file."""

from __future__ import annotations

import json
import os
import sys
from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor
from functools import cached_property
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import torch
from torch import Tensor
from tqdm import tqdm

from ..geometry import invert_transform
from ..rig import CalibrationError, Rig
from .layout import DEPTH_SCALE, DatasetError, DatasetLayout

__all__ = ["DatasetReader"]

_DECODE_WORKERS = 8
"""Most threads decoding images at once (PNG decoding scales to a few cores; more only adds memory)."""


def _read_json(path: Path) -> Any:
    """The parsed JSON file; DatasetError if it is missing or not JSON."""
    if not path.is_file():
        raise DatasetError(path, "file not found")
    try:
        return json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise DatasetError(path, f"not valid JSON: {e}") from None


def _imread(path: Path, flags: int) -> np.ndarray:
    """``cv2.imread`` (BGR); DatasetError if the file is missing or does not decode."""
    if not path.is_file():
        raise DatasetError(path, "file not found")
    img = cv2.imread(str(path), flags)
    if img is None:
        raise DatasetError(path, "cannot decode PNG (corrupt or truncated file)")
    return img


class DatasetReader:
    """A dataset directory: ``rig``, ``poses``, ``frames``, ``split`` and per-frame items on demand.

    Opening checks the rig, the poses and that every frame has an image for every camera
    (existence only, cheap); ``validate(deep=True)`` also decodes every file.
    """

    def __init__(self, root: str | Path, validate: bool = True) -> None:
        """Open a dataset directory.

        Args:
            root: the dataset directory.
            validate: run the cheap ``validate()`` now (False defers every check to first use).

        Raises:
            DatasetError: ``root`` is not a directory, or (with ``validate``) the layout is broken.
        """
        self.layout = DatasetLayout(root)
        if not self.layout.root.is_dir():
            raise DatasetError(self.layout.root, "dataset directory not found")
        if validate:
            self.validate()

    # --- scene-level items -------------------------------------------------------------
    @cached_property
    def rig(self) -> Rig:
        """The cameras and the BEV spec (``rig.json``), read once; DatasetError if it is missing or invalid."""
        try:
            return Rig.load(self.layout.rig)
        except CalibrationError as e:   # its message may already start with the file's name: say it once
            raise DatasetError(self.layout.rig, str(e).removeprefix(f"{self.layout.rig}: ")) from None

    @cached_property
    def _pose_table(self) -> tuple[list[int], Tensor | None, list[float], dict[str, Tensor] | None]:
        """Frame ids, ego poses ``[N, 4, 4]`` (or None), timestamps and per-image poses ``{camera: [N, 4, 4]}``."""
        path = self.layout.poses
        data = _read_json(path)
        expected = "{'frames': [{frame, timestamp, T_world_vehicle 4x4 and/or T_world_camera {camera: 4x4}}]}"
        try:
            entries = data["frames"]
            frames = [int(e["frame"]) for e in entries]
            stamps = [float(e["timestamp"]) for e in entries]
            ego = self._pose_column(path, [e.get("T_world_vehicle") for e in entries], "T_world_vehicle")
            per_image = [e.get("T_world_camera") for e in entries]
            cams = None
            if any(p is not None for p in per_image):
                if not all(isinstance(p, dict) for p in per_image):
                    raise DatasetError(path, "T_world_camera must be given for every frame or for none")
                names = sorted(per_image[0])
                if any(sorted(p) != names for p in per_image):
                    raise DatasetError(path, "every frame's T_world_camera must name the same cameras")
                cams = {}
                for c in names:
                    column = self._pose_column(path, [p[c] for p in per_image], f"T_world_camera[{c!r}]")
                    if column is None:
                        raise DatasetError(path, f"T_world_camera[{c!r}] is null in every frame")
                    cams[c] = column
        except DatasetError:
            raise
        except (KeyError, TypeError, ValueError, RuntimeError) as e:
            raise DatasetError(path, f"expected {expected}: {e}") from None
        if ego is None and cams is None:
            raise DatasetError(path, "frames need T_world_vehicle, T_world_camera, or both")
        if len(set(frames)) != len(frames):
            raise DatasetError(path, "duplicate frame ids")
        return frames, ego, stamps, cams

    @staticmethod
    def _pose_column(path: Path, values: list[Any], key: str) -> Tensor | None:
        """``[N, 4, 4]`` float64 from one pose key of every frame: all present (finite) or all absent (None)."""
        if all(v is None for v in values):
            return None
        if any(v is None for v in values):
            raise DatasetError(path, f"{key} must be given for every frame or for none")
        poses = torch.tensor(values, dtype=torch.float64).reshape(-1, 4, 4)
        if not torch.isfinite(poses).all():
            raise DatasetError(path, f"non-finite {key} values")
        return poses

    @property
    def frames(self) -> list[int]:
        """Frame ids in pose order."""
        return self._pose_table[0]

    @property
    def has_vehicle_poses(self) -> bool:
        """Whether frames carry ego poses (T_world_vehicle); without them the scene renders at camera poses only."""
        return self._pose_table[1] is not None

    @property
    def has_camera_poses(self) -> bool:
        """Whether every image carries its own pose (T_world_camera), as COLMAP and nerfstudio give."""
        return self._pose_table[3] is not None

    @property
    def poses(self) -> Tensor:
        """T_world_vehicle per frame, ``[N, 4, 4]`` float64; DatasetError when the dataset has per-image poses only."""
        poses = self._pose_table[1]
        if poses is None:
            raise DatasetError(self.layout.poses, "this dataset has per-image camera poses only, no ego poses "
                                                  "(T_world_vehicle): it renders at camera poses, not at ego poses")
        return poses

    @property
    def timestamps(self) -> list[float]:
        """Timestamp of each frame in seconds, in pose order."""
        return self._pose_table[2]

    def pose(self, frame: int) -> Tensor:
        """T_world_vehicle of one frame (see ``poses``).

        Args:
            frame: the frame id.

        Returns:
            ``[4, 4]`` float64 ego pose.

        Raises:
            DatasetError: no pose for ``frame``, or the dataset has per-image poses only.
        """
        return self.poses[self._index(frame)]

    def camera_pose(self, camera: str, frame: int) -> Tensor:
        """T_world_camera of one image: its own pose when the dataset has per-image poses, else ego pose x rig.

        Args:
            camera: the camera's name in the rig.
            frame: the frame id.

        Returns:
            ``[4, 4]`` float64 camera pose (OpenCV camera axes).

        Raises:
            DatasetError: no pose for ``frame`` or none for ``camera``.
        """
        cams = self._pose_table[3]
        if cams is not None:
            if camera not in cams:
                raise DatasetError(self.layout.poses, f"no per-image pose for camera {camera!r}")
            return cams[camera][self._index(frame)]
        return self.pose(frame) @ self.rig.cameras[camera].T_vehicle_camera

    def view_pose(self, camera: str, frame: int) -> Tensor:
        """The T_world_vehicle at which ``render(..., cameras=[camera])`` puts the camera at ``camera_pose``.

        Equal to ``pose(frame)`` for rig datasets; per-image poses are carried through the camera's extrinsics.

        Args:
            camera: the camera's name in the rig.
            frame: the frame id.

        Returns:
            ``[4, 4]`` float64 ``T_world_vehicle``.
        """
        if self._pose_table[3] is None:
            return self.pose(frame)
        return self.camera_pose(camera, frame) @ invert_transform(self.rig.cameras[camera].T_vehicle_camera)

    def camera_centres(self) -> Tensor:
        """World positions of every image's camera centre (frame-major).

        Returns:
            ``[N * C, 3]`` float64 metres for N frames and C cameras.
        """
        return torch.stack([self.camera_pose(c, f)[:3, 3] for f in self.frames for c in self.rig.names])

    @cached_property
    def split(self) -> dict[str, list[int]]:
        """``{"train": [...], "test": [...]}``; all frames are train when there is no split file."""
        if not self.layout.split.is_file():
            return {"train": list(self.frames), "test": []}
        data = _read_json(self.layout.split)
        known = set(self.frames)
        for key in ("train", "test"):
            unknown = sorted(set(data.get(key, [])) - known)
            if unknown:
                raise DatasetError(self.layout.split, f"{key} lists frames without a pose: {unknown[:5]}")
        return {"train": list(data.get("train", [])), "test": list(data.get("test", []))}

    @cached_property
    def meta(self) -> dict[str, Any]:
        """``meta.json`` (generator, preset, seed, ...), or ``{}`` when there is none."""
        return _read_json(self.layout.meta) if self.layout.meta.is_file() else {}

    @cached_property
    def map(self) -> dict[str, Any]:
        """World-frame slots and obstacles (map.json)."""
        return _read_json(self.layout.map)

    @cached_property
    def points(self) -> tuple[np.ndarray, np.ndarray]:
        """Sparse point cloud: positions ``[N, 3]`` float32 and colours ``[N, 3]`` uint8."""
        from plyfile import PlyData

        path = self.layout.points
        if not path.is_file():
            raise DatasetError(path, "file not found")
        try:
            v = PlyData.read(str(path))["vertex"]
            xyz = np.stack([v["x"], v["y"], v["z"]], 1).astype(np.float32)
            rgb = np.stack([v["red"], v["green"], v["blue"]], 1).astype(np.uint8)
        except (KeyError, ValueError, IndexError, EOFError) as e:
            raise DatasetError(path, f"not a point-cloud PLY with x, y, z, red, green, blue: {e}") from None
        return xyz, rgb

    @property
    def has_ipm(self) -> bool:
        """Whether the dataset has ground-truth BEV images (``ipm/``)."""
        return self.layout.ipm_dir.is_dir()

    @property
    def has_labels(self) -> bool:
        """Whether the dataset has slot labels (``labels/``)."""
        return self.layout.labels_dir.is_dir()

    # --- per-frame items ---------------------------------------------------------------
    def _index(self, frame: int) -> int:
        """Position of ``frame`` in ``frames``; DatasetError if it has no pose."""
        try:
            return self.frames.index(frame)
        except ValueError:
            raise DatasetError(self.layout.poses, f"no pose for frame {frame}") from None

    def image(self, camera: str, frame: int) -> Tensor:
        """Fisheye image as float32 RGB in [0, 1], HxWx3.

        Args:
            camera: the camera's name in the rig.
            frame: the frame id.

        Returns:
            ``[H, W, 3]`` float32 at the rig's size for that camera.

        Raises:
            DatasetError: an unknown camera or frame, a missing or undecodable PNG, or one of the wrong size.
        """
        if camera not in self.rig.cameras:
            raise DatasetError(self.layout.rig, f"no camera {camera!r}; the rig has {self.rig.names}")
        self._index(frame)
        path = self.layout.image(camera, frame)
        img = _imread(path, cv2.IMREAD_COLOR)
        m = self.rig.cameras[camera].model
        if img.shape[:2] != (m.height, m.width):
            raise DatasetError(path, f"image is {img.shape[1]}x{img.shape[0]} but the rig says {m.width}x{m.height}")
        return torch.from_numpy(cv2.cvtColor(img, cv2.COLOR_BGR2RGB)).float() / 255.0

    def images(self, views: Sequence[tuple[int, str]], progress: bool = True) -> dict[tuple[int, str], Tensor]:
        """``image(camera, frame)`` of every ``(frame, camera)`` view, decoded on a thread pool (cv2 releases the GIL).

        Reading all images up front finds a corrupt one before a long run rather than when it is first sampled;
        the first bad file in ``views`` order raises its DatasetError. ``progress`` shows a bar on stderr.

        Args:
            views: ``(frame, camera)`` pairs.
            progress: show a progress bar on stderr.

        Returns:
            ``{(frame, camera): [H, W, 3] float32}`` in ``views`` order.
        """
        _ = self.rig, self.frames   # built once here, not raced for by the workers
        pool = ThreadPoolExecutor(min(_DECODE_WORKERS, os.cpu_count() or 1))
        try:
            futures = [pool.submit(self.image, camera, frame) for frame, camera in views]
            decoded = {}
            with tqdm(total=len(futures), desc="decode images", unit="img", disable=not progress, file=sys.stderr,
                      dynamic_ncols=True) as bar:
                for view, future in zip(views, futures):
                    decoded[view] = future.result()
                    bar.update()
            return decoded
        finally:
            pool.shutdown(cancel_futures=True)

    def ipm(self, frame: int) -> Tensor:
        """Ground-truth BEV image as float32 RGB in [0, 1], HxWx3.

        Args:
            frame: the frame id.

        Returns:
            ``[Hb, Wb, 3]`` float32 at the BEV spec's size.

        Raises:
            DatasetError: an unknown frame, a missing or undecodable PNG, or one of the wrong size.
        """
        self._index(frame)
        path = self.layout.ipm(frame)
        img = _imread(path, cv2.IMREAD_COLOR)
        bev = self.rig.bev
        if img.shape[:2] != (bev.height, bev.width):
            raise DatasetError(path, f"BEV image is {img.shape[1]}x{img.shape[0]} "
                                     f"but the BEV spec is {bev.width}x{bev.height}")
        return torch.from_numpy(cv2.cvtColor(img, cv2.COLOR_BGR2RGB)).float() / 255.0

    def depth(self, camera: str, frame: int) -> Tensor:
        """Distance along each pixel's ray in metres (0 = no depth), float32 HxW.

        Args:
            camera: the camera's name in the rig.
            frame: the frame id.

        Returns:
            ``[H, W]`` float32 metres.

        Raises:
            DatasetError: an unknown frame, a missing or undecodable PNG, or not a single-channel 16-bit one.
        """
        self._index(frame)
        path = self.layout.depth(camera, frame)
        d = _imread(path, cv2.IMREAD_UNCHANGED)
        if d.dtype != np.uint16 or d.ndim != 2:
            raise DatasetError(path, f"depth must be a single-channel 16-bit PNG, got {d.dtype} with shape {d.shape}")
        return torch.from_numpy(d.astype(np.float32) / DEPTH_SCALE)

    def labels(self, frame: int) -> dict[str, Any]:
        """Slot labels (DMPR-PS form, BEV pixels); checked to lie inside the BEV and to reference real points.

        Args:
            frame: the frame id.

        Returns:
            The label file's content: ``marks`` (``x``, ``y`` in BEV pixels, ``shape`` "T" or "L", ...) and
            ``slots`` (``p1``, ``p2`` indices into ``marks``, ...).

        Raises:
            DatasetError: an unknown frame, a missing or malformed file, a point outside the BEV, an unknown shape,
                or a slot naming a point that does not exist.
        """
        self._index(frame)
        path = self.layout.labels(frame)
        data = _read_json(path)
        bev = self.rig.bev
        try:
            marks, slots = data["marks"], data["slots"]
            for i, m in enumerate(marks):
                x, y = float(m["x"]), float(m["y"])
                if not (-0.5 <= x <= bev.width - 0.5 and -0.5 <= y <= bev.height - 0.5):
                    raise DatasetError(path, f"marking point {i} at ({x:.1f}, {y:.1f}) lies outside the "
                                             f"{bev.width}x{bev.height} BEV")
                if m["shape"] not in ("T", "L"):
                    raise DatasetError(path, f"marking point {i} has shape {m['shape']!r}; expected 'T' or 'L'")
            for j, s in enumerate(slots):
                for key in ("p1", "p2"):
                    if not 0 <= int(s[key]) < len(marks):
                        raise DatasetError(path, f"slot {j} {key}={s[key]} is not one of the "
                                                 f"{len(marks)} marking points")
        except DatasetError:
            raise
        except (KeyError, TypeError, ValueError) as e:
            raise DatasetError(path, f"malformed labels: {e!r}") from None
        return data

    # --- checks --------------------------------------------------------------------------
    def validate(self, deep: bool = False) -> None:
        """Check the layout: rig, poses, one image per camera and frame, no strays; ``deep`` decodes all files.

        Args:
            deep: also decode every image, BEV image and label file (reads the whole dataset).

        Raises:
            DatasetError: the first problem found, naming its file.
        """
        rig, frames = self.rig, self.frames
        cams = self._pose_table[3]
        if cams is not None and sorted(cams) != sorted(rig.names):
            raise DatasetError(self.layout.poses, f"T_world_camera names cameras {sorted(cams)} "
                                                  f"but the rig has {sorted(rig.names)}")
        for camera in rig.names:
            folder = self.layout.image_dir(camera)
            if not folder.is_dir():
                raise DatasetError(folder, f"image folder for camera {camera!r} not found")
            for f in frames:
                if not self.layout.image(camera, f).is_file():
                    raise DatasetError(self.layout.image(camera, f), f"missing image for frame {f}")
            count = sum(1 for _ in folder.glob("*.png"))
            if count != len(frames):
                raise DatasetError(self.layout.poses, f"{len(frames)} poses but {count} images in {folder}")
        if self.layout.split.is_file():
            _ = self.split
        if deep:
            for f in frames:
                for camera in rig.names:
                    self.image(camera, f)
                if self.has_ipm:
                    self.ipm(f)
                if self.has_labels:
                    self.labels(f)
