"""What every importer returns (``Recording``) and the one writer that turns it into a dataset folder.

Importers only read and check their format; ``write_recording`` checks what all of them share (poses finite with
proper rotations, timestamps increasing, every image decoding to its camera's size), writes the dataset layout of
``parksim.data`` into a temp folder renamed at the end, and saves ``import_report.json``.

An image that cannot be imported whole (absent, cut short, unreadable, or of another size than its camera's: the
``IMAGE_DEFECTS``) is one ``ImageDefect``, whichever importer read it: ``write_recording`` drops its frame with the
reason as one ``Dropped`` counted in the report, or with ``strict`` refuses the recording naming it.

A rotation read from a file is a rotation when it is one within ``parksim.geometry.ROTATION_TOLERANCE`` (float32
and 6-decimal files are): ``check_pose`` projects it to the nearest proper rotation and ``Corrections`` counts what
was corrected, per kind, for the report's ``corrected``.
"""

from __future__ import annotations

import copy
import dataclasses
import math
import sys
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Protocol, runtime_checkable

import numpy as np

if TYPE_CHECKING:   # importers are imported to build `parksim import --help`: no torch at import time
    from ..data import DatasetWriter
    from ..rig import Rig

__all__ = ["ImageSource", "CheckedSource", "RecordingError", "ImageDefect", "Dropped", "Corrections", "Recording",
           "write_recording", "check_pose", "correction_summary", "drop_summary", "downscaled_rig", "REPORT_FILE",
           "ROTATIONS", "CALIBRATION_ROTATIONS", "QUATERNION_NORMS", "MISSING_IMAGE", "TRUNCATED", "UNREADABLE_IMAGE",
           "WRONG_SIZE", "IMAGE_DEFECTS"]

ImageSource = Callable[[], np.ndarray]
"""Returns one image as uint8 RGB ``[H, W, 3]``; called once, when the image is written."""


@runtime_checkable
class CheckedSource(Protocol):
    """An ``ImageSource`` that can tell, cheaply and before anything is written, why its image is unusable (a file
    absent, cut short, unreadable or of another size than its camera: ``parksim.importers.images.FileImage``)."""

    def __call__(self) -> np.ndarray: ...

    def check(self, size: tuple[int, int]) -> None:
        """Raise ``ImageDefect`` when the image cannot be imported whole at its camera's ``size`` (width, height)."""


MISSING_IMAGE = "image file not found"
TRUNCATED = "truncated image file"
"""A JPEG without its end-of-image marker or a PNG without its IEND chunk (``parksim.importers.images``)."""
UNREADABLE_IMAGE = "unreadable image"
"""A file whose header or pixels do not decode."""
WRONG_SIZE = "image size differs from its camera's"
IMAGE_DEFECTS = (MISSING_IMAGE, TRUNCATED, UNREADABLE_IMAGE, WRONG_SIZE)
"""The reasons an image's frame is dropped (``ImageDefect``), or with ``strict`` the import refused."""

REPORT_FILE = "import_report.json"
ROTATIONS = "rotations"
"""``Corrections`` kind: pose rotations (a transform_matrix, an ego or camera pose) projected to a proper one."""
CALIBRATION_ROTATIONS = "calibration_rotations"
"""``Corrections`` kind: calibration rotations (``T_vehicle_camera`` of an extrinsics or rig file) projected."""
QUATERNION_NORMS = "quaternion_norms"
"""``Corrections`` kind: quaternions (COLMAP images, pose logs, extrinsics) normalised; the amount is |norm - 1|."""


class RecordingError(ValueError):
    """The input recording is unusable; the one-line message names the file or option at fault."""


class ImageDefect(RecordingError):
    """One image cannot be imported whole: ``reason`` is one of ``IMAGE_DEFECTS`` (what the report counts), the
    message one line naming the file. ``write_recording`` drops its frame, or with ``strict`` refuses."""

    def __init__(self, reason: str, message: str) -> None:
        super().__init__(message)
        self.reason = reason


@dataclass
class Dropped:
    """One frame or image left out of the dataset, and why."""

    reason: str
    camera: str | None = None
    frame: int | None = None
    timestamp: float | None = None
    detail: str | None = None
    """The one line naming the file at fault (an ``ImageDefect``'s message)."""


