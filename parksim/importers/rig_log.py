"""``parksim import rig-log``: a vehicle's own recording (calibration, ego odometry, per-camera images or videos)
-> ``Recording``. See docs/import_rig_log.md for worked examples of every input.

- Calibration: ``rig_log_calib`` (OpenCV fisheye YAML, WoodScape JSON, OCamCalib, ParkSim rig; extrinsics file).
- Poses: T_world_vehicle against time, CSV or JSON with the columns of ``POSE_COLUMNS``: 6-DoF (x, y, z and a
  quaternion qw, qx, qy, qz) or 2D odometry (x, y, yaw; z = 0). Checked finite, unit quaternions (within
  ``QUATERNION_TOLERANCE``, then normalised) and strictly increasing timestamps.
- Images: per-camera folders, each file's time in its name (``TIME_RULE``); or videos sampled at ``--fps``,
  frame i at ``--video-start + i / (the video's frame rate)``.
- Frames: the first camera's images in time order; every other camera joins with its image nearest in time,
  within ``--sync-tolerance``; the frame's time is the mean of its images' times.
- Poses at those times: the logged pose at a logged time (within ``TIME_EPS``), else interpolated between the two
  logged poses around it when they are at most ``--max-gap`` apart (linear translation, slerp rotation). A frame
  outside the log or in a gap is dropped and counted.
- Frames whose images all share one time (within ``TIME_EPS``) give ego poses; otherwise every frame has its ego
  pose at the frame time and per-image camera poses, each image's ego pose at its own time through the rig.
"""

from __future__ import annotations

import csv
import functools
import json
import math
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal

import numpy as np

from .base import CheckedOptions, Importer
from .images import image_source
from .recording import UNREADABLE_IMAGE, Corrections, Dropped, ImageDefect, ImageSource, Recording, RecordingError
from .rig_log_calib import FORMATS, QUATERNION_TOLERANCE, CalibFormat, rotations, unit_quaternions

if TYPE_CHECKING:
    from ..rig import Rig

__all__ = ["RigLogImporter", "RigLogOptions", "POSE_COLUMNS", "TIME_RULE", "PoseLog", "read_poses", "file_time",
           "slerp"]

TIME_COLUMNS = {"timestamp": 1, "time": 1, "t": 1, "timestamp_s": 1, "timestamp_ms": 10**3, "timestamp_us": 10**6,
                "timestamp_ns": 10**9}
"""Accepted time columns and their ticks per second."""
POSITION_COLUMNS = (("x", "tx"), ("y", "ty"), ("z", "tz"))
QUATERNION_COLUMNS = ("qw", "qx", "qy", "qz")
YAW_COLUMNS = {"yaw": 1.0, "yaw_deg": math.pi / 180.0}
POSE_COLUMNS = ("time: one of timestamp, time, t, timestamp_s (seconds), timestamp_ms, timestamp_us, timestamp_ns; "
                "position: x (or tx), y (or ty), z (or tz); rotation: qw, qx, qy, qz (Hamilton, vehicle -> world) or "
                "yaw (rad) / yaw_deg with z optional (default 0); names case-insensitive, other columns ignored")
TIME_RULE = ("the last number in the file name is the time: with a decimal point, seconds; an integer by its digit "
             "count, <=10 seconds, 11-13 milliseconds, 14-16 microseconds, 17-19 nanoseconds (or --time-unit)")
UNIT_TICKS = {"s": 1, "ms": 10**3, "us": 10**6, "ns": 10**9}
TimeUnit = Literal["auto", "s", "ms", "us", "ns"]
"""``auto`` (``TIME_RULE``) or a key of ``UNIT_TICKS``."""
TIME_EPS = 1e-6
"""Seconds within which two times are the same (a logged pose is used as is; a frame is synchronised)."""
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".webp")
NUMBER = re.compile(r"\d+(?:\.\d+)?")

def _camera_value(text: str) -> tuple[str, str]:
    """``CAM=VALUE`` -> (camera, value)."""
    camera, sep, value = text.partition("=")
    if not sep or not camera or not value:
        raise RecordingError(f"--images: expected CAM=DIR, got {text!r}")
    return camera, value


