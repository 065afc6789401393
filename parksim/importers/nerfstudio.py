"""nerfstudio ``transforms.json``: ``parksim import nerfstudio`` reads one, ``parksim export nerfstudio`` writes one.

Every nerfstudio convention lives here (nerfstudio's ``nerfstudio_dataparser.py`` and ``ns-process-data``):

- ``transform_matrix`` is camera-to-world with OpenGL camera axes (x right, y up, z back); ParkSim's camera frame is
  OpenCV's (x right, y down, z forward), so ``T_world_camera = transform_matrix @ diag(1, -1, -1, 1)``.
- The world is the file's, as stored: ``applied_transform`` (what ``ns-process-data`` applied to its source's
  world, e.g. COLMAP's) is already in every ``transform_matrix`` and in the ``ply_file_path`` points; it is
  reported, not undone.
- Pixels: nerfstudio puts the first pixel's centre at (0.5, 0.5), ParkSim at (0, 0): ``cx_parksim = cx - 0.5``.
- Intrinsics ``fl_x, fl_y, cx, cy, w, h``: a top-level key holds for every frame, else each frame gives it;
  distortion ``k1..k4, p1, p2`` all come from the top level when any of them is there, else from each frame
  (absent = 0). ``camera_model`` is top-level (absent: a perspective camera, as nerfstudio).
- Images are grouped into cameras by parent folder when they lie in several folders, else by distinct intrinsics
  (``cam0``, ``cam1``... in order of appearance); into frames by the last integer in the file stem.

Other ``transforms.json`` dialects reuse the reading in three steps: ``load_json`` (the file), ``read_frames``
(every frame's image, lens and pose, once the dialect's keys are rewritten as nerfstudio's) and
``recording_from_transforms`` (cameras, frames, split, points and notes); ``instant_ngp`` does so.
"""

from __future__ import annotations

import json
import math
import os
import shutil
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from .base import CheckedOptions, Importer
from .images import Distortion, frame_number, image_source
from .recording import Corrections, Dropped, Recording, RecordingError, check_pose

if TYPE_CHECKING:
    from ..camera import CameraModel
    from ..data import DatasetReader

__all__ = ["NerfstudioImporter", "NerfstudioOptions", "Lens", "Image", "load_json", "json_number",
           "read_frames", "read_transforms", "recording_from_transforms", "export", "transforms_of",
           "OPENGL_FROM_OPENCV", "PIXEL_OFFSET", "FISHEYE", "DISTORTION"]

OPENGL_FROM_OPENCV = np.diag([1.0, -1.0, -1.0, 1.0])
"""Right factor between ParkSim's T_world_camera (OpenCV axes) and nerfstudio's transform_matrix (OpenGL axes);
its own inverse."""
PIXEL_OFFSET = 0.5
"""nerfstudio's principal point minus ParkSim's: their pixel centres sit at half-integers, ours at integers."""
FISHEYE = "OPENCV_FISHEYE"
PERSPECTIVE = ("OPENCV", "PINHOLE", "SIMPLE_PINHOLE", "SIMPLE_RADIAL", "RADIAL")
"""nerfstudio's perspective models: all one camera type there (fl_x, fl_y, cx, cy and optional distortion)."""
INTRINSICS = ("fl_x", "fl_y", "cx", "cy", "w", "h")
DISTORTION = ("k1", "k2", "k3", "k4", "p1", "p2")
SPLITS = {"train": ("train_filenames",), "test": ("test_filenames", "val_filenames")}


@dataclass(frozen=True)
class NerfstudioOptions(CheckedOptions):
    """Options of ``parksim import nerfstudio``."""

    transforms: Path = field(metadata={"help": "transforms.json, or the folder holding it", "positional": True})
    fps: float = field(default=10.0, metadata={
        "help": "frame rate giving timestamps (frame number / fps) when frames have no 'time'", "low": 0,
        "open_low": True})


