"""What every importer returns (``Recording``) and the one writer that turns it into a dataset folder.

Importers only read and check their format; ``write_recording`` checks what all of them share (poses finite with
proper rotations, timestamps increasing, every image decoding to its camera's size), writes the dataset layout of
``parksim.data`` into a temp folder renamed at the end, and saves ``import_report.json``.
"""

from __future__ import annotations

import dataclasses
import math
import sys
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Protocol, runtime_checkable

import numpy as np

if TYPE_CHECKING:   # importers are imported to build `parksim import --help`: no torch at import time
    from ..rig import Rig

__all__ = ["ImageSource", "CheckedSource", "RecordingError", "Dropped", "Recording", "write_recording", "check_pose",
           "REPORT_FILE", "ROTATION_TOLERANCE"]

ImageSource = Callable[[], np.ndarray]
"""Returns one image as uint8 RGB ``[H, W, 3]``; called once, when the image is written."""


@runtime_checkable
class CheckedSource(Protocol):
    """An ``ImageSource`` that can tell, cheaply and before anything is written, why its image is unusable (a file
    cut short: ``parksim.importers.images.FileImage``); the frame is then dropped with that reason."""

    def __call__(self) -> np.ndarray: ...

    def defect(self) -> str | None: ...

REPORT_FILE = "import_report.json"
ROTATION_TOLERANCE = 1e-6
"""Largest deviation of ``R^T R`` from the identity (and of det R from 1) accepted in a pose."""


class RecordingError(ValueError):
    """The input recording is unusable; the one-line message names the file or option at fault."""


@dataclass
class Dropped:
    """One frame or image left out of the dataset, and why."""

    reason: str
    camera: str | None = None
    frame: int | None = None
    timestamp: float | None = None


@dataclass
class Recording:
    """A recording read by an importer: the rig, time-ordered frames, their poses and images.

    ``poses`` are ego poses T_world_vehicle ``[N, 4, 4]``; ``camera_poses`` a ``{camera: T_world_camera}`` per
    frame (what COLMAP and nerfstudio give). At least one of the two is set. ``images`` holds a source for every
    (frame, camera). ``notes`` are importer facts for the report (calibration format, codec, scale source...).
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


def check_pose(T: np.ndarray, what: str) -> None:
    """A 4x4 rigid transform: finite, last row (0, 0, 0, 1), proper rotation within ``ROTATION_TOLERANCE``."""
    T = np.asarray(T, np.float64)
    if T.shape != (4, 4) or not np.isfinite(T).all():
        raise RecordingError(f"{what}: expected a finite 4x4 transform")
    if np.abs(T[3] - [0.0, 0.0, 0.0, 1.0]).max() > 0:
        raise RecordingError(f"{what}: the last row of a rigid transform must be 0 0 0 1, got {T[3].tolist()}")
    R = T[:3, :3]
    err = max(float(np.abs(R.T @ R - np.eye(3)).max()), abs(float(np.linalg.det(R)) - 1.0))
    if err > ROTATION_TOLERANCE:
        raise RecordingError(f"{what}: not a proper rotation (|R^T R - I| or |det R - 1| = {err:.2g} > "
                             f"{ROTATION_TOLERANCE:g})")


def _drop_defective(rec: Recording) -> Recording:
    """``rec`` without the frames that have an image with a defect (``CheckedSource``), each dropped and counted
    with its reason; the first camera at fault is named."""
    why: dict[int, Dropped] = {}
    for f in rec.frames:
        for c in rec.rig.names:
            source = rec.images.get((f, c))
            reason = source.defect() if isinstance(source, CheckedSource) else None
            if reason is not None:
                why[f] = Dropped(reason, c, f)
                break
    if not why:
        return rec
    keep = [i for i, f in enumerate(rec.frames) if f not in why]
    frames = [rec.frames[i] for i in keep]
    return dataclasses.replace(
        rec, frames=frames, timestamps=[rec.timestamps[i] for i in keep],
        poses=None if rec.poses is None else np.asarray(rec.poses)[keep],
        camera_poses=None if rec.camera_poses is None else [rec.camera_poses[i] for i in keep],
        split=None if rec.split is None else ([f for f in rec.split[0] if f not in why],
                                              [f for f in rec.split[1] if f not in why]),
        dropped=[*rec.dropped, *why.values()])


def _check(rec: Recording) -> None:
    """Everything checkable before a file is written: sizes agree, poses are rigid, time increases."""
    n = len(rec.frames)
    if n == 0:
        reasons = _reasons(rec.dropped)
        raise RecordingError(f"no frame is left to import; {len(rec.dropped)} dropped: "
                             + "; ".join(f"{count} {reason}" for reason, count in reasons.items()))
    if len(rec.timestamps) != n or len(set(rec.frames)) != n:
        raise RecordingError(f"{n} frames, {len(rec.timestamps)} timestamps, {len(set(rec.frames))} distinct ids")
    stamps = np.asarray(rec.timestamps, np.float64)
    if not np.isfinite(stamps).all() or (np.diff(stamps) <= 0).any():
        i = int(np.argmax(~np.isfinite(stamps[1:]) | (np.diff(stamps) <= 0)))
        raise RecordingError(f"timestamps must be finite and strictly increasing: frame {rec.frames[i + 1]} at "
                             f"{stamps[i + 1]} follows {stamps[i]}")
    if rec.poses is None and rec.camera_poses is None:
        raise RecordingError("the recording has neither ego poses nor per-image camera poses")
    if rec.poses is not None:
        if len(rec.poses) != n:
            raise RecordingError(f"{len(rec.poses)} ego poses for {n} frames")
        for f, T in zip(rec.frames, rec.poses):
            check_pose(T, f"ego pose of frame {f}")
    if rec.camera_poses is not None:
        if len(rec.camera_poses) != n:
            raise RecordingError(f"{len(rec.camera_poses)} sets of camera poses for {n} frames")
        for f, poses in zip(rec.frames, rec.camera_poses):
            if sorted(poses) != sorted(rec.rig.names):
                raise RecordingError(f"frame {f} has camera poses for {sorted(poses)}; the rig has {rec.rig.names}")
            for c, T in poses.items():
                check_pose(T, f"pose of camera {c!r} in frame {f}")
    missing = [(f, c) for f in rec.frames for c in rec.rig.names if (f, c) not in rec.images]
    if missing:
        raise RecordingError(f"no image for {len(missing)} (frame, camera) pairs, e.g. {missing[0]}")


def _image(rec: Recording, frame: int, camera: str) -> np.ndarray:
    """The decoded image, checked to be uint8 RGB at the camera's size."""
    img = np.asarray(rec.images[(frame, camera)]())
    model = rec.rig.cameras[camera].model
    if img.dtype != np.uint8 or img.ndim != 3 or img.shape[2] != 3:
        raise RecordingError(f"camera {camera!r} frame {frame}: expected an 8-bit RGB image, got {img.dtype} "
                             f"{img.shape}")
    if img.shape[:2] != (model.height, model.width):
        raise RecordingError(f"camera {camera!r} frame {frame}: image is {img.shape[1]}x{img.shape[0]} but the "
                             f"calibration says {model.width}x{model.height}")
    return img


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