@dataclass(frozen=True, kw_only=True)
class RigLogOptions(CheckedOptions):
    """Options of ``parksim import rig-log`` (keyword arguments, in the order ``--help`` lists them)."""

    calib: Path = field(metadata={
        "help": "calibration file, or a folder with one file per camera named by the camera (front.yaml, "
                "rear.json, left.txt...) and extrinsics.json/yaml when the format has none, or a SensorsCalibration "
                "surround-view folder (intrinsic/, extrinsic/, avm.json)", "metavar": "FILE|DIR"})
    calib_format: CalibFormat | None = field(default=None, metadata={
        "help": "calibration format (default: from each file's content): "
                + "; ".join(f"{k}: {v}" for k, v in FORMATS.items())})
    extrinsics: Path | None = field(default=None, metadata={
        "help": "T_vehicle_camera per camera (JSON/YAML: cameras: {name: {T_vehicle_camera: 4x4} or {x, y, z, qw, "
                "qx, qy, qz}}, optional bev) for OpenCV YAML and OCamCalib calibrations", "metavar": "FILE"})
    max_fov: float | None = field(default=None, metadata={
        "help": "lens field of view (the files do not state it; default: 190 for OpenCV and WoodScape, 360 for "
                "OCamCalib, i.e. up to the image corners)", "metavar": "DEG", "low": 0, "open_low": True,
        "high": 360})
    poses: Path = field(metadata={
        "help": "ego poses T_world_vehicle, .csv (header row; comma- or whitespace-separated) or .json (a list of "
                "objects, or {\"poses\": [...]}); columns: " + POSE_COLUMNS, "metavar": "FILE"})
    images: tuple[str, ...] = field(default=(), metadata={
        "help": "one image folder per camera as CAM=DIR, or one DIR holding a sub-folder per camera; " + TIME_RULE,
        "metavar": "[CAM=]DIR", "nargs": "+"})
    video: dict[str, Path] = field(default_factory=dict, metadata={
        "help": "one video per camera (anything cv2.VideoCapture reads); frame i is at --video-start + i / the "
                "video's frame rate", "metavar": "CAM=FILE"})
    video_start: dict[str, float] = field(default_factory=dict, metadata={
        "help": "time of a video's first frame (default 0)", "metavar": "CAM=SECONDS"})
    fps: float | None = field(default=None, metadata={
        "help": "sample videos at this rate: the frame nearest each multiple of 1/HZ (default: every frame)",
        "metavar": "HZ", "low": 0, "open_low": True})
    time_unit: TimeUnit = field(default="auto", metadata={
        "help": "unit of the numbers in image file names (auto: " + TIME_RULE + ")"})
    sync_tolerance: float = field(default=0.02, metadata={
        "help": "largest time between the first camera's image and another camera's image of one frame",
        "metavar": "S", "low": 0})
    max_gap: float = field(default=0.2, metadata={
        "help": "largest time between the two logged poses a pose is interpolated between", "metavar": "S",
        "low": 0, "open_low": True})

    def __post_init__(self) -> None:
        super().__post_init__()
        if not self.images and not self.video:
            raise ValueError("give the images: --images (folders) or --video (one per camera)")


# --- poses ----------------------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class PoseLog:
    """Logged ego poses: times (s, increasing), translations ``[N, 3]``, unit quaternions ``[N, 4]`` (w, x, y, z)."""

    path: Path
    times: np.ndarray
    translations: np.ndarray
    quaternions: np.ndarray
    kind: str

    def at(self, t: np.ndarray, max_gap: float) -> tuple[np.ndarray, list[str | None]]:
        """T_world_vehicle ``[M, 4, 4]`` at times ``t``, and per time None or why it has no pose (then NaN)."""
        t = np.asarray(t, np.float64)
        n = len(self.times)
        right = np.minimum(np.searchsorted(self.times, t), n - 1)
        left = np.maximum(right - 1, 0)
        nearest = np.where(np.abs(self.times[left] - t) <= np.abs(self.times[right] - t), left, right)
        logged = np.abs(self.times[nearest] - t) <= TIME_EPS
        outside = ~logged & ((t < self.times[0]) | (t > self.times[-1]))
        j = np.clip(np.searchsorted(self.times, t, side="right") - 1, 0, max(n - 2, 0))
        k = np.minimum(j + 1, n - 1)
        gap = self.times[k] - self.times[j]
        in_gap = ~logged & ~outside & (gap > max_gap)
        w = np.where(gap > 0, (t - self.times[j]) / np.where(gap > 0, gap, 1.0), 0.0)
        q = slerp(self.quaternions[j], self.quaternions[k], w)
        xyz = self.translations[j] + w[:, None] * (self.translations[k] - self.translations[j])
        q = np.where(logged[:, None], self.quaternions[nearest], q)
        xyz = np.where(logged[:, None], self.translations[nearest], xyz)
        T = np.tile(np.eye(4), (len(t), 1, 1))
        T[:, :3, :3], T[:, :3, 3] = rotations(q), xyz
        T[outside | in_gap] = np.nan
        why = [("outside the pose log" if o else f"in a pose-log gap longer than --max-gap {max_gap:g} s" if g
                else None) for o, g in zip(outside.tolist(), in_gap.tolist())]
        return T, why