@dataclass(frozen=True)
class Lens:
    """One image's camera as transforms.json states it (nerfstudio pixel convention)."""

    model: str
    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    distortion: tuple[float, ...]   # k1, k2, k3, k4, p1, p2
    max_fov_deg: float | None

    def camera(self) -> CameraModel:
        """The ParkSim camera: OpenCVFisheye, or Pinhole (after undistortion when there is distortion)."""
        from ..camera import OpenCVFisheye, Pinhole

        cx, cy = self.cx - PIXEL_OFFSET, self.cy - PIXEL_OFFSET
        fov = {} if self.max_fov_deg is None else {"max_fov_deg": self.max_fov_deg}
        if self.model == FISHEYE:
            return OpenCVFisheye(self.width, self.height, self.fx, self.fy, cx, cy, list(self.distortion[:4]), **fov)
        return Pinhole(self.width, self.height, self.fx, self.fy, cx, cy, **fov)

    @property
    def distortion_to_remove(self) -> Distortion | None:
        """The perspective distortion the images must lose to become pinhole images, or None."""
        if self.model == FISHEYE or not any(self.distortion):
            return None
        k1, k2, k3, k4, p1, p2 = self.distortion
        return Distortion(self.width, self.height, self.fx, self.fy, self.cx - PIXEL_OFFSET, self.cy - PIXEL_OFFSET,
                          (k1, k2, k3, k4), (p1, p2))


@dataclass(frozen=True)
class Image:
    """One entry of ``frames``: its file, frame id, time, camera and pose."""

    path: Path
    frame: int
    time: float | None
    lens: Lens
    T_world_camera: np.ndarray


