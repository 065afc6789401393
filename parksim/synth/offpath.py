"""Off-path test split: ground truth at ego poses the recording never visited, where planners drive.

Planners in closed loop leave the recorded path (1-2 m beside the lane, turned by tens of degrees, swinging into
slots); a reconstruction degrades most there and real logs have no ground truth there, but the ray caster does.
From each recorded test frame the ego is moved sideways (``LATERAL_M``, both sides, along the vehicle y axis) and
turned about its origin (``YAW_DEG``, both ways); and for free slots beside the path a forward-in parking
manoeuvre (a cubic Bezier from a recorded pose in the aisle to the slot centre) is sampled at
``MANOEUVRE_STEPS`` poses. Poses whose body (grown by ``CLEARANCE``) overlaps a pillar, car or wall, or leaves
the garage, are skipped and counted. ``write_offpath`` renders them into ``DATA/offpath/`` (a complete dataset,
every frame in test) with ``offpath.json`` describing each frame. See docs/offpath.md.
"""

from __future__ import annotations

import math
import shutil
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ..data import DatasetReader, DatasetWriter
from ..data.layout import DatasetError
from ..fileio import atomic_directory, write_json
from ..vehicle import Obstacles, VehicleParams, footprint
from .garage import LayoutParams
from .presets import ScenePreset
from .shading import SensorOptions
from .trajectory import TrajectoryParams

__all__ = ["OffpathSplit", "offpath_poses", "plan_offpath", "write_offpath", "read_offpath", "group_frames",
           "group_label", "LATERAL_M", "YAW_DEG", "MANOEUVRE_STEPS", "FRAME_BASE", "CLEARANCE", "OFFPATH_DIR",
           "OFFPATH_FILE"]

LATERAL_M = (0.25, 0.5, 1.0, 2.0)
"""Sideways offsets (m), applied to both sides of each recorded test pose."""
YAW_DEG = (10.0, 20.0)
"""Yaw offsets (deg) about the ego origin, applied both ways."""
MANOEUVRE_STEPS = 6
"""Poses sampled along each parking manoeuvre (after its start on the path, the last one in the slot)."""
NEAR_M = 5.0
"""A free slot gets a manoeuvre when its entrance lies within this distance (m) of a recorded ego position."""
MAX_TURN_DEG = 100.0
"""Largest heading change of a forward-in manoeuvre; slots that would need more (behind the driving direction)
are left out."""
CLEARANCE = 0.15
"""Body growth (m) for the collision test: the side cameras sit in the mirrors, 0.12 m outside the body."""
FRAME_BASE = 100_000
"""Off-path frame ids start here, above any recorded frame id (recorded datasets number frames from 0)."""
OFFPATH_DIR = "offpath"
"""Folder of the split inside the dataset."""
OFFPATH_FILE = "offpath.json"
"""Descriptors and skip counts inside the split."""
_STRAIGHT_IN = 3.0
"""Bezier handle (m) beyond the slot entrance at the end of a manoeuvre: the last metres run straight along the slot,
as drivers line up before they enter (a corner-cutting curve clips the neighbours' cars)."""
_VEHICLE = VehicleParams()


@dataclass
class OffpathSplit:
    """Off-path ego poses ``[N, 4, 4]`` (T_world_vehicle), one descriptor per pose, and skipped poses by reason.

    A descriptor: ``frame`` (new id), ``base`` (the recorded frame it comes from), ``kind`` (lateral | yaw |
    manoeuvre), ``offset`` (m sideways, deg of yaw; for manoeuvres the distance from the recorded path, m),
    ``unit``, ``slot`` (map slot id, manoeuvres only) and ``heading_change`` (deg from the start, manoeuvres only).
    """

    poses: np.ndarray
    descriptors: list[dict[str, Any]]
    skipped: dict[str, int] = field(default_factory=dict)


def _yaw(pose: np.ndarray) -> float:
    return math.atan2(pose[1, 0], pose[0, 0])


def _planar(x: float, y: float, yaw: float) -> np.ndarray:
    """T_world_vehicle on the floor at (x, y) heading ``yaw``."""
    T = np.eye(4)
    c, s = math.cos(yaw), math.sin(yaw)
    T[:2, :2] = [[c, -s], [s, c]]
    T[0, 3], T[1, 3] = x, y
    return T


def _local(dy: float, dyaw: float) -> np.ndarray:
    """Vehicle-frame motion: ``dy`` metres to the left, then a turn by ``dyaw`` rad about the ego origin."""
    return _planar(0.0, dy, dyaw)