def slerp(q0: np.ndarray, q1: np.ndarray, w: np.ndarray) -> np.ndarray:
    """Spherical linear interpolation between unit quaternions ``[M, 4]`` at weights ``w [M]``, shortest arc."""
    d = (q0 * q1).sum(-1)
    q1 = np.where(d[:, None] < 0, -q1, q1)
    theta = np.arccos(np.clip(np.abs(d), 0.0, 1.0))
    s = np.sin(theta)
    small = s < 1e-12
    safe = np.where(small, 1.0, s)
    a = np.where(small, 1.0 - w, np.sin((1.0 - w) * theta) / safe)
    b = np.where(small, w, np.sin(w * theta) / safe)
    q = a[:, None] * q0 + b[:, None] * q1
    return q / np.linalg.norm(q, axis=1, keepdims=True)


def _table(path: Path) -> tuple[list[str], list[list[Any]], list[str]]:
    """Column names (lower case), rows of values and a label per row (``FILE line N`` / ``FILE poses[i]``)."""
    try:
        text = path.read_text()
    except FileNotFoundError:
        raise RecordingError(f"--poses {path}: file not found") from None
    except UnicodeDecodeError:
        raise RecordingError(f"--poses {path}: not a text file") from None
    if path.suffix.lower() == ".json":
        try:
            doc = json.loads(text)
        except json.JSONDecodeError as e:
            raise RecordingError(f"{path}: not valid JSON: {e}") from None
        entries = doc.get("poses") if isinstance(doc, dict) else doc
        if not isinstance(entries, list) or not entries or not all(isinstance(e, dict) for e in entries):
            raise RecordingError(f"{path}: expected a non-empty list of objects, or {{\"poses\": [...]}}")
        names = [str(k).lower() for k in entries[0]]
        rows, labels = [], []
        for i, entry in enumerate(entries):
            row = {str(k).lower(): v for k, v in entry.items()}
            missing = [n for n in names if n not in row]
            if missing:
                raise RecordingError(f"{path} poses[{i}]: no {missing[0]!r} (poses[0] has it)")
            rows.append([row[n] for n in names])
            labels.append(f"{path} poses[{i}]")
        return names, rows, labels
    lines = [(i + 1, line) for i, line in enumerate(text.splitlines()) if line.strip()]
    if not lines:
        raise RecordingError(f"{path}: empty pose log")
    header = lines[0][1].strip().lstrip("#")
    comma = "," in header

    def split(line: str) -> list[str]:
        return [v.strip() for v in next(csv.reader([line]))] if comma else line.split()

    names = [n.lower() for n in split(header)]
    rows, labels = [], []
    for number, line in lines[1:]:
        if line.lstrip().startswith("#"):
            continue
        values = split(line)
        if len(values) != len(names):
            raise RecordingError(f"{path} line {number}: {len(values)} values for {len(names)} columns")
        rows.append(values)
        labels.append(f"{path} line {number}")
    if not rows:
        raise RecordingError(f"{path}: no pose rows after the header")
    return names, rows, labels