@dataclass
class Corrections:
    """What an import corrected in its input, per kind (``ROTATIONS``, ``CALIBRATION_ROTATIONS``,
    ``QUATERNION_NORMS``): ``{kind: {"count", "largest", "where"}}``, the report's ``corrected``."""

    kinds: dict[str, dict[str, Any]] = field(default_factory=dict)

    def add(self, kind: str, amount: float, where: str) -> None:
        """Count one value of ``kind`` corrected by ``amount`` at ``where``; an amount of 0 is nothing to count."""
        if amount <= 0:
            return
        entry = self.kinds.setdefault(kind, {"count": 0, "largest": 0.0, "where": where})
        entry["count"] += 1
        if amount > entry["largest"]:
            entry.update(largest=amount, where=where)

    def add_quaternion(self, norm: float, where: str) -> None:
        """Count a quaternion of ``norm`` normalised at ``where`` (``QUATERNION_NORMS``, by ``|norm - 1|``) unless
        its norm is 1 to float64 round-off (``parksim.geometry.ROTATION_ROUNDOFF``)."""
        from ..geometry import ROTATION_ROUNDOFF

        deviation = abs(norm - 1.0)
        self.add(QUATERNION_NORMS, deviation if deviation > ROTATION_ROUNDOFF else 0.0, where)


def correction_summary(corrected: dict[str, dict[str, Any]]) -> str | None:
    """One line for a report's ``corrected`` (``Corrections.kinds``), or None when nothing was corrected."""
    if not corrected:
        return None
    return "corrected: " + "; ".join(f"{e['count']} {kind.replace('_', ' ')} (largest {e['largest']:.2g} at "
                                     f"{e['where']})" for kind, e in corrected.items())


@dataclass
class Recording:
    """A recording read by an importer: the rig, time-ordered frames, their poses and images.

    ``poses`` are ego poses T_world_vehicle ``[N, 4, 4]``; ``camera_poses`` a ``{camera: T_world_camera}`` per
    frame (what COLMAP and nerfstudio give). At least one of the two is set. ``images`` holds a source for every
    (frame, camera). ``notes`` are importer facts for the report (calibration format, codec, scale source...);
    ``corrected`` what the importer corrected in its input (rotations projected, quaternions normalised).
    """

    rig: Rig
    frames: list[int]
    timestamps: list[float]
    images: dict[tuple[int, str], ImageSource]
    poses: np.ndarray | None = None
    camera_poses: list[dict[str, np.ndarray]] | None = None
    points: tuple[np.ndarray, np.ndarray] | None = None
    dropped: list[Dropped] = field(default_factory=list)
    notes: dict[str, Any] = field(default_factory=dict)
    split: tuple[list[int], list[int]] | None = None
    corrected: Corrections = field(default_factory=Corrections)


def check_pose(T: np.ndarray, what: str, corrected: Corrections | None = None, kind: str = ROTATIONS) -> np.ndarray:
    """A 4x4 rigid transform: finite, last row (0, 0, 0, 1), a rotation within ``ROTATION_TOLERANCE``
    (``parksim.geometry.nearest_rotation``), which is projected to the nearest proper rotation.

    Args:
        T: the 4x4 transform as read.
        what: names it in the error and in ``corrected``.
        corrected: counts the correction under ``kind`` (None: not counted).
        kind: the ``Corrections`` kind.

    Returns:
        ``T`` as float64 with its rotation projected; ``T`` itself when it is exact (float64 round-off).
    """
    from ..geometry import nearest_rotation

    T = np.asarray(T, np.float64)
    if T.shape != (4, 4) or not np.isfinite(T).all():
        raise RecordingError(f"{what}: expected a finite 4x4 transform")
    if np.abs(T[3] - [0.0, 0.0, 0.0, 1.0]).max() > 0:
        raise RecordingError(f"{what}: the last row of a rigid transform must be 0 0 0 1, got {T[3].tolist()}")
    try:
        R, correction = nearest_rotation(T[:3, :3])
    except ValueError as e:
        raise RecordingError(f"{what}: {e}") from None
    if correction == 0:
        return T
    if corrected is not None:
        corrected.add(kind, correction, what)
    T = T.copy()
    T[:3, :3] = R
    return T


def _strict_error(d: Dropped) -> RecordingError:
    """The one-line refusal of a strict import for the image defect ``d``: its file, camera and frame."""
    at = ", ".join(f"{key} {value!r}" for key, value in (("camera", d.camera), ("frame", d.frame)) if value is not None)
    return RecordingError(f"--strict: {d.detail or d.reason}" + (f" ({at})" if at else ""))


def _dropped(defect: ImageDefect, camera: str, frame: int, timestamp: float, strict: bool) -> Dropped:
    """The ``Dropped`` of an image ``defect`` at (``frame``, ``camera``); with ``strict`` its refusal is raised.

    Raises:
        RecordingError: ``strict`` (``_strict_error``).
    """
    d = Dropped(defect.reason, camera, frame, timestamp, str(defect))
    if strict:
        raise _strict_error(d) from None
    return d


