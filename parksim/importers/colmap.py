"""COLMAP sparse model (cameras, images, points3D as ``.bin`` or ``.txt``) and its images -> ``Recording``.

Our own reader of COLMAP's documented formats (https://colmap.github.io/format.html), so importing needs no
pycolmap. Conventions of the source and what becomes of them:

- images store world -> camera as a Hamilton quaternion ``(qw, qx, qy, qz)`` and ``t``; the camera frame is
  OpenCV's (x right, y down, z forward), as ParkSim's, so ``T_world_camera = [R | t]^-1`` with no axis change.
- COLMAP puts the first pixel's centre at (0.5, 0.5), ParkSim at (0, 0): ``cx = cx_colmap - 0.5`` (same for cy).
- OPENCV_FISHEYE becomes ``OpenCVFisheye`` and SIMPLE_PINHOLE/PINHOLE ``Pinhole`` unchanged; SIMPLE_RADIAL,
  RADIAL and OPENCV (cv2's k1 k2 p1 p2 model) become ``Pinhole`` with the same K, their images undistorted by
  ``cv2.remap`` (bilinear; pixels that see outside the source image are black). Other models are refused.
- Images are grouped into cameras by their folder (``front/000001.png`` -> camera ``front``; an image at the
  top level -> ``cam<COLMAP camera id>``), each folder holding one COLMAP camera, and into frames by the last
  integer in the file stem. Frames without an image from every camera are dropped and counted.
- COLMAP has no times: frame ``f`` is at ``f / fps``. Its points3D are the sparse (initial) point cloud.
"""

from __future__ import annotations

import struct
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from .base import CheckedOptions, Importer
from .images import Distortion, frame_number, image_source
from .recording import Corrections, Dropped, Recording, RecordingError

__all__ = ["ColmapImporter", "ColmapOptions", "ColmapError", "ColmapCamera", "ColmapImage", "ColmapModel",
           "read_model", "recording_from_model", "MODEL_NAMES"]

MODEL_NAMES = ("SIMPLE_PINHOLE", "PINHOLE", "SIMPLE_RADIAL", "RADIAL", "OPENCV", "OPENCV_FISHEYE", "FULL_OPENCV",
               "FOV", "SIMPLE_RADIAL_FISHEYE", "RADIAL_FISHEYE", "THIN_PRISM_FISHEYE", "RAD_TAN_THIN_PRISM_FISHEYE",
               "SIMPLE_DIVISION", "DIVISION", "SIMPLE_FISHEYE", "FISHEYE", "EUCM", "EQUIRECTANGULAR")
"""COLMAP's camera model names, indexed by model id (as stored in cameras.bin)."""

PARAMS = {"SIMPLE_PINHOLE": 3, "PINHOLE": 4, "SIMPLE_RADIAL": 4, "RADIAL": 5, "OPENCV": 8, "OPENCV_FISHEYE": 8}
"""The camera models imported, with their number of parameters."""

QUATERNION_TOLERANCE = 1e-3
"""Largest deviation of an image quaternion's norm from 1 accepted (text files round); it is then normalised and
the deviation reported (``ColmapImage.norm``)."""


class ColmapError(RecordingError):
    """A COLMAP model is missing, malformed or uses what ParkSim cannot import; the message names the file."""


@dataclass(frozen=True)
class ColmapCamera:
    """One ``cameras`` entry: COLMAP model name, image size and parameters (COLMAP's pixel convention)."""

    camera_id: int
    model: str
    width: int
    height: int
    params: tuple[float, ...]