def _seconds(value: Any, ticks: int, where: str) -> float:
    """A time value in seconds; integer ticks are divided exactly (nanosecond stamps exceed float precision)."""
    text = str(value).strip()
    try:
        return int(text) / ticks if re.fullmatch(r"[+-]?\d+", text) else float(text) / ticks
    except ValueError:
        raise RecordingError(f"{where}: time {value!r} is not a number") from None


def _column(names: list[str], choices: tuple[str, ...] | dict[str, Any], path: Path, what: str) -> str | None:
    """The one column of ``choices`` present in ``names``, or None."""
    found = [c for c in choices if c in names]
    if len(found) > 1:
        raise RecordingError(f"{path}: several {what} columns {found}; keep one")
    return found[0] if found else None


def _required(names: list[str], choices: tuple[str, ...] | dict[str, Any], path: Path, what: str) -> str:
    """The one column of ``choices`` present in ``names``; its absence is an error listing ``choices``."""
    found = _column(names, choices, path, what)
    if found is None:
        raise RecordingError(f"{path}: no {what} column (accepted: {', '.join(choices)})")
    return found


def _rotation_columns(names: list[str], path: Path) -> list[str]:
    """qw, qx, qy, qz, or the one yaw column."""
    has_q = [c in names for c in QUATERNION_COLUMNS]
    yaw = _column(names, YAW_COLUMNS, path, "yaw")
    if any(has_q) and yaw is not None:
        raise RecordingError(f"{path}: has both a quaternion and {yaw!r}; give one rotation")
    if any(has_q) and not all(has_q):
        raise RecordingError(f"{path}: a quaternion needs all of qw, qx, qy, qz columns")
    if any(has_q):
        return list(QUATERNION_COLUMNS)
    if yaw is None:
        raise RecordingError(f"{path}: no rotation columns (qw, qx, qy, qz, or yaw / yaw_deg)")
    return [yaw]


def read_poses(path: Path, corrected: Corrections | None = None) -> PoseLog:
    """Read and check a pose log (see ``POSE_COLUMNS``); errors name the file and row; quaternions normalised are
    counted in ``corrected``."""
    names, rows, labels = _table(path)
    tcol = _required(names, tuple(TIME_COLUMNS), path, "time")
    rotation = _rotation_columns(names, path)
    six_dof = len(rotation) == 4
    position = [_required(names, c, path, c[0]) for c in POSITION_COLUMNS[:2]]
    z = (_required if six_dof else _column)(names, POSITION_COLUMNS[2], path, "z")
    position += [z] if z else []
    columns = position + rotation
    times = np.array([_seconds(r[names.index(tcol)], TIME_COLUMNS[tcol], where) for r, where in zip(rows, labels)])
    values = np.empty((len(rows), len(columns)))
    for i, (r, where) in enumerate(zip(rows, labels)):
        for j, c in enumerate(columns):
            try:
                values[i, j] = float(r[names.index(c)])
            except (TypeError, ValueError):
                raise RecordingError(f"{where}: {c} = {r[names.index(c)]!r} is not a number") from None
            if not math.isfinite(values[i, j]):
                raise RecordingError(f"{where}: {c} is not finite ({values[i, j]})")
        if not math.isfinite(times[i]):
            raise RecordingError(f"{where}: {tcol} is not finite ({times[i]})")
        if i and not times[i] > times[i - 1]:
            raise RecordingError(f"{where}: {tcol} {float(times[i])!r} does not follow {float(times[i - 1])!r}; "
                                 "timestamps must increase strictly")
    xyz = np.zeros((len(rows), 3))
    xyz[:, :len(position)] = values[:, :len(position)]
    if six_dof:
        return PoseLog(path, times, xyz, unit_quaternions(values[:, 3:], labels, corrected),
                       "6-DoF (x, y, z, qw, qx, qy, qz)")
    half = 0.5 * values[:, -1] * YAW_COLUMNS[rotation[0]]
    q = np.stack([np.cos(half), np.zeros_like(half), np.zeros_like(half), np.sin(half)], 1)
    return PoseLog(path, times, xyz, q, f"2D odometry (x, y, {rotation[0]}{', z' if z else '; z = 0'})")


# --- images and videos ----------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Shot:
    """One image of one camera: its time (s), how to decode it, and what to call it in messages."""

    time: float
    source: ImageSource
    label: str