def report_of(rec: Recording, importer: str, out: Path) -> dict[str, Any]:
    """The import report: frames per camera, dropped frames and why, time span, path length, importer notes."""
    reasons = _reasons(rec.dropped)
    return {"importer": importer, "output": str(out), "frames": len(rec.frames),
            "images_per_camera": {c: len(rec.frames) for c in rec.rig.names},
            "dropped": len(rec.dropped), "dropped_by_reason": reasons,
            "dropped_items": [{k: v for k, v in vars(d).items() if v is not None} for d in rec.dropped[:1000]],
            "time_span_s": float(rec.timestamps[-1] - rec.timestamps[0]) if rec.timestamps else 0.0,
            "path_length_m": round(_path_length(rec), 6),
            "poses": ("ego and per-image" if rec.poses is not None and rec.camera_poses is not None
                      else "ego" if rec.poses is not None else "per-image only"),
            "points": 0 if rec.points is None else len(rec.points[0]), **rec.notes}


def write_recording(rec: Recording, out: str | Path, importer: str, test_every: int = 10,
                    overwrite: bool = False, progress: bool = True) -> dict[str, Any]:
    """Check ``rec`` and write it as a dataset at ``out`` (all or nothing); returns the import report.

    Frames with an image cut short (a ``CheckedSource`` with a defect) are dropped and counted first."""
    from tqdm import tqdm

    from ..data import DatasetWriter
    from ..data.layout import LAYOUT_VERSION
    from ..fileio import atomic_directory, write_json

    out = Path(out)
    rec = _drop_defective(rec)
    _check(rec)
    report = report_of(rec, importer, out)
    train, test = _split(rec, test_every)
    with atomic_directory(out, overwrite=overwrite) as tmp:
        w = DatasetWriter(tmp)
        w.rig(rec.rig)
        w.poses(rec.poses, rec.timestamps, rec.frames, rec.camera_poses)
        with tqdm(total=len(rec.frames) * len(rec.rig.names), desc=f"import {importer}", unit="img",
                  disable=not progress, file=sys.stderr, dynamic_ncols=True) as bar:
            for f in rec.frames:
                for c in rec.rig.names:
                    w.image(c, f, _image(rec, f, c))
                    bar.update()
        if rec.points is not None and len(rec.points[0]):
            xyz, rgb = (np.asarray(a) for a in rec.points)
            if not np.isfinite(xyz).all():
                raise RecordingError("the sparse point cloud has non-finite coordinates")
            w.points(xyz.astype(np.float32), rgb.astype(np.uint8), np.zeros_like(xyz, dtype=np.float32))
        w.split(train, test)
        w.meta({"source": "import", "importer": importer, "layout_version": LAYOUT_VERSION,
                "frames": len(rec.frames), "cameras": rec.rig.names,
                **{k: v for k, v in rec.notes.items() if isinstance(v, (str, int, float, bool)) or v is None}})
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