def _without(rec: Recording, why: dict[int, Dropped]) -> Recording:
    """``rec`` less the frames that are keys of ``why``, whose values join its ``dropped``."""
    if not why:
        return rec
    keep = [i for i, f in enumerate(rec.frames) if f not in why]
    return dataclasses.replace(
        rec, frames=[rec.frames[i] for i in keep], timestamps=[rec.timestamps[i] for i in keep],
        poses=None if rec.poses is None else np.asarray(rec.poses)[keep],
        camera_poses=None if rec.camera_poses is None else [rec.camera_poses[i] for i in keep],
        split=None if rec.split is None else ([f for f in rec.split[0] if f not in why],
                                              [f for f in rec.split[1] if f not in why]),
        dropped=[*rec.dropped, *why.values()])


def _drop_defective(rec: Recording, strict: bool = False) -> Recording:
    """``rec`` without the frames that have an image with a defect (``CheckedSource.check`` against its camera's
    size), each dropped with its reason and the first camera at fault. With ``strict`` the first image defect, found
    here or dropped by the importer (a reason of ``IMAGE_DEFECTS``), is a ``RecordingError`` instead."""
    first = next((d for d in rec.dropped if d.reason in IMAGE_DEFECTS), None)
    if strict and first is not None:
        raise _strict_error(first)
    why: dict[int, Dropped] = {}
    for f, t in zip(rec.frames, rec.timestamps):
        for c in rec.rig.names:
            source = rec.images.get((f, c))
            if not isinstance(source, CheckedSource):
                continue
            model = rec.rig.cameras[c].model
            try:
                source.check((model.width, model.height))
            except ImageDefect as e:
                why[f] = _dropped(e, c, f, t, strict)
                break
    return _without(rec, why)


def _require_frames(rec: Recording) -> None:
    """Nothing left to import is a one-line ``RecordingError`` counting the drops by reason and naming the first
    file at fault."""
    if rec.frames:
        return
    first = next((d.detail for d in rec.dropped if d.detail), None)
    raise RecordingError(f"no frame is left to import; {len(rec.dropped)} dropped: "
                         + "; ".join(f"{count} {reason}" for reason, count in _reasons(rec.dropped).items())
                         + (f" (first: {first})" if first else ""))


def _check(rec: Recording) -> Recording:
    """Everything checkable before a file is written: sizes agree, poses are rigid, time increases. Returns ``rec``
    with every pose's rotation projected to a proper one (``check_pose``) and counted in a copy of ``corrected``."""
    _require_frames(rec)
    n = len(rec.frames)
    if len(rec.timestamps) != n or len(set(rec.frames)) != n:
        raise RecordingError(f"{n} frames, {len(rec.timestamps)} timestamps, {len(set(rec.frames))} distinct ids")
    stamps = np.asarray(rec.timestamps, np.float64)
    if not np.isfinite(stamps).all() or (np.diff(stamps) <= 0).any():
        i = int(np.argmax(~np.isfinite(stamps[1:]) | (np.diff(stamps) <= 0)))
        raise RecordingError(f"timestamps must be finite and strictly increasing: frame {rec.frames[i + 1]} at "
                             f"{stamps[i + 1]} follows {stamps[i]}")
    if rec.poses is None and rec.camera_poses is None:
        raise RecordingError("the recording has neither ego poses nor per-image camera poses")
    corrected = Corrections(copy.deepcopy(rec.corrected.kinds))
    poses, camera_poses = rec.poses, rec.camera_poses
    if rec.poses is not None:
        if len(rec.poses) != n:
            raise RecordingError(f"{len(rec.poses)} ego poses for {n} frames")
        poses = np.stack([check_pose(T, f"ego pose of frame {f}", corrected) for f, T in zip(rec.frames, rec.poses)])
    if rec.camera_poses is not None:
        if len(rec.camera_poses) != n:
            raise RecordingError(f"{len(rec.camera_poses)} sets of camera poses for {n} frames")
        camera_poses = []
        for f, by_camera in zip(rec.frames, rec.camera_poses):
            if sorted(by_camera) != sorted(rec.rig.names):
                raise RecordingError(f"frame {f} has camera poses for {sorted(by_camera)}; the rig has "
                                     f"{rec.rig.names}")
            camera_poses.append({c: check_pose(T, f"pose of camera {c!r} in frame {f}", corrected)
                                 for c, T in by_camera.items()})
    missing = [(f, c) for f in rec.frames for c in rec.rig.names if (f, c) not in rec.images]
    if missing:
        raise RecordingError(f"no image for {len(missing)} (frame, camera) pairs, e.g. {missing[0]}")
    return dataclasses.replace(rec, poses=poses, camera_poses=camera_poses, corrected=corrected)