def file_time(path: Path, unit: str = "auto") -> tuple[float, str]:
    """The time (s) in an image's file name and the unit read (see ``TIME_RULE``)."""
    numbers = NUMBER.findall(path.stem)
    if not numbers:
        raise RecordingError(f"{path}: no timestamp in the file name ({TIME_RULE})")
    text = numbers[-1]
    if unit == "auto":
        digits = len(text)
        unit = "s" if "." in text or digits <= 10 else "ms" if digits <= 13 else "us" if digits <= 16 else \
            "ns" if digits <= 19 else ""
        if not unit:
            raise RecordingError(f"{path}: {digits}-digit time in the file name; {TIME_RULE}")
    return _seconds(text, UNIT_TICKS[unit], str(path)), unit


def _image_folder(camera: str, folder: Path, unit: str) -> tuple[list[Shot], set[str]]:
    """A camera's images in time order, and the time units read. Their files are checked when the dataset is
    written (``images.FileImage.check``): an absent (a dangling link), cut short, unreadable or wrong-size image
    drops its frame."""
    if not folder.is_dir():
        raise RecordingError(f"--images {camera}={folder}: not a folder")
    files = sorted(p for p in folder.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)
    if not files:
        raise RecordingError(f"--images {camera}={folder}: no image ({', '.join(IMAGE_SUFFIXES)}) in the folder")
    shots, units = [], set()
    for p in files:
        t, u = file_time(p, unit)
        shots.append(Shot(t, image_source(p), str(p)))
        units.add(u)
    shots.sort(key=lambda s: s.time)
    for a, b in zip(shots, shots[1:]):
        if b.time == a.time:
            raise RecordingError(f"{b.label}: same time as {a.label} ({a.time!r} s)")
    return shots, units


class _Video:
    """Decodes one video's frames asked in increasing order in a single pass (reopened if asked backwards)."""

    def __init__(self, path: Path, last: int) -> None:
        self.path, self.last, self.position = path, last, 0
        self.capture: Any = None

    def frame(self, index: int) -> np.ndarray:
        import cv2

        if self.capture is None or index < self.position:
            self.capture, self.position = cv2.VideoCapture(str(self.path)), 0
        while self.position < index and self.capture.grab():
            self.position += 1
        ok, img = self.capture.read()
        self.position += 1
        if not ok or self.position != index + 1:
            raise ImageDefect(UNREADABLE_IMAGE, f"{self.path}: cannot decode frame {index}")
        if index == self.last:
            self.capture.release()
            self.capture = None
        return cv2.cvtColor(img, cv2.COLOR_BGR2RGB)


def _video(camera: str, path: Path, start: float, fps: float | None, size: tuple[int, int]
           ) -> tuple[list[Shot], dict[str, Any]]:
    """A video's sampled frames at ``start + i / rate`` and what the report says of it; checks it decodes."""
    import cv2

    capture = cv2.VideoCapture(str(path))
    if not path.is_file() or not capture.isOpened():
        raise RecordingError(f"--video {camera}={path}: cannot open the video (missing, unreadable or unsupported)")
    rate = float(capture.get(cv2.CAP_PROP_FPS))
    found = (int(capture.get(cv2.CAP_PROP_FRAME_WIDTH)), int(capture.get(cv2.CAP_PROP_FRAME_HEIGHT)))
    code = int(capture.get(cv2.CAP_PROP_FOURCC))
    count = 0
    while capture.grab():   # counts the frames that decode (the container's count can be wrong)
        count += 1
    capture.release()
    if count == 0:
        raise RecordingError(f"--video {camera}={path}: no frame decodes")
    if not (math.isfinite(rate) and rate > 0):
        raise RecordingError(f"--video {camera}={path}: the video states no frame rate ({rate})")
    if found != size:
        raise RecordingError(f"--video {camera}={path}: video is {found[0]}x{found[1]} but camera {camera!r} is "
                             f"calibrated at {size[0]}x{size[1]}")
    if fps is not None and fps > rate * (1 + 1e-9):
        raise RecordingError(f"--fps {fps:g} exceeds the frame rate of {path} ({rate:g})")
    step = 1.0 if fps is None else rate / fps
    indices = sorted({int(math.floor(k * step + 0.5)) for k in range(int(count / step) + 2)} & set(range(count)))
    video = _Video(path, indices[-1])
    shots = [Shot(start + i / rate, functools.partial(video.frame, i), f"{path} frame {i}") for i in indices]
    fourcc = "".join(chr((code >> 8 * k) & 0xFF) for k in range(4)).strip("\x00") or "unknown"
    return shots, {"video": str(path), "fourcc": fourcc, "frame_rate": rate, "frames": count,
                   "sampled": len(shots), "start_s": start}


