"""A dataset written as a rig log, the input ``parksim import rig-log`` reads: OpenCV YAML calibrations and an
extrinsics file, ego poses as CSV at the frame times, and per camera either a folder of PNGs named by their time
in nanoseconds or one mp4v video. The import suite measures what such a log costs (and the import tests read it
back); the writers keep every bit of the poses and intrinsics (``repr``), so an import can be checked to the bit.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:
    import torch

    from ..camera import OpenCVFisheye
    from ..rig import Rig

__all__ = ["write_rig_log", "opencv_yaml", "extrinsics_file", "poses_csv", "image_folders", "videos", "stamp_name",
           "FOURCC", "QUATERNION_FORM"]

FOURCC = "mp4v"
"""The codec OpenCV's FFmpeg writer encodes into .mp4 in builds without an H.264/HEVC encoder;
VIDEOWRITER_PROP_QUALITY cannot be set for it, so frames are at the backend's default quality (~35 dB PSNR
against the PNGs on the tiny garage)."""
QUATERNION_FORM = ("rear", "right")
"""Cameras whose extrinsics are written as x, y, z + quaternion (the others as a 4x4 T_vehicle_camera)."""


def stamp_name(t: float) -> str:
    """An image file name holding ``t`` (s) as 19-digit integer nanoseconds (read back by the digit-count rule)."""
    return f"{round(t * 1e9):019d}.png"


def opencv_yaml(model: OpenCVFisheye, path: Path) -> None:
    """Write an OpenCV fisheye calibration (camera_matrix, dist_coeffs, resolution) as cv2.FileStorage does.

    Args:
        model: an ``OpenCVFisheye`` (``K`` [3, 3], ``k`` [4], width, height).
        path: the ``.yaml`` file to write.
    """
    import cv2

    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
    fs.write("camera_matrix", model.K.numpy())
    fs.write("dist_coeffs", model.k.numpy().reshape(4, 1))
    fs.write("resolution", np.array([[model.width], [model.height]], np.int32))
    fs.release()


def _quaternion(R: torch.Tensor) -> list[float]:
    """(w, x, y, z) of the rotation ``R`` [3, 3]."""
    from ..geometry import quaternion_from_rotation

    return [float(v) for v in quaternion_from_rotation(R)]


def extrinsics_file(rig: Rig, path: Path) -> None:
    """Write every camera's T_vehicle_camera (4x4, or x, y, z + quaternion for ``QUATERNION_FORM``) and the BEV
    spec as JSON.

    Args:
        rig: the rig.
        path: the ``.json`` file to write.
    """
    cameras: dict[str, dict[str, Any]] = {}
    for name, cam in rig.cameras.items():
        T = cam.T_vehicle_camera
        if name in QUATERNION_FORM:
            qw, qx, qy, qz = _quaternion(T[:3, :3])
            cameras[name] = dict(zip(("x", "y", "z"), T[:3, 3].tolist()), qw=qw, qx=qx, qy=qy, qz=qz)
        else:
            cameras[name] = {"T_vehicle_camera": T.tolist()}
    path.write_text(json.dumps({"cameras": cameras, "bev": rig.bev.to_dict()}))


def poses_csv(path: Path, times: np.ndarray, poses: np.ndarray, spoil: dict[int, dict[str, float]] | None = None
              ) -> None:
    """Write ``timestamp, x, y, z, qw, qx, qy, qz`` rows (``repr``: every bit kept).

    Args:
        path: the ``.csv`` file to write.
        times: [N] seconds.
        poses: [N, 4, 4] T_world_vehicle.
        spoil: values that replace some rows' (row index -> column -> value), to make bad logs.
    """
    import torch

    lines = ["timestamp,x,y,z,qw,qx,qy,qz"]
    for i, (t, T) in enumerate(zip(times, poses)):
        row = dict(zip(("timestamp", "x", "y", "z"), [float(t), *T[:3, 3].tolist()]),
                   **dict(zip(("qw", "qx", "qy", "qz"), _quaternion(torch.from_numpy(T[:3, :3])))))
        row.update((spoil or {}).get(i, {}))
        lines.append(",".join(repr(float(v)) for v in row.values()))
    path.write_text("\n".join(lines) + "\n")


def image_folders(data: Path, root: Path, offsets: dict[str, float] | None = None) -> None:
    """Copy every camera's PNGs to ``root/<camera>/<time in ns>.png``.

    Args:
        data: the dataset.
        root: the folder to write (one sub-folder per camera).
        offsets: seconds added to a camera's times (unsynchronised cameras).
    """
    from ..data import DatasetReader

    reader = DatasetReader(data)
    for c in reader.rig.names:
        (root / c).mkdir(parents=True)
        for f, t in zip(reader.frames, reader.timestamps):
            (root / c / stamp_name(t + (offsets or {}).get(c, 0.0))).write_bytes(reader.layout.image(c, f).read_bytes())


def videos(data: Path, root: Path, fps: float) -> dict[str, Path]:
    """Write one ``FOURCC`` .mp4 per camera of the dataset's frames at ``fps``.

    Args:
        data: the dataset.
        root: the folder to write them in.
        fps: their frame rate.

    Returns:
        camera -> its video.
    """
    import cv2

    from ..data import DatasetReader

    reader = DatasetReader(data)
    root.mkdir(parents=True, exist_ok=True)
    paths = {}
    for c in reader.rig.names:
        m = reader.rig.cameras[c].model
        paths[c] = root / f"{c}.mp4"
        writer = cv2.VideoWriter(str(paths[c]), cv2.VideoWriter.fourcc(*FOURCC), fps, (m.width, m.height))
        if not writer.isOpened():
            raise RuntimeError(f"this OpenCV build cannot write {FOURCC} videos ({paths[c]})")
        for f in reader.frames:
            image = cv2.imread(str(reader.layout.image(c, f)), cv2.IMREAD_COLOR)
            if image is None:
                raise RuntimeError(f"{reader.layout.image(c, f)}: not a readable image")
            writer.write(image)
        writer.release()
    return paths


def write_rig_log(data: Path, out: Path, video: bool) -> dict[str, Any]:
    """Write the dataset as a rig log: OpenCV YAML + extrinsics, poses.csv at the frame times, and PNG folders or
    mp4v videos at the dataset's rate.

    Args:
        data: a dataset with ego poses (a ``parksim synth`` one).
        out: the folder to write (``calib/``, ``poses.csv``, ``images/`` or ``video/``).
        video: videos instead of image folders.

    Returns:
        The ``parksim import rig-log`` options that read it, as keyword arguments of the importer's ``Options``
        (``calib``, ``poses``, and ``images`` or ``video``).
    """
    from ..camera import OpenCVFisheye
    from ..data import DatasetReader

    reader = DatasetReader(data)
    (out / "calib").mkdir(parents=True)
    for c, cam in reader.rig.cameras.items():
        if not isinstance(cam.model, OpenCVFisheye):
            raise TypeError(f"{data}: camera {c} is a {type(cam.model).__name__}; rig logs are written with OpenCV "
                            "fisheye calibrations")
        opencv_yaml(cam.model, out / "calib" / f"{c}.yaml")
    extrinsics_file(reader.rig, out / "calib" / "extrinsics.json")
    poses_csv(out / "poses.csv", np.array(reader.timestamps), reader.poses.numpy())
    options: dict[str, Any] = {"calib": out / "calib", "poses": out / "poses.csv"}
    if video:
        rate = 1.0 / float(np.median(np.diff(reader.timestamps)))
        return {**options, "video": videos(data, out / "video", rate)}
    image_folders(data, out / "images")
    return {**options, "images": (str(out / "images"),)}