def load_json(path: Path) -> tuple[Path, dict[str, Any]]:
    """The transforms file (``path`` or ``path/transforms.json``) and its content, checked to be an object with a
    non-empty ``frames`` list."""
    file = path / "transforms.json" if path.is_dir() else path
    if not file.is_file():
        raise RecordingError(f"{file}: file not found")
    try:
        meta = json.loads(file.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise RecordingError(f"{file}: not valid JSON: {e}") from None
    if not isinstance(meta, dict) or not isinstance(meta.get("frames"), list) or not meta["frames"]:
        raise RecordingError(f"{file}: expected an object with a non-empty 'frames' list")
    return file, meta


def json_number(entry: dict[str, Any], key: str, where: str, default: float | None = None) -> float:
    """``entry[key]`` (else ``default``) as a finite float; its absence or another type is an error at ``where``."""
    value = entry.get(key, default)
    if value is None:
        raise RecordingError(f"{where}: no {key!r} (at the top level or in the frame)")
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise RecordingError(f"{where}: {key!r} must be a finite number, got {value!r}")
    return float(value)


def _lens(meta: dict[str, Any], frame: dict[str, Any], model: str, where: str) -> Lens:
    """A frame's intrinsics: per key from the top level if there, else from the frame (nerfstudio's rule)."""
    def pick(key: str, default: float | None = None) -> float:
        return json_number(meta if key in meta else frame, key, where, default)

    source = meta if any(k in meta for k in DISTORTION) else frame
    distortion = tuple(json_number(source, k, where, 0.0) for k in DISTORTION)
    size = []
    for key in ("w", "h"):
        v = pick(key)
        if v != int(v) or v <= 0:
            raise RecordingError(f"{where}: {key!r} must be a positive integer, got {v}")
        size.append(int(v))
    fov = meta.get("max_fov_deg", frame.get("max_fov_deg"))
    if model == FISHEYE and any(distortion[4:]):
        raise RecordingError(f"{where}: OPENCV_FISHEYE has no tangential distortion, got p1, p2 = {distortion[4:]}")
    return Lens(model, size[0], size[1], pick("fl_x"), pick("fl_y"), pick("cx"), pick("cy"), distortion,
                None if fov is None else json_number({"max_fov_deg": fov}, "max_fov_deg", where))


def _pose(frame: dict[str, Any], where: str, corrected: Corrections | None) -> np.ndarray:
    """T_world_camera (OpenCV axes) from a 4x4 or 3x4 camera-to-world ``transform_matrix`` (OpenGL axes), its
    rotation projected to the nearest proper one (``check_pose``; counted in ``corrected``)."""
    try:
        M = np.array(frame["transform_matrix"], dtype=np.float64)
    except KeyError:
        raise RecordingError(f"{where}: no 'transform_matrix'") from None
    except (TypeError, ValueError):
        raise RecordingError(f"{where}: transform_matrix must be a 4x4 (or 3x4) matrix of numbers") from None
    if M.shape == (3, 4):
        M = np.vstack([M, [0.0, 0.0, 0.0, 1.0]])
    if M.shape != (4, 4):
        raise RecordingError(f"{where}: transform_matrix must be 4x4 (or 3x4), got shape {M.shape}")
    if not np.isfinite(M).all():
        raise RecordingError(f"{where}: transform_matrix has non-finite values")
    return check_pose(M, f"{where}: transform_matrix", corrected) @ OPENGL_FROM_OPENCV


def read_frames(file: Path, meta: dict[str, Any], corrected: Corrections | None = None) -> list[Image]:
    """Every frame of ``meta`` (the content of ``file``), checked: its lens is one ParkSim models, its pose is rigid
    (a rotation within tolerance is projected to a proper one). Its image file is not opened: an absent, unreadable
    or wrong-size image drops its frame when the dataset is written (``recording.write_recording``).

    Args:
        file: the transforms file (image paths are relative to its folder; messages name it).
        meta: its content in nerfstudio's keys (``load_json``).
        corrected: counts the rotations projected (None: not counted).

    Returns:
        One ``Image`` per entry of ``meta["frames"]``, in order.
    """
    model = meta.get("camera_model", "OPENCV")
    if model != FISHEYE and model not in PERSPECTIVE:
        raise RecordingError(f"{file}: camera_model {model!r} is not supported; use {FISHEYE} or one of "
                             f"{', '.join(PERSPECTIVE)}")
    images = []
    for i, frame in enumerate(meta["frames"]):
        where = f"{file} frames[{i}]"
        if not isinstance(frame, dict) or not isinstance(frame.get("file_path"), str) or not frame["file_path"]:
            raise RecordingError(f"{where}: no 'file_path'")
        image = file.parent / frame["file_path"]
        where = f"{where} ({frame['file_path']})"
        lens = _lens(meta, frame, model, where)
        time = None if "time" not in frame else json_number(frame, "time", where)
        images.append(Image(image, frame_number(image.name, where), time, lens, _pose(frame, where, corrected)))
    if len({im.time is None for im in images}) > 1:
        raise RecordingError(f"{file}: 'time' must be given for every frame or for none")
    return images


def read_transforms(path: Path, corrected: Corrections | None = None) -> tuple[Path, dict[str, Any], list[Image]]:
    """Parse and check transforms.json (``path`` or the folder holding it): the file, its content, its frames
    (rotations projected counted in ``corrected``)."""
    file, meta = load_json(path)
    return file, meta, read_frames(file, meta, corrected)


def _group(file: Path, images: list[Image]) -> tuple[list[str], str]:
    """Each image's camera name and the rule used: parent folder when there are several, else intrinsics."""
    parents = list(dict.fromkeys(im.path.parent for im in images))
    if len(parents) > 1:
        names = [p.name for p in parents]
        clash = sorted({n for n in names if names.count(n) > 1})
        if clash:
            raise RecordingError(f"{file}: image folders share the name {clash[0]!r}; camera names come from the "
                                 "parent folder's name")
        return [im.path.parent.name for im in images], "parent folder"
    lenses = list(dict.fromkeys(im.lens for im in images))
    return [f"cam{lenses.index(im.lens)}" for im in images], "distinct intrinsics"


def _points(file: Path, meta: dict[str, Any]) -> tuple[np.ndarray, np.ndarray] | None:
    """The ``ply_file_path`` point cloud (x, y, z and red, green, blue), or None."""
    if "ply_file_path" not in meta:
        return None
    from plyfile import PlyData

    path = file.parent / str(meta["ply_file_path"])
    if not path.is_file():
        raise RecordingError(f"{path}: ply_file_path not found")
    try:
        v = PlyData.read(str(path))["vertex"]
        xyz = np.stack([v["x"], v["y"], v["z"]], 1).astype(np.float64)
        rgb = np.stack([v["red"], v["green"], v["blue"]], 1)
    except (KeyError, ValueError, IndexError, EOFError) as e:
        raise RecordingError(f"{path}: not a point-cloud PLY with x, y, z, red, green, blue: {e}") from None
    if rgb.dtype != np.uint8:
        raise RecordingError(f"{path}: colours must be 8-bit (uchar red, green, blue), got {rgb.dtype}")
    if not np.isfinite(xyz).all():
        raise RecordingError(f"{path}: non-finite point coordinates")
    return xyz, rgb


def _split(file: Path, meta: dict[str, Any], frame_images: dict[int, list[Path]]
           ) -> tuple[list[int], list[int]] | None:
    """(train, test) frames from ``train_filenames`` and ``test_filenames``/``val_filenames``: a frame is test
    when any of its images is listed for test or val, else train. None when the file has no split."""
    if not any(k in meta for keys in SPLITS.values() for k in keys):
        return None
    listed = set()
    for key in SPLITS["test"]:
        names = meta.get(key, [])
        if not isinstance(names, list) or not all(isinstance(n, str) for n in names):
            raise RecordingError(f"{file}: {key} must be a list of file paths")
        listed |= {os.path.normpath(file.parent / n) for n in names}
    test = [f for f, paths in frame_images.items() if any(os.path.normpath(p) in listed for p in paths)]
    return [f for f in frame_images if f not in set(test)], test


def _timestamp(images: list[Image], fps: float) -> float:
    """A frame's time: the earliest ``time`` of its images, else its frame number / ``fps``."""
    times = [im.time for im in images if im.time is not None]
    return min(times) if times else images[0].frame / fps


def recording_from_transforms(file: Path, meta: dict[str, Any], images: list[Image], fps: float,
                              source: str = "nerfstudio", corrected: Corrections | None = None,
                              dropped: list[Dropped] | None = None) -> Recording:
    """The frames of a transforms file as a Recording with per-image poses (``import_recording`` fits the rig).

    Args:
        file: the transforms file; ``meta`` its content in nerfstudio's keys; ``images`` its frames
            (``read_frames``).
        fps: frames without ``time`` are at frame number / ``fps`` seconds.
        source: the dialect, named in the report's notes.
        corrected: what ``read_frames`` corrected, for the report (None: nothing).
        dropped: frames the dialect left out already (an image it could not read a lens from), not counted again.

    Returns:
        Cameras grouped by folder (else intrinsics), frames with an image from every camera (the others dropped),
        the file's split and point cloud when it has them.
    """
    import torch

    from ..rig import BEVSpec, Rig, RigCamera

    names, rule = _group(file, images)
    cameras = list(dict.fromkeys(names))
    lenses: dict[str, Lens] = {}
    table: dict[tuple[int, str], Image] = {}
    for im, cam in zip(images, names):
        if lenses.setdefault(cam, im.lens) != im.lens:
            raise RecordingError(f"{file}: camera {cam!r} has images with different intrinsics ({im.path.name})")
        if (im.frame, cam) in table:
            raise RecordingError(f"{file}: {table[(im.frame, cam)].path.name} and {im.path.name} are both frame "
                                 f"{im.frame} of camera {cam!r}")
        table[(im.frame, cam)] = im
    models = {}
    for cam, lens in lenses.items():
        try:
            models[cam] = lens.camera()
        except ValueError as e:
            raise RecordingError(f"{file}: camera {cam!r}: {e}") from None
    known = {d.frame for d in dropped or []}
    frames, dropped = [], list(dropped or [])
    for f in sorted({f for f, _ in table}):
        missing = [c for c in cameras if (f, c) not in table]
        if missing:
            if f not in known:
                dropped.append(Dropped(f"no image from camera(s) {', '.join(missing)}", frame=f))
        else:
            frames.append(f)
    if not frames:
        raise RecordingError(f"{file}: no frame has an image from every camera {cameras}")
    timed = images[0].time is not None
    stamps = [_timestamp([table[(f, c)] for c in cameras], fps) for f in frames]
    rig = Rig({c: RigCamera(c, models[c], torch.eye(4, dtype=torch.float64)) for c in cameras}, BEVSpec())
    notes: dict[str, Any] = {
        "source": str(file), "camera_model": meta.get("camera_model", "OPENCV (absent)"), "cameras_by": rule,
        "timestamps": "the frames' time" if timed else f"frame number / {fps} fps",
        "principal_point": f"cx = cx_{source} - 0.5, cy = cy_{source} - 0.5 (pixel centres at 0.5 there, 0 here)"}
    undistorted = {c: f"{source}'s perspective distortion -> pinhole (same fl_x, fl_y, cx, cy), cv2.remap "
                      "bilinear, black where the source has no pixel"
                   for c in cameras if lenses[c].distortion_to_remove}
    extra = {"applied_transform": meta.get("applied_transform"), "undistorted": undistorted,
             "ignored": sorted({k for fr in meta["frames"] for k in ("mask_path", "depth_file_path") if k in fr})}
    notes.update({k: v for k, v in extra.items() if v})
    return Recording(
        rig=rig, frames=frames, timestamps=stamps,
        images={(f, c): image_source(table[(f, c)].path, lenses[c].distortion_to_remove)
                for f in frames for c in cameras},
        camera_poses=[{c: table[(f, c)].T_world_camera for c in cameras} for f in frames],
        points=_points(file, meta), dropped=dropped, notes=notes,
        split=_split(file, meta, {f: [table[(f, c)].path for c in cameras] for f in frames}),
        corrected=corrected or Corrections())


class NerfstudioImporter(Importer):
    """nerfstudio's ``transforms.json`` and its images."""

    name = "nerfstudio"
    help = "a nerfstudio transforms.json (OPENCV_FISHEYE, OPENCV or PINHOLE cameras) with its images"
    description = (
        "Read a nerfstudio dataset: transforms.json (camera_model OPENCV_FISHEYE, OPENCV, PINHOLE or another "
        "perspective model; fl_x, fl_y, cx, cy, w, h and k1..k4, p1, p2 at the top level or per frame; per "
        "frame file_path relative to the json and transform_matrix camera-to-world in OpenGL camera axes; "
        "optional time (s), ply_file_path, train/val/test_filenames). Images are grouped into cameras by parent "
        "folder (else by distinct intrinsics) and into frames by the last integer in the file name; a frame "
        "missing a camera is dropped. Perspective images with distortion are undistorted to pinhole cameras with "
        "the same focal length and centre. Timestamps are the frames' time, else frame number / --fps. See "
        "docs/import_nerfstudio.md.")
    Options = NerfstudioOptions

    def load(self, options: NerfstudioOptions) -> Recording:
        """Read and check transforms.json and its images (nothing is written)."""
        file, meta = load_json(options.transforms)
        corrected = Corrections()
        images = read_frames(file, meta, corrected)
        return recording_from_transforms(file, meta, images, options.fps, corrected=corrected)


# --- export -------------------------------------------------------------------------------------------------------
def _lens_keys(name: str, model: CameraModel) -> tuple[str, dict[str, Any]]:
    """camera_model and the transforms.json intrinsics of a ParkSim camera; other models are a clear error."""
    from ..camera import OpenCVFisheye, Pinhole

    if not isinstance(model, (OpenCVFisheye, Pinhole)):
        raise ValueError(f"camera {name!r} is {model.model}; nerfstudio export supports opencv_fisheye "
                         "(OPENCV_FISHEYE) and pinhole (PINHOLE) cameras only")
    keys: dict[str, Any] = {"fl_x": float(model.fx), "fl_y": float(model.fy), "cx": float(model.cx) + PIXEL_OFFSET,
                            "cy": float(model.cy) + PIXEL_OFFSET, "w": model.width, "h": model.height}
    if isinstance(model, OpenCVFisheye):
        keys.update(zip(DISTORTION[:4], (float(v) for v in model.k)))
    keys["max_fov_deg"] = model.max_fov_deg
    return (FISHEYE if isinstance(model, OpenCVFisheye) else "PINHOLE"), keys


def transforms_of(reader: DatasetReader) -> tuple[dict[str, Any], list[tuple[Path, str]]]:
    """transforms.json for a dataset and the (source, relative destination) image copies it refers to."""
    from ..data.layout import frame_name

    rig = reader.rig
    lenses = {c: _lens_keys(c, rig.cameras[c].model) for c in rig.names}
    kinds = {kind for kind, _ in lenses.values()}
    if len(kinds) > 1:
        raise ValueError(f"the rig mixes {' and '.join(sorted(kinds))} cameras; nerfstudio's camera_model is one "
                         "per transforms.json")
    shared = all(keys == lenses[rig.names[0]][1] for _, keys in lenses.values())
    meta: dict[str, Any] = {"camera_model": kinds.pop(), **(lenses[rig.names[0]][1] if shared else {})}
    frames: list[dict[str, Any]] = []
    copies: list[tuple[Path, str]] = []
    names: dict[int, list[str]] = {}
    for f, t in zip(reader.frames, reader.timestamps):
        for c in rig.names:
            rel = f"images/{c}/{frame_name(f)}.png"
            T = reader.camera_pose(c, f).numpy() @ OPENGL_FROM_OPENCV
            frames.append({"file_path": rel, "transform_matrix": T.tolist(), "time": float(t),
                           **({} if shared else lenses[c][1])})
            copies.append((reader.layout.image(c, f), rel))
            names.setdefault(f, []).append(rel)
    meta["frames"] = frames
    test = reader.split["test"]
    if test:
        meta["train_filenames"] = [n for f in reader.split["train"] for n in names[f]]
        meta["val_filenames"] = meta["test_filenames"] = [n for f in test for n in names[f]]
    if reader.layout.points.is_file():
        meta["ply_file_path"] = "sparse_pc.ply"
        copies.append((reader.layout.points, "sparse_pc.ply"))
    return meta, copies


def export(dataset: str | Path, out: str | Path, overwrite: bool = False) -> dict[str, Any]:
    """Write ``dataset`` as a nerfstudio folder at ``out`` (transforms.json, images copied byte for byte,
    sparse_pc.ply), all or nothing; returns a short report."""
    from ..data import DatasetReader
    from ..fileio import atomic_directory

    reader = DatasetReader(dataset)
    meta, copies = transforms_of(reader)
    with atomic_directory(out, overwrite=overwrite) as tmp:
        for src, rel in copies:
            (tmp / rel).parent.mkdir(parents=True, exist_ok=True)
            shutil.copyfile(src, tmp / rel)
        (tmp / "transforms.json").write_text(json.dumps(meta, indent=1))
    return {"output": str(out), "camera_model": meta["camera_model"], "cameras": reader.rig.names,
            "frames": len(reader.frames), "images": len(meta["frames"]),
            "intrinsics": "shared (top level)" if "fl_x" in meta else "per frame",
            "points": "ply_file_path" in meta, "split": "train_filenames" in meta}
