"""instant-ngp's ``transforms.json``: ``parksim import instant-ngp``.

instant-ngp (its ``nerf_loader.cu`` and ``scripts/colmap2nerf.py``) reads the NeRF ``transforms.json`` with lens
keys of its own. This module rewrites those keys as nerfstudio's and hands the file to ``nerfstudio``'s reader
(``read_frames``, ``recording_from_transforms``), so everything else is nerfstudio's convention:

- ``transform_matrix`` is camera-to-world with OpenGL camera axes; the world is the file's. ``scale``, ``offset``,
  ``aabb`` and ``aabb_scale`` are how instant-ngp maps that world into its unit cube for training: reported, not
  applied.
- Focal length per axis: ``fl_x`` (pixels), ``camera_angle_x`` (radians) or ``x_fov`` (degrees), likewise for y;
  one axis alone gives both. ``cx``, ``cy`` default to the image centre (pixel centres at 0.5, as nerfstudio).
- Lens: OpenCV (``k1, k2, p1, p2``; images undistorted to a pinhole when any is nonzero), or with ``is_fisheye``
  OpenCV fisheye (``k1..k4``). FTheta, latlong and equirectangular lenses are refused.
- A top-level key holds for every frame unless the frame has its own (instant-ngp's rule; a frame's focal length
  replaces both axes). ``w``, ``h`` absent: the image's size; a frame whose image is then absent or unreadable
  has no lens and is dropped here (``recording.ImageDefect``), any other image defect when the dataset is written.
- ``file_path`` without an extension is the first of ``EXTENSIONS`` that exists, as instant-ngp resolves it.
- ``sharpness`` (per frame), ``sharpness_discard_threshold`` and ``n_frames`` are not applied: every frame is
  imported.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from .base import Importer
from .images import frame_number, header_size
from .nerfstudio import (
    DISTORTION,
    FISHEYE,
    NerfstudioOptions,
    json_number,
    load_json,
    read_frames,
    recording_from_transforms,
)
from .recording import Corrections, Dropped, ImageDefect, Recording, RecordingError

__all__ = ["InstantNgpImporter", "InstantNgpOptions", "as_nerfstudio", "EXTENSIONS"]

EXTENSIONS = (".png", ".jpg", ".jpeg", ".bmp")
"""Tried in order for a ``file_path`` without an extension (instant-ngp's list, less what ParkSim cannot decode)."""
LENS_KEYS = ("cx", "cy", "w", "h", "k1", "k2", "k3", "k4", "p1", "p2", "is_fisheye")
FOCAL_KEYS = {"fov": ("{}_fov", "degrees"), "fl": ("fl_{}", "pixels"), "angle": ("camera_angle_{}", "radians")}
"""instant-ngp's focal-length keys per axis, in the order it reads them, and their units."""
UNSUPPORTED = {"ftheta_p0": "FTheta", "latlong": "latlong", "equirectangular": "equirectangular"}
UNIT_CUBE = ("scale", "offset", "aabb", "aabb_scale")
IGNORED = ("sharpness", "sharpness_discard_threshold", "n_frames", "depth_path", "integer_depth_scale",
           "rolling_shutter", "transform_matrix_start", "transform_matrix_end")


@dataclass(frozen=True)
class InstantNgpOptions(NerfstudioOptions):
    """Options of ``parksim import instant-ngp``: nerfstudio's (instant-ngp's frames never have a 'time', so ``fps``
    always gives the timestamps) and the lens' field of view, which instant-ngp's files do not state."""

    max_fov: float | None = field(default=None, metadata={
        "help": "field of view of the lens (instant-ngp's files do not state it; default: 190 with is_fisheye, "
                "else 170)", "metavar": "DEG", "low": 0, "open_low": True, "high": 360})


def _image_path(file: Path, file_path: str) -> str:
    """``file_path`` as instant-ngp resolves it: ``\\`` as ``/``; without an extension and missing, the first
    of ``EXTENSIONS`` that exists (else as given, for the reader to report)."""
    rel = file_path.replace("\\", "/")
    path = file.parent / rel
    if path.suffix or path.exists():
        return rel
    return next((rel + ext for ext in EXTENSIONS if path.with_name(path.name + ext).is_file()), rel)


def _focal(entry: dict[str, Any], size: tuple[int, int], where: str) -> tuple[tuple[float, float], str] | None:
    """(fx, fy) in pixels and the keys read, from one JSON object by instant-ngp's rule, or None without any."""
    found: dict[str, tuple[float, str]] = {}
    for axis, resolution in zip("xy", size):
        for pattern, unit in FOCAL_KEYS.values():
            key = pattern.format(axis)
            if key not in entry:
                continue
            value = json_number(entry, key, where)
            if unit != "pixels":
                angle = math.radians(value) if unit == "degrees" else value
                if not 0 < angle < math.pi:
                    raise RecordingError(f"{where}: {key} = {value} is not a field of view in (0, 180) degrees")
                value = 0.5 * resolution / math.tan(0.5 * angle)
            found[axis] = (value, key)
            break
    if not found:
        return None
    fx, fy = found.get("x") or found["y"], found.get("y") or found["x"]
    return (fx[0], fy[0]), ", ".join(dict.fromkeys((fx[1], fy[1])))


def _frame(file: Path, meta: dict[str, Any], frame: Any, i: int, max_fov: float | None
           ) -> tuple[Any, bool | None, str | None]:
    """One entry of ``frames`` in nerfstudio's keys, whether its lens is a fisheye, and its focal-length keys.
    An entry without a file path is passed on as it is, for ``read_frames`` to report.

    Raises:
        ImageDefect: ``w``, ``h`` are not stated and the image to read them from is absent or unreadable.
    """
    if not isinstance(frame, dict) or not isinstance(frame.get("file_path"), str) or not frame["file_path"]:
        return frame, None, None
    rel = _image_path(file, frame["file_path"])
    where = f"{file} frames[{i}] ({rel})"
    for key, kind in UNSUPPORTED.items():
        if key in frame or key in meta:
            raise RecordingError(f"{where}: instant-ngp's {kind} lens is not supported (OpenCV or OpenCV fisheye)")
    lens = {**{k: meta[k] for k in LENS_KEYS if k in meta}, **{k: frame[k] for k in LENS_KEYS if k in frame}}
    fisheye = bool(lens.get("is_fisheye", False))
    if not fisheye and any(json_number(lens, k, where, 0.0) for k in ("k3", "k4")):
        raise RecordingError(f"{where}: k3, k4 belong to is_fisheye lenses; instant-ngp's OpenCV lens reads k1, "
                             "k2, p1, p2")
    w, h = header_size(file.parent / rel) if "w" not in lens or "h" not in lens else (0, 0)
    w, h = int(json_number(lens, "w", where, w)), int(json_number(lens, "h", where, h))
    focal = _focal(frame, (w, h), where) or _focal(meta, (w, h), where)
    if focal is None:
        raise RecordingError(f"{where}: no focal length (fl_x/fl_y, camera_angle_x/_y or x_fov/y_fov, at the top "
                             "level or in the frame)")
    (fx, fy), source = focal
    out: dict[str, Any] = {
        "file_path": rel, "fl_x": fx, "fl_y": fy, "cx": json_number(lens, "cx", where, w / 2),
        "cy": json_number(lens, "cy", where, h / 2), "w": lens.get("w", w), "h": lens.get("h", h),
        **{k: json_number(lens, k, where, 0.0) for k in DISTORTION},
        **({"transform_matrix": frame["transform_matrix"]} if "transform_matrix" in frame else {})}
    if max_fov is not None:
        out["max_fov_deg"] = max_fov
    return out, fisheye, source


def as_nerfstudio(file: Path, meta: dict[str, Any], max_fov: float | None = None
                  ) -> tuple[dict[str, Any], dict[str, Any], list[Dropped]]:
    """An instant-ngp transforms file's content in nerfstudio's keys, notes on what was read, and the frames left
    out because their lens is unknown (no ``w``, ``h`` and no image to read them from).

    Args:
        file: the transforms file (image paths are relative to its folder; messages name it).
        meta: its content (``nerfstudio.load_json``).
        max_fov: the lens's field of view in degrees, or None for the camera model's default.

    Returns:
        ``camera_model`` and ``frames`` with every lens key per frame (``nerfstudio.read_frames`` reads them),
        notes for the import report, and the frames dropped (each with its ``ImageDefect``'s reason and line).

    Raises:
        RecordingError: an entry is not one ParkSim reads, or every frame is dropped.
    """
    frames, kinds, sources, dropped = [], set(), set(), []
    for i, frame in enumerate(meta["frames"]):
        try:
            out, fisheye, source = _frame(file, meta, frame, i, max_fov)
        except ImageDefect as e:
            where = f"{file} frames[{i}]"
            dropped.append(Dropped(e.reason, frame=frame_number(frame["file_path"], where), detail=f"{where}: {e}"))
            continue
        frames.append(out)
        if fisheye is not None and source is not None:
            kinds.add(fisheye)
            sources.add(source)
    if not frames:
        raise RecordingError(f"{file}: no frame is left to import; {len(dropped)} dropped (first: "
                             f"{dropped[0].detail})")
    if len(kinds) > 1:
        raise RecordingError(f"{file}: is_fisheye differs between frames; ParkSim reads one lens type per file")
    fisheye = kinds == {True}
    notes: dict[str, Any] = {
        "camera_model": "OpenCV fisheye (is_fisheye)" if fisheye else "OpenCV (k1, k2, p1, p2)",
        "focal_length_from": sorted(sources),
        "world": "the file's (instant-ngp's scale, offset and aabb map it into its unit cube for training; not "
                 "applied)"}
    cube = {k: meta[k] for k in UNIT_CUBE if k in meta}
    ignored = sorted({k for k in IGNORED if k in meta} |
                     {k for fr in meta["frames"] if isinstance(fr, dict) for k in IGNORED if k in fr})
    notes.update({k: v for k, v in (("unit_cube", cube), ("ignored", ignored)) if v})
    return {"camera_model": FISHEYE if fisheye else "OPENCV", "frames": frames}, notes, dropped


class InstantNgpImporter(Importer):
    """instant-ngp's ``transforms.json`` and its images (through the nerfstudio reader)."""

    name = "instant-ngp"
    help = "an instant-ngp transforms.json (OpenCV or OpenCV fisheye lens) with its images"
    description = (
        "Read an instant-ngp dataset: transforms.json with the focal length as fl_x/fl_y, camera_angle_x/_y "
        "(radians) or x_fov/y_fov (degrees), optional cx, cy (default: the centre), w, h (default: the image's), "
        "k1, k2, p1, p2 (OpenCV) or is_fisheye with k1..k4, at the top level or per frame (a frame's own keys win); "
        "per frame file_path relative to the json (an extension-less path gets .png, .jpg... as instant-ngp) and "
        "transform_matrix camera-to-world in OpenGL camera axes. scale, offset, aabb and aabb_scale (instant-ngp's "
        "unit cube) are reported, not applied; sharpness is not applied. Images are grouped into cameras by parent "
        "folder (else by distinct intrinsics) and into frames by the last integer in the file name, at frame "
        "number / --fps; distorted OpenCV images are undistorted to pinholes. See docs/import_instant_ngp.md.")
    Options = InstantNgpOptions

    def load(self, options: InstantNgpOptions) -> Recording:
        """Read and check transforms.json and its images (nothing is written)."""
        file, meta = load_json(options.transforms)
        nerfstudio, notes, dropped = as_nerfstudio(file, meta, options.max_fov)
        corrected = Corrections()
        images = read_frames(file, nerfstudio, corrected)
        rec = recording_from_transforms(file, nerfstudio, images, options.fps, "instant-ngp", corrected, dropped)
        rec.notes.update(notes)
        return rec