@dataclass(frozen=True)
class ColmapImage:
    """One ``images`` entry: world -> camera as unit quaternion ``qvec = (w, x, y, z)`` and ``tvec``; ``norm`` is
    the quaternion's norm in the file (``qvec`` is normalised)."""

    image_id: int
    qvec: tuple[float, float, float, float]
    tvec: tuple[float, float, float]
    camera_id: int
    name: str
    norm: float = 1.0

    @property
    def T_camera_world(self) -> np.ndarray:
        """4x4 float64 world -> camera."""
        w, x, y, z = self.qvec
        T = np.eye(4)
        T[:3, :3] = [[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                     [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                     [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]]
        T[:3, 3] = self.tvec
        return T

    @property
    def T_world_camera(self) -> np.ndarray:
        """4x4 float64 camera -> world (the rigid inverse of ``T_camera_world``)."""
        T_cw = self.T_camera_world
        T = np.eye(4)
        T[:3, :3] = T_cw[:3, :3].T
        T[:3, 3] = -T_cw[:3, :3].T @ T_cw[:3, 3]
        return T


@dataclass
class ColmapModel:
    """A sparse model: cameras and images by id, points ``xyz [M, 3]`` float64 and ``rgb [M, 3]`` uint8."""

    path: Path
    format: str
    cameras: dict[int, ColmapCamera]
    images: dict[int, ColmapImage]
    xyz: np.ndarray
    rgb: np.ndarray


# --- reading ---------------------------------------------------------------------------------------------------
def _supported(path: Path, where: str, camera_id: int, model: str) -> int:
    """The number of parameters of ``model``, or the error that ParkSim does not import it."""
    if model not in PARAMS:
        raise ColmapError(f"{path}: {where}camera {camera_id} uses COLMAP model {model}, which ParkSim does not "
                          f"import (supported: {', '.join(PARAMS)})")
    return PARAMS[model]


def _camera(path: Path, where: str, camera_id: int, model: str, width: int, height: int,
            params: tuple[float, ...]) -> ColmapCamera:
    """A checked camera entry: supported model, positive size, finite parameters of the right number."""
    _supported(path, where, camera_id, model)
    if width <= 0 or height <= 0:
        raise ColmapError(f"{path}: {where}camera {camera_id} has size {width}x{height}")
    if len(params) != PARAMS[model] or not np.isfinite(params).all():
        raise ColmapError(f"{path}: {where}camera {camera_id} ({model}) needs {PARAMS[model]} finite parameters, "
                          f"got {list(params)}")
    return ColmapCamera(camera_id, model, width, height, params)


def _image(path: Path, where: str, image_id: int, q: tuple[float, ...], t: tuple[float, ...], camera_id: int,
           name: str) -> ColmapImage:
    """A checked image entry with its quaternion normalised."""
    norm = float(np.linalg.norm(q))
    if not (np.isfinite(q).all() and np.isfinite(t).all()) or abs(norm - 1) > QUATERNION_TOLERANCE:
        raise ColmapError(f"{path}: {where}image {image_id} ({name}) has a non-finite pose or a quaternion of norm "
                          f"{norm:.6g} (expected 1)")
    w, x, y, z = (v / norm for v in q)
    return ColmapImage(image_id, (w, x, y, z), (t[0], t[1], t[2]), camera_id, name, norm)


class _Bytes:
    """A cursor over a little-endian binary file that names the file and offset when it runs short."""

    def __init__(self, path: Path) -> None:
        self.path, self.data, self.pos = path, path.read_bytes(), 0

    def take(self, fmt: str) -> tuple[Any, ...]:
        size = struct.calcsize("<" + fmt)
        if self.pos + size > len(self.data):
            raise ColmapError(f"{self.path}: truncated at byte {len(self.data)} (a record needs bytes up to "
                              f"{self.pos + size})")
        values = struct.unpack_from("<" + fmt, self.data, self.pos)
        self.pos += size
        return values

    def skip(self, size: int) -> None:
        if self.pos + size > len(self.data):
            raise ColmapError(f"{self.path}: truncated at byte {len(self.data)} (a record needs bytes up to "
                              f"{self.pos + size})")
        self.pos += size

    def name(self) -> str:
        end = self.data.find(b"\0", self.pos)
        if end < 0:
            raise ColmapError(f"{self.path}: truncated at byte {len(self.data)} (an image name has no end)")
        text, self.pos = self.data[self.pos:end].decode("utf-8", "replace"), end + 1
        return text

    def done(self) -> None:
        if self.pos != len(self.data):
            raise ColmapError(f"{self.path}: {len(self.data) - self.pos} bytes after the last record (corrupt file)")


def _read_binary(folder: Path) -> tuple[dict[int, ColmapCamera], dict[int, ColmapImage], np.ndarray, np.ndarray]:
    f = _Bytes(folder / "cameras.bin")
    cameras = {}
    for _ in range(f.take("Q")[0]):
        camera_id, model_id, width, height = f.take("IiQQ")
        model = MODEL_NAMES[model_id] if 0 <= model_id < len(MODEL_NAMES) else f"id {model_id}"
        params = f.take(f"{_supported(f.path, '', camera_id, model)}d")
        cameras[camera_id] = _camera(f.path, "", camera_id, model, width, height, params)
    f.done()
    f = _Bytes(folder / "images.bin")
    images = {}
    for _ in range(f.take("Q")[0]):
        image_id, *pose, camera_id = f.take("I7dI")
        name = f.name()
        f.skip(24 * f.take("Q")[0])  # POINTS2D: x, y (double), POINT3D_ID (uint64)
        images[image_id] = _image(f.path, "", image_id, tuple(pose[:4]), tuple(pose[4:]), camera_id, name)
    f.done()
    f = _Bytes(folder / "points3D.bin")
    n = f.take("Q")[0]
    xyz, rgb = np.empty((n, 3)), np.empty((n, 3), np.uint8)
    for i in range(n):
        _, *xyz[i], r, g, b, _ = f.take("Q3d3Bd")
        rgb[i] = r, g, b
        f.skip(8 * f.take("Q")[0])  # TRACK: IMAGE_ID, POINT2D_IDX (uint32 each)
    f.done()
    return cameras, images, xyz, rgb


def _lines(path: Path) -> Iterator[tuple[int, str]]:
    """``(line number, line)`` of a text model file, comments and blank lines included (images.txt needs them)."""
    with open(path, encoding="utf-8") as fh:
        yield from enumerate((line.strip() for line in fh), start=1)


def _is_data(line: str) -> bool:
    return bool(line) and not line.startswith("#")


def _read_text(folder: Path) -> tuple[dict[int, ColmapCamera], dict[int, ColmapImage], np.ndarray, np.ndarray]:
    cameras, images, xyz, rgb = {}, {}, [], []
    path = folder / "cameras.txt"
    for no, line in _lines(path):
        if _is_data(line):
            try:
                cid, model, width, height, *params = line.split()
                fields = int(cid), model, int(width), int(height), tuple(float(v) for v in params)
            except ValueError:
                raise ColmapError(f"{path}: line {no}: expected CAMERA_ID MODEL WIDTH HEIGHT PARAMS[]") from None
            cameras[fields[0]] = _camera(path, f"line {no}: ", *fields)
    path = folder / "images.txt"
    lines = _lines(path)
    for no, line in lines:
        if _is_data(line):
            next(lines, None)  # POINTS2D[] as (X, Y, POINT3D_ID), possibly an empty line
            try:
                iid, *pose, cid, name = line.split(maxsplit=9)
                values = [float(v) for v in pose]
                if len(values) != 7:
                    raise ValueError
                image_id, camera_id = int(iid), int(cid)
            except ValueError:
                raise ColmapError(f"{path}: line {no}: expected IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME") \
                    from None
            images[image_id] = _image(path, f"line {no}: ", image_id, tuple(values[:4]), tuple(values[4:]),
                                      camera_id, name)
    path = folder / "points3D.txt"
    for no, line in _lines(path):
        if _is_data(line):
            try:
                cols = line.split()
                xyz.append([float(v) for v in cols[1:4]])
                rgb.append([int(v) for v in cols[4:7]])
                if len(xyz[-1]) != 3 or len(rgb[-1]) != 3 or not 0 <= min(rgb[-1]) <= max(rgb[-1]) <= 255:
                    raise ValueError
            except ValueError:
                raise ColmapError(f"{path}: line {no}: expected POINT3D_ID X Y Z R G B ERROR TRACK[]") from None
    return cameras, images, np.array(xyz, np.float64).reshape(-1, 3), np.array(rgb, np.uint8).reshape(-1, 3)


def read_model(folder: str | Path) -> ColmapModel:
    """Read a sparse model folder, binary when all three ``.bin`` files are there (as COLMAP), else text."""
    folder = Path(folder)
    if not folder.is_dir():
        raise ColmapError(f"{folder}: COLMAP model folder not found")
    parts = ("cameras", "images", "points3D")
    for fmt, ext, read in (("binary", "bin", _read_binary), ("text", "txt", _read_text)):
        if all((folder / f"{p}.{ext}").is_file() for p in parts):
            cameras, images, xyz, rgb = read(folder)
            model_format = fmt
            break
    else:
        found = sorted(p.name for p in folder.iterdir() if p.suffix in (".bin", ".txt"))
        raise ColmapError(f"{folder}: not a readable COLMAP model (needs cameras, images and points3D, all .bin or "
                          f"all .txt; found {found or 'none'})")
    unknown = sorted({im.camera_id for im in images.values()} - set(cameras))
    if unknown:
        raise ColmapError(f"{folder}: images refer to camera ids {unknown} that the cameras file lacks")
    if not np.isfinite(xyz).all():
        raise ColmapError(f"{folder}: points3D has non-finite coordinates")
    return ColmapModel(folder, model_format, cameras, images, xyz, rgb)


# --- model -> Recording -------------------------------------------------------------------------------------------
def _lens(cam: ColmapCamera) -> tuple[Any, Distortion | None]:
    """ParkSim camera model for a COLMAP camera, and the distortion its images must lose when it has one."""
    from ..camera import OpenCVFisheye, Pinhole

    p = cam.params
    if cam.model == "OPENCV_FISHEYE":
        return OpenCVFisheye(cam.width, cam.height, p[0], p[1], p[2] - 0.5, p[3] - 0.5, list(p[4:])), None
    # SIMPLE_* and RADIAL have one focal length; the distortion terms after it are k1 k2 p1 p2, zero-padded.
    fx, fy, cx, cy, *dist = (p[0], *p) if cam.model in ("SIMPLE_PINHOLE", "SIMPLE_RADIAL", "RADIAL") else p
    pinhole = Pinhole(cam.width, cam.height, fx, fy, cx - 0.5, cy - 0.5)
    if not dist:
        return pinhole, None
    k1, k2, p1, p2 = [*dist, 0.0, 0.0, 0.0][:4]
    return pinhole, Distortion(cam.width, cam.height, fx, fy, cx - 0.5, cy - 0.5, (k1, k2, 0.0, 0.0), (p1, p2))


def _camera_names(model: ColmapModel) -> dict[int, str]:
    """Image id -> camera name: its folder (``/`` -> ``_``), or ``cam<camera id>`` at the top level."""
    names: dict[int, str] = {}
    ids_of: dict[str, set[int]] = {}
    for im in model.images.values():
        folder = Path(im.name).parent.as_posix()
        name = folder.replace("/", "_") if folder != "." else f"cam{im.camera_id}"
        names[im.image_id] = name
        ids_of.setdefault(name, set()).add(im.camera_id)
    for name, ids in ids_of.items():
        if len(ids) > 1:
            raise ColmapError(f"{model.path}: the images of camera {name!r} use COLMAP cameras {sorted(ids)}; "
                              f"ParkSim needs one camera (intrinsics) per image folder")
    return names


def _images_dir(model_dir: Path, given: Path | None) -> Path:
    """``--images``, else ``images/`` beside the model, else beside its parent (COLMAP's ``sparse/0``)."""
    if given is not None:
        if not given.is_dir():
            raise ColmapError(f"--images {given}: folder not found")
        return given
    candidates = [model_dir.resolve().parent / "images", model_dir.resolve().parent.parent / "images"]
    for folder in candidates:
        if folder.is_dir():
            return folder
    raise ColmapError(f"{model_dir}: no images folder at {candidates[0]} or {candidates[1]}; pass --images")


def recording_from_model(model: ColmapModel, images_dir: Path, fps: float = 10.0) -> Recording:
    """The model's images as a Recording with per-image poses (no ego poses: ``fit_rig`` recovers them)."""
    import torch

    from ..rig import BEVSpec, Rig, RigCamera

    if not model.images:
        raise ColmapError(f"{model.path}: the model has no images")
    names = _camera_names(model)
    camera_of = {names[im.image_id]: model.cameras[im.camera_id] for im in model.images.values()}
    order = sorted(camera_of, key=lambda n: (camera_of[n].camera_id, n))
    lenses = {n: _lens(camera_of[n]) for n in order}
    rig = Rig({n: RigCamera(n, lenses[n][0], torch.eye(4, dtype=torch.float64)) for n in order}, BEVSpec())
    by_frame: dict[int, dict[str, ColmapImage]] = {}
    for im in sorted(model.images.values(), key=lambda im: im.name):
        frame, camera = frame_number(im.name, f"{model.path}: image {im.name!r}"), names[im.image_id]
        other = by_frame.setdefault(frame, {}).setdefault(camera, im)
        if other is not im:
            raise ColmapError(f"{model.path}: images {other.name!r} and {im.name!r} are both frame {frame} of "
                              f"camera {camera!r}")
    frames, dropped = [], []
    for f in sorted(by_frame):
        missing = [c for c in order if c not in by_frame[f]]
        if missing:
            dropped.append(Dropped("a camera has no image in this frame", ", ".join(missing), f))
        else:
            frames.append(f)
    paths = {(f, c): images_dir / by_frame[f][c].name for f in frames for c in order}
    if paths and not any(p.is_file() for p in paths.values()):   # a wrong folder, not a few lost files
        raise ColmapError(f"none of the {len(paths)} images named in {model.path} is in {images_dir} (see "
                          f"--images), e.g. {next(iter(paths.values()))}")
    images = {(f, c): image_source(p, lenses[c][1]) for (f, c), p in paths.items()}
    undistorted = {c: f"{camera_of[c].model} -> pinhole (same K), cv2.remap bilinear, black where the source has "
                      f"no pixel" for c in order if lenses[c][1] is not None}
    notes: dict[str, Any] = {
        "colmap_model": str(model.path), "colmap_format": model.format, "images_dir": str(images_dir),
        "colmap_cameras": {c: f"{camera_of[c].model} (camera id {camera_of[c].camera_id})" for c in order},
        "timestamps": f"frame id / {fps:g} fps (COLMAP has no times)",
        "frame_ids": "the last integer in each image's file stem",
        "principal_point": "cx = cx_colmap - 0.5, cy = cy_colmap - 0.5 (pixel centres at 0.5 in COLMAP, 0 here)"}
    if undistorted:
        notes["undistorted"] = undistorted
    camera_poses = [{c: by_frame[f][c].T_world_camera for c in order} for f in frames]
    corrected = Corrections()
    for im in sorted(model.images.values(), key=lambda im: im.image_id):
        corrected.add_quaternion(im.norm, f"{model.path}: image {im.image_id} ({im.name}) quaternion")
    return Recording(rig, frames, [f / fps for f in frames], images, camera_poses=camera_poses,
                     points=(model.xyz, model.rgb), dropped=dropped, notes=notes, corrected=corrected)


@dataclass(frozen=True)
class ColmapOptions(CheckedOptions):
    """Options of ``parksim import colmap``."""

    model: Path = field(metadata={"help": "COLMAP sparse model folder (cameras, images, points3D: .bin or .txt)",
                                  "positional": True, "metavar": "MODEL"})
    images: Path | None = field(default=None, metadata={
        "help": "folder the model's image names are relative to (default: images/ beside MODEL, else beside its "
                "parent)", "metavar": "DIR"})
    fps: float = field(default=10.0, metadata={
        "help": "frame rate: frame f is at f / FPS seconds (COLMAP has no times)", "low": 0, "open_low": True})


class ColmapImporter(Importer):
    """A COLMAP sparse model and its images."""

    name = "colmap"
    help = "a COLMAP sparse model (cameras, images, points3D as .bin or .txt) with its images"
    description = (
        "MODEL is a COLMAP sparse model folder holding cameras, images and points3D, all .bin or all .txt (binary "
        "preferred, as COLMAP does); rigs/frames files are not needed. The images named in it are read from "
        "--images (default: images/ beside MODEL, or beside its parent as in COLMAP's project/sparse/0). An "
        "image's folder is its camera (front/000001.png -> camera front; top-level images -> cam<COLMAP camera "
        "id>) and the last integer in its file stem its frame id; frames without every camera are dropped. Camera "
        "models: OPENCV_FISHEYE, SIMPLE_PINHOLE, PINHOLE; SIMPLE_RADIAL, RADIAL and OPENCV are undistorted to "
        "pinhole. Principal points move from COLMAP's pixel-centre-at-0.5 convention to ParkSim's 0. points3D "
        "becomes the initial point cloud. SfM poses have no metric scale: give --scale, or --rig for its camera "
        "baselines.")
    Options = ColmapOptions

    def load(self, options: ColmapOptions) -> Recording:
        """Read and check the model and its images (nothing is written)."""
        model = read_model(options.model)
        return recording_from_model(model, _images_dir(options.model, options.images), options.fps)