def _sources(options: RigLogOptions, rig: Rig) -> tuple[dict[str, list[Shot]], dict[str, Any]]:
    """Every camera's shots in time order (from --images or --video) and notes on where they came from."""
    folders: dict[str, Path] = {}
    if options.images:
        plain = [v for v in options.images if "=" not in v]
        if plain and len(options.images) > 1:
            raise RecordingError(f"--images: give one ROOT folder or CAM=DIR per camera, not both ({plain[0]!r})")
        if plain:
            root = Path(plain[0])
            if not root.is_dir():
                raise RecordingError(f"--images {root}: not a folder")
            folders = {p.name: p for p in sorted(root.iterdir()) if p.is_dir()}
        else:
            folders = {c: Path(d) for c, d in (_camera_value(v) for v in options.images)}
    videos, starts = dict(options.video), dict(options.video_start)
    given = list(folders) + list(videos)
    for c in given + list(starts):
        if c not in rig.cameras:
            raise RecordingError(f"images or video for camera {c!r}, which --calib does not calibrate "
                                 f"(cameras: {', '.join(rig.names)})")
    for c in rig.names:
        if given.count(c) != 1:
            raise RecordingError(f"camera {c!r}: give exactly one image folder or video (--images / --video), got "
                                 f"{given.count(c)}")
        if c in starts and c not in videos:
            raise RecordingError(f"--video-start {c}: camera {c!r} has no --video")
    shots, notes, units = {}, {}, set()
    for c in rig.names:
        size = (rig.cameras[c].model.width, rig.cameras[c].model.height)
        if c in folders:
            shots[c], found = _image_folder(c, folders[c], options.time_unit)
            units |= found
            notes[c] = {"images": str(folders[c]), "count": len(shots[c])}
        else:
            shots[c], notes[c] = _video(c, videos[c], starts.get(c, 0.0), options.fps, size)
    if len(units) > 1:
        raise RecordingError(f"image file names read as {' and '.join(sorted(units))}: the digit counts differ; "
                             "give --time-unit")
    return shots, {"sources": notes, **({"time_unit": units.pop()} if units else {})}


# --- frames ---------------------------------------------------------------------------------------------------------
def _group(shots: dict[str, list[Shot]], names: list[str], tolerance: float
           ) -> tuple[list[tuple[int, dict[str, Shot]]], list[Dropped]]:
    """Frames (id = index of the first camera's image) with every camera's image nearest in time within
    ``tolerance``; the frames left out, and the images no first-camera image matched, each with why."""
    ref, others = names[0], names[1:]
    times = {c: np.array([s.time for s in shots[c]]) for c in others}
    used: dict[str, set[int]] = {c: set() for c in others}   # in a frame
    seen: dict[str, set[int]] = {c: set() for c in others}   # matched to a first-camera image, kept or not
    frames, dropped = [], []
    for i, shot in enumerate(shots[ref]):
        chosen = {c: int(np.argmin(np.abs(times[c] - shot.time))) for c in others}
        missing = [c for c, k in chosen.items() if abs(times[c][k] - shot.time) > tolerance or k in used[c]]
        for c, k in chosen.items():
            if c not in missing:
                seen[c].add(k)
        if missing:
            dropped.append(Dropped(f"no image from camera(s) {', '.join(missing)} within --sync-tolerance", ref,
                                   i, shot.time))
            continue
        for c, k in chosen.items():
            used[c].add(k)
        frames.append((i, {ref: shot, **{c: shots[c][k] for c, k in chosen.items()}}))
    for c in others:
        dropped += [Dropped(f"no image from camera {ref} within --sync-tolerance", c, None, s.time)
                    for k, s in enumerate(shots[c]) if k not in seen[c]]
    return frames, dropped