def _image(rec: Recording, frame: int, camera: str) -> np.ndarray:
    """The decoded image, checked to be uint8 RGB at the camera's size.

    Raises:
        ImageDefect: it does not decode (raised by its source) or is of another size (``WRONG_SIZE``).
        RecordingError: it is not 8-bit RGB (the importer's fault).
    """
    img = np.asarray(rec.images[(frame, camera)]())
    model = rec.rig.cameras[camera].model
    if img.dtype != np.uint8 or img.ndim != 3 or img.shape[2] != 3:
        raise RecordingError(f"camera {camera!r} frame {frame}: expected an 8-bit RGB image, got {img.dtype} "
                             f"{img.shape}")
    if img.shape[:2] != (model.height, model.width):
        raise ImageDefect(WRONG_SIZE, f"image is {img.shape[1]}x{img.shape[0]} but the calibration says "
                                      f"{model.width}x{model.height}")
    return img


def downscaled_rig(rig: Rig, n: int) -> Rig:
    """``rig`` with its images ``n`` times smaller: every camera ``CameraModel.scaled(1 / n)`` (focal lengths over
    ``n``, principal point by the pixel-centre rule ``c' = (c + 0.5) / n - 0.5``), extrinsics and BEV kept.

    Args:
        rig: the recording's rig.
        n: the integer downscale factor (1: ``rig`` itself).

    Returns:
        The rig of the images as stored.

    Raises:
        RecordingError: ``n`` below 1, or a camera's width or height that ``n`` does not divide (its pixel grid
            would not be ``n`` times coarser, so no intrinsics would be exact).
    """
    from ..rig import Rig, RigCamera

    if n < 1:
        raise RecordingError(f"--downscale must be an integer >= 1, got {n}")
    if n == 1:
        return rig
    for c, cam in rig.cameras.items():
        if cam.model.width % n or cam.model.height % n:
            raise RecordingError(f"--downscale {n}: camera {c!r} is {cam.model.width}x{cam.model.height}, not a "
                                 f"multiple of {n} in both sides; choose a factor that divides them")
    return Rig({c: RigCamera(c, cam.model.scaled(1.0 / n), cam.T_vehicle_camera) for c, cam in rig.cameras.items()},
               rig.bev)


def _write_images(rec: Recording, rig: Rig, w: DatasetWriter, strict: bool, bar: Any) -> dict[int, Dropped]:
    """Decode, check and write every frame's images, resized to ``rig``'s cameras (``cv2.INTER_AREA``) when it is
    downscaled; a frame with an image that does not decode or is of another size is not written.

    Returns:
        The frames left out, with why (``_without``).

    Raises:
        RecordingError: with ``strict``, the first such image (``_strict_error``).
    """
    import cv2

    why: dict[int, Dropped] = {}
    for f, t in zip(rec.frames, rec.timestamps):
        images = {}
        for c in rec.rig.names:
            try:
                images[c] = _image(rec, f, c)
            except ImageDefect as e:
                why[f] = _dropped(e, c, f, t, strict)
                break
        bar.update(len(rec.rig.names))
        if f in why:
            continue
        for c, img in images.items():
            model = rig.cameras[c].model
            if img.shape[:2] != (model.height, model.width):
                img = cv2.resize(img, (model.width, model.height), interpolation=cv2.INTER_AREA)
            w.image(c, f, img)
    return why


def _path_length(rec: Recording) -> float:
    """Length of the ego path, or of the mean camera centre's path when there are per-image poses only."""
    if rec.poses is not None:
        centres = np.asarray(rec.poses)[:, :3, 3]
    else:
        assert rec.camera_poses is not None
        centres = np.stack([np.mean([T[:3, 3] for T in p.values()], axis=0) for p in rec.camera_poses])
    return float(np.linalg.norm(np.diff(centres, axis=0), axis=1).sum())


def _split(rec: Recording, test_every: int) -> tuple[list[int], list[int]]:
    if rec.split is not None:
        return rec.split
    test = [f for i, f in enumerate(rec.frames) if i % test_every == 0] if test_every > 0 else []
    return [f for f in rec.frames if f not in set(test)], test


def _reasons(dropped: list[Dropped]) -> dict[str, int]:
    """How many were dropped for each reason, in the order first seen."""
    reasons: dict[str, int] = {}
    for d in dropped:
        reasons[d.reason] = reasons.get(d.reason, 0) + 1
    return reasons