class _Clearance:
    """Why a pose is not allowed (None when it is): outside the garage or the kind of obstacle its body hits."""

    def __init__(self, scene_map: Mapping[str, Any]) -> None:
        self.obstacles = Obstacles(scene_map["obstacles"])
        self.x = scene_map["garage"]["x"]
        self.y = scene_map["garage"]["y"]

    def reason(self, pose: np.ndarray) -> str | None:
        body = footprint((pose[0, 3], pose[1, 3], _yaw(pose)), _VEHICLE, CLEARANCE)
        inside = ((body[:, 0] >= self.x[0]) & (body[:, 0] <= self.x[1])
                  & (body[:, 1] >= self.y[0]) & (body[:, 1] <= self.y[1]))
        if not inside.all():
            return "outside"
        hits = np.flatnonzero(self.obstacles.hits(body))
        return self.obstacles.kinds[hits[0]] if len(hits) else None


def _path_distance(points: np.ndarray, path: np.ndarray) -> np.ndarray:
    """Distance (m) of each xy point [K, 2] to the polyline ``path`` [N, 2]."""
    if len(path) == 1:
        return np.linalg.norm(points - path[0], axis=1)
    a, b = path[:-1], path[1:]
    ab = b - a
    t = np.clip(np.einsum("kni,ni->kn", points[:, None] - a[None], ab) / np.maximum((ab * ab).sum(1), 1e-12), 0, 1)
    nearest = a[None] + t[..., None] * ab[None]
    return np.linalg.norm(points[:, None] - nearest, axis=2).min(1)


def _manoeuvre(slot: Mapping[str, Any], poses: np.ndarray) -> tuple[int, np.ndarray] | None:
    """Start index into ``poses`` and the ``MANOEUVRE_STEPS`` poses of a forward-in drive into ``slot``, or None
    when no recorded pose faces it.

    The end pose puts the body's centre on the slot's centre, heading into the slot along its separators. The
    start is the recorded pose from which a circular turn onto that end pose fits best (ahead of it by
    ``lateral * cot(turn / 2)``); the path between is a cubic Bezier tangent to both headings.
    """
    corners = np.asarray(slot["corners"], np.float64)
    entrance = (corners[0] + corners[1]) / 2
    into = corners[3] - corners[0]
    u = into / np.linalg.norm(into)
    x0, x1, _, _ = _VEHICLE.extent
    end = entrance + into / 2 - u * (x0 + x1) / 2          # rear-axle position with the body centred in the slot
    xy, yaw = poses[:, :2, 3], np.arctan2(poses[:, 1, 0], poses[:, 0, 0])
    h = np.stack([np.cos(yaw), np.sin(yaw)], 1)
    rel = end - xy
    along = (rel * h).sum(1)
    lateral = np.abs(h[:, 0] * rel[:, 1] - h[:, 1] * rel[:, 0])
    turn = np.arccos(np.clip(h @ u, -1.0, 1.0))
    ok = (along > 0) & (turn <= math.radians(MAX_TURN_DEG)) & (turn > 1e-3)
    if not ok.any():
        return None
    misfit = np.abs(along - lateral / np.tan(np.maximum(turn, 1e-3) / 2))
    i = int(np.flatnonzero(ok)[np.argmin(misfit[ok])])
    p0, p3 = xy[i], end
    reach = 0.4 * float(np.linalg.norm(p3 - p0))
    straight = float((end - entrance) @ u) + _STRAIGHT_IN   # the body is aligned with the slot at its entrance
    ctrl = np.stack([p0, p0 + reach * h[i], p3 - straight * u, p3])
    t = np.arange(1, MANOEUVRE_STEPS + 1, dtype=np.float64)[:, None] / MANOEUVRE_STEPS
    basis = np.concatenate([(1 - t) ** 3, 3 * t * (1 - t) ** 2, 3 * t ** 2 * (1 - t), t ** 3], 1)
    dbasis = np.concatenate([-3 * (1 - t) ** 2, 3 * (1 - t) ** 2 - 6 * t * (1 - t), 6 * t * (1 - t) - 3 * t ** 2,
                             3 * t ** 2], 1)
    pts, tangent = basis @ ctrl, dbasis @ ctrl
    out = np.stack([_planar(float(p[0]), float(p[1]), math.atan2(d[1], d[0])) for p, d in zip(pts, tangent)])
    return i, out