class RigLogImporter(Importer):
    """A vehicle's own recording: calibration, ego odometry, per-camera images or videos."""

    name = "rig-log"
    help = "a vehicle's rig log: calibration, ego odometry and per-camera images or videos"
    description = (
        "Read a rig log: --calib (OpenCV fisheye YAML, WoodScape JSON, OCamCalib calib_results.txt or JSON, or a "
        "ParkSim rig; a folder with one file per camera named by the camera, plus extrinsics.json/yaml for the formats "
        "without extrinsics; or a SensorsCalibration surround-view folder: intrinsic/, extrinsic/, avm.json), "
        "--poses (CSV or JSON, T_world_vehicle against time; " + POSE_COLUMNS + "), and images: "
        "--images with one folder per camera (" + TIME_RULE + ") or --video per camera sampled at --fps (frame i at "
        "--video-start + i / the video's frame rate). A frame is the first camera's image with every other camera's "
        "nearest image within --sync-tolerance, at the mean of their times; its pose is interpolated between logged "
        "poses at most --max-gap apart (linear translation, slerp rotation), else the frame is dropped and counted. "
        "Unsynchronised cameras get per-image poses at their own times. See docs/import_rig_log.md.")
    Options = RigLogOptions

    def load(self, options: RigLogOptions) -> Recording:
        """Read the calibration, pose log and images; group them into frames with poses (see the module's
        docstring)."""
        from .rig_log_calib import load_calibration

        corrected = Corrections()
        rig, notes = load_calibration(options.calib, options.calib_format, options.extrinsics, options.max_fov,
                                      corrected)
        log = read_poses(options.poses, corrected)
        shots, source_notes = _sources(options, rig)
        names = rig.names
        grouped, dropped = _group(shots, names, options.sync_tolerance)
        synchronised = all(max(s.time for s in m.values()) - min(s.time for s in m.values()) <= TIME_EPS
                           for _, m in grouped)
        frame_times = np.array([np.mean([s.time for s in m.values()]) for _, m in grouped])
        ego, why = log.at(frame_times, options.max_gap)
        why = [None if w is None else f"frame time {w}" for w in why]
        own = None
        if not synchronised:   # every image's ego pose at its own time
            own_T, own_why = log.at(np.array([m[c].time for _, m in grouped for c in names]), options.max_gap)
            own = own_T.reshape(len(grouped), len(names), 4, 4)
            for i in range(len(grouped)):
                mine = own_why[i * len(names):(i + 1) * len(names)]
                bad = [f"image of camera {c} {w}" for c, w in zip(names, mine) if w]
                why[i] = why[i] or (bad[0] if bad else None)
        keep = [i for i, w in enumerate(why) if w is None]
        dropped += [Dropped(w, None, grouped[i][0], float(frame_times[i])) for i, w in enumerate(why) if w]
        frames = [grouped[i][0] for i in keep]
        camera_poses = None
        if own is not None:
            rigT = {c: rig.cameras[c].T_vehicle_camera.numpy() for c in names}
            camera_poses = [{c: own[i, j] @ rigT[c] for j, c in enumerate(names)} for i in keep]
        notes.update({"poses_file": str(options.poses), "pose_log": log.kind, "pose_samples": len(log.times),
                      "pose_time_span_s": [float(log.times[0]), float(log.times[-1])], **source_notes,
                      "synchronised": synchronised,
                      "frame_poses": ("ego poses (every frame's images share one time)" if synchronised else
                                      "ego poses at the frame time (mean of its images' times) and per-image camera "
                                      "poses at each image's time"),
                      "interpolation": "linear translation, slerp rotation, between logged poses at most --max-gap "
                                       "apart",
                      "sync_tolerance_s": options.sync_tolerance, "max_gap_s": options.max_gap,
                      "quaternion_tolerance": QUATERNION_TOLERANCE})
        return Recording(rig=rig, frames=frames, timestamps=[float(frame_times[i]) for i in keep],
                         images={(grouped[i][0], c): grouped[i][1][c].source for i in keep for c in names},
                         poses=ego[keep], camera_poses=camera_poses, dropped=dropped, notes=notes,
                         corrected=corrected)