def report_of(rec: Recording, importer: str, out: Path, downscale: int = 1) -> dict[str, Any]:
    """The import report: frames per camera, dropped frames and why, time span, path length, what was corrected
    (``Corrections.kinds``), the downscale factor of the stored images, importer notes."""
    reasons = _reasons(rec.dropped)
    return {"importer": importer, "output": str(out), "frames": len(rec.frames), "downscale": downscale,
            "images_per_camera": {c: len(rec.frames) for c in rec.rig.names},
            "dropped": len(rec.dropped), "dropped_by_reason": reasons,
            "dropped_items": [{k: v for k, v in vars(d).items() if v is not None} for d in rec.dropped[:1000]],
            "time_span_s": float(rec.timestamps[-1] - rec.timestamps[0]) if rec.timestamps else 0.0,
            "path_length_m": round(_path_length(rec), 6),
            "poses": ("ego and per-image" if rec.poses is not None and rec.camera_poses is not None
                      else "ego" if rec.poses is not None else "per-image only"),
            "points": 0 if rec.points is None else len(rec.points[0]), "corrected": rec.corrected.kinds,
            **rec.notes}


def drop_summary(report: dict[str, Any]) -> str | None:
    """One line for a report's drops (``dropped_by_reason``), or None when nothing was dropped."""
    if not report["dropped"]:
        return None
    return (f"dropped {report['dropped']} (kept {report['frames']} frames): "
            + "; ".join(f"{count} {reason}" for reason, count in report["dropped_by_reason"].items()))


def write_recording(rec: Recording, out: str | Path, importer: str, test_every: int = 10,
                    overwrite: bool = False, progress: bool = True, *, strict: bool = False,
                    downscale: int = 1) -> dict[str, Any]:
    """Check ``rec`` and write it as a dataset at ``out`` (all or nothing); returns the import report.

    A frame with an image that is absent, cut short, unreadable or of another size than its camera's is dropped
    with the reason (``IMAGE_DEFECTS``; checked from the files before writing, and again as each image decodes).

    Args:
        rec: the recording (``Importer.load``).
        out: the dataset folder.
        importer: the importer's name, for ``meta.json`` and the report.
        test_every: every n-th frame is a test frame when ``rec`` has no split (0: none).
        overwrite: replace an existing ``out``.
        progress: show a progress bar on stderr.
        strict: refuse the recording at its first image defect instead of dropping the frame.
        downscale: store the images ``downscale`` times smaller (``cv2.INTER_AREA``) and the rig scaled to match
            (``downscaled_rig``).

    Returns:
        The import report (``report_of``), also saved as ``import_report.json``.

    Raises:
        RecordingError: the recording is unusable, no frame is left, or (``strict``) an image defect.
    """
    from tqdm import tqdm

    from ..data import DatasetWriter
    from ..data.layout import LAYOUT_VERSION
    from ..fileio import atomic_directory, write_json

    out = Path(out)
    rec = _check(_drop_defective(rec, strict))
    rig = downscaled_rig(rec.rig, downscale)
    with atomic_directory(out, overwrite=overwrite) as tmp:
        w = DatasetWriter(tmp)
        with tqdm(total=len(rec.frames) * len(rec.rig.names), desc=f"import {importer}", unit="img",
                  disable=not progress, file=sys.stderr, dynamic_ncols=True) as bar:
            rec = _without(rec, _write_images(rec, rig, w, strict, bar))
        _require_frames(rec)
        w.rig(rig)
        w.poses(rec.poses, rec.timestamps, rec.frames, rec.camera_poses)
        if rec.points is not None and len(rec.points[0]):
            xyz, rgb = (np.asarray(a) for a in rec.points)
            if not np.isfinite(xyz).all():
                raise RecordingError("the sparse point cloud has non-finite coordinates")
            w.points(xyz.astype(np.float32), rgb.astype(np.uint8), np.zeros_like(xyz, dtype=np.float32))
        w.split(*_split(rec, test_every))
        w.meta({"source": "import", "importer": importer, "layout_version": LAYOUT_VERSION,
                "frames": len(rec.frames), "cameras": rec.rig.names, "downscale": downscale,
                **{k: v for k, v in rec.notes.items() if isinstance(v, (str, int, float, bool)) or v is None}})
        report = report_of(rec, importer, out, downscale)
        write_json(tmp / REPORT_FILE, _finite(report))
    return report


def _finite(value: Any) -> Any:
    """JSON-safe: NaN/inf floats become None (json.dumps would write invalid NaN)."""
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, dict):
        return {k: _finite(v) for k, v in value.items()}
    if isinstance(value, list):
        return [_finite(v) for v in value]
    return value