def offpath_poses(poses: np.ndarray, frames: Sequence[int], test: Sequence[int], scene_map: Mapping[str, Any],
                  lateral: Sequence[float] = LATERAL_M, yaw_deg: Sequence[float] = YAW_DEG) -> OffpathSplit:
    """Off-path poses around the recorded ``poses`` ([N, 4, 4] T_world_vehicle of ``frames``), float64.

    Lateral and yaw offsets are applied at every ``test`` frame; manoeuvres go into every free, non-parallel slot
    of ``scene_map`` (map.json) near the path. Poses that overlap an obstacle or leave the garage are counted in
    ``skipped`` by reason (``outside``, or the obstacle kind: pillar, car, wall); so are slots without a
    manoeuvre (``slot_far``: no recorded pose within ``NEAR_M``, ``slot_behind``: none facing it).
    """
    poses = np.asarray(poses, np.float64)
    index = {f: i for i, f in enumerate(frames)}
    clearance = _Clearance(scene_map)
    out: list[np.ndarray] = []
    descriptors: list[dict[str, Any]] = []
    skipped: dict[str, int] = {}

    def add(pose: np.ndarray, desc: dict[str, Any]) -> None:
        why = clearance.reason(pose)
        if why is not None:
            skipped[why] = skipped.get(why, 0) + 1
            return
        descriptors.append({"frame": FRAME_BASE + len(out), **desc})
        out.append(pose)

    for f in test:
        base = poses[index[f]]
        for d in lateral:
            for s in (1.0, -1.0):
                add(base @ _local(s * d, 0.0), {"base": int(f), "kind": "lateral", "offset": s * d, "unit": "m"})
        for a in yaw_deg:
            for s in (1.0, -1.0):
                add(base @ _local(0.0, math.radians(s * a)),
                    {"base": int(f), "kind": "yaw", "offset": s * a, "unit": "deg"})
    path = poses[:, :2, 3]
    for slot in scene_map["slots"]:
        if slot["occupied"] or slot["type"] == "parallel":
            continue
        if np.linalg.norm(path - np.mean(np.asarray(slot["corners"])[:2], axis=0), axis=1).min() > NEAR_M:
            skipped["slot_far"] = skipped.get("slot_far", 0) + 1
            continue
        found = _manoeuvre(slot, poses)
        if found is None:
            skipped["slot_behind"] = skipped.get("slot_behind", 0) + 1
            continue
        i, drive = found
        distance = _path_distance(drive[:, :2, 3], path)
        for pose, dist in zip(drive, distance):
            change = math.degrees(math.remainder(_yaw(pose) - _yaw(poses[i]), 2 * math.pi))
            add(pose, {"base": int(frames[i]), "kind": "manoeuvre", "offset": float(dist), "unit": "m",
                       "slot": int(slot["id"]), "heading_change": change})
    return OffpathSplit(np.stack(out) if out else np.zeros((0, 4, 4)), descriptors, skipped)


def plan_offpath(reader: DatasetReader) -> OffpathSplit:
    """The off-path poses of a dataset: ``offpath_poses`` around its recorded poses, test frames and map."""
    return offpath_poses(reader.poses.numpy(), reader.frames, reader.split["test"], reader.map)


def group_label(kind: str, offset: float | None) -> str:
    """Row name of a group: ``lateral ±0.5 m``, ``yaw ±10 deg``, ``manoeuvre``."""
    if offset is None:
        return "manoeuvre into slot"
    return f"{kind} ±{offset:g} {'m' if kind == 'lateral' else 'deg'}"


def group_frames(descriptors: Sequence[Mapping[str, Any]]) -> dict[str, dict[str, Any]]:
    """Frames grouped by kind and offset size (both signs together; all manoeuvres one group), in table order:
    ``{label: {"kind", "offset" (abs; None for manoeuvres), "frames": [...]}}``."""
    groups: dict[tuple[int, float], dict[str, Any]] = {}
    order = {"lateral": 0, "yaw": 1, "manoeuvre": 2}
    for d in descriptors:
        size = None if d["kind"] == "manoeuvre" else abs(float(d["offset"]))
        key = (order[d["kind"]], -1.0 if size is None else size)
        groups.setdefault(key, {"kind": d["kind"], "offset": size, "frames": []})["frames"].append(int(d["frame"]))
    return {group_label(g["kind"], g["offset"]): g for _, g in sorted(groups.items())}


def read_offpath(split_dir: str | Path) -> dict[str, Any]:
    """A written split's ``offpath.json``: ``frames`` (the descriptors), ``skipped`` and the offsets used."""
    import json

    path = Path(split_dir) / OFFPATH_FILE
    if not path.is_file():
        raise DatasetError(path, "file not found (write the split with `parksim offpath DATA`)")
    try:
        info = json.loads(path.read_text())
        if not isinstance(info["frames"], list) or not isinstance(info["skipped"], dict):
            raise TypeError("frames must be a list, skipped a mapping")
    except (json.JSONDecodeError, KeyError, TypeError) as e:
        raise DatasetError(path, f"not an off-path descriptor file: {e!r}") from None
    return dict(info)


def _preset(reader: DatasetReader) -> ScenePreset:
    """The ``ScenePreset`` recorded in a synthetic dataset's meta.json; ValueError for any other dataset."""
    meta, root = reader.meta, reader.layout.root
    if meta.get("split") == OFFPATH_DIR:
        raise ValueError(f"{root}: this is an off-path split already; give the dataset it was made from")
    if meta.get("generator") != "parksim synth":
        made = meta.get("generator", "no meta.json generator")
        raise ValueError(f"{root}: not a `parksim synth` dataset ({made}); an off-path split needs the synthetic "
                         "garage's ray caster for its ground truth")
    try:
        layout = dict(meta["layout"])
        layout["kinds"] = tuple(layout["kinds"])
        return ScenePreset(meta["preset"], LayoutParams(**layout), TrajectoryParams(**meta["trajectory"]),
                           frames=int(meta["frames"]), width=int(meta["width"]), height=int(meta["height"]),
                           bev_px=int(meta["bev_px"]), sensor=SensorOptions(**meta["sensor"]))
    except (KeyError, TypeError, ValueError) as e:
        raise DatasetError(reader.layout.meta, f"cannot rebuild the scene preset: {e!r}") from None


def _check_rebuild(reader: DatasetReader, preset: ScenePreset) -> None:
    """Fail unless the rebuilt scene reproduces the dataset: same map, and the first test frame's front image
    re-rendered within one 8-bit step (the generator may have changed since the dataset was made)."""
    import json

    from .generate import SceneRenderer, scene_map

    renderer = SceneRenderer(preset)
    rebuilt = json.loads(json.dumps(scene_map(renderer.garage)))
    if rebuilt != reader.map:
        raise ValueError(f"{reader.layout.map}: the garage rebuilt from meta.json differs from this map; "
                         "regenerate the dataset with this version of `parksim synth`")
    frame = (reader.split["test"] or reader.frames)[0]
    camera = renderer.rig.names[0]
    image = renderer.render(reader.pose(frame).numpy(), frame, [camera])[camera].image
    diff = float(np.abs(np.rint(np.clip(image, 0, 1) * 255) - reader.image(camera, frame).numpy() * 255).max())
    if diff > 1.0:
        raise ValueError(f"{reader.layout.image(camera, frame)}: re-rendering it from meta.json differs by "
                         f"{diff:.0f}/255; regenerate the dataset with this version of `parksim synth`")


def write_offpath(data_dir: str | Path, workers: int | None = None, progress: Callable[[int], Any] | None = None,
                  overwrite: bool = False) -> Path:
    """Write ``DATA/offpath/``: the off-path poses of a synthetic dataset, rendered as a complete dataset.

    Each view takes the exposure drift of its base (recorded) frame, so on- and off-path images differ only by
    geometry. All checks run before any rendering; the folder appears only when complete.
    """
    from .generate import write_frames

    reader = DatasetReader(data_dir)
    out = reader.layout.root / OFFPATH_DIR
    if out.exists() and not overwrite:
        raise FileExistsError(f"{out} already exists (pass --overwrite to replace it)")
    preset = _preset(reader)
    if not reader.split["test"]:
        raise ValueError(f"{reader.layout.split}: no test frames to offset")
    _check_rebuild(reader, preset)
    split = plan_offpath(reader)
    if not split.descriptors:
        raise ValueError(f"{data_dir}: every off-path pose overlaps an obstacle ({split.skipped})")
    ids = [d["frame"] for d in split.descriptors]
    bases = [d["base"] for d in split.descriptors]
    stamps = [reader.timestamps[reader.frames.index(b)] for b in bases]
    with atomic_directory(out, overwrite=overwrite) as tmp:
        writer = DatasetWriter(tmp)
        writer.rig(reader.rig)
        writer.poses(split.poses, stamps, frames=ids)
        shutil.copyfile(reader.layout.map, writer.layout.map)
        write_frames(preset, writer, split.poses, ids, workers=workers, progress=progress, exposure_frames=bases)
        writer.split([], ids)
        writer.meta({**reader.meta, "split": "offpath", "source": str(reader.layout.root.resolve()),
                     "frames": len(ids)})
        write_json(tmp / OFFPATH_FILE, {"lateral_m": list(LATERAL_M), "yaw_deg": list(YAW_DEG),
                                        "manoeuvre_steps": MANOEUVRE_STEPS, "clearance_m": CLEARANCE,
                                        "skipped": split.skipped, "frames": split.descriptors})
    return out

