"""Generate one synthetic scene: lay out the garage, drive the ego, ray-cast every frame, write the dataset."""

from __future__ import annotations

import dataclasses
import multiprocessing
import os
from collections.abc import Callable, Sequence
from concurrent.futures import ProcessPoolExecutor, as_completed
from pathlib import Path
from typing import Any

import cv2
import numba
import numpy as np
import torch

from ..data import DatasetWriter
from ..data.layout import LAYOUT_VERSION
from ..fileio import atomic_directory
from ..ipm import IPM
from .garage import Box, Garage
from .labels import frame_labels
from .layout import build_garage
from .points import sample_points
from .presets import ScenePreset
from .raycast import SUB, TILE, BoxSet, Hits, TiledRays, trace_camera
from .rig import avm_rig, ego_box
from .shading import Sensor, Shader
from .trajectory import drive

__all__ = ["SceneRenderer", "FrameRender", "generate", "write_frames", "usable_cores", "scene_map", "GENERATOR_VERSION"]

GENERATOR_VERSION = "1.1.0"
"""1.1: the worn and busy presets and their knobs (scene1-4 render as in 1.0), frames rendered by a process pool."""
_N_SUB = TILE * TILE * SUB * SUB


@dataclasses.dataclass
class FrameRender:
    """One camera at one frame: display image [H, W, 3] in [0, 1], depth along the ray (m, 0 = none),
    primitive id per pixel centre (``raycast`` ids) and the lens-valid mask."""

    image: np.ndarray
    depth: np.ndarray
    prim: np.ndarray
    valid: np.ndarray


class SceneRenderer:
    """A preset's garage, rig, rays and shading, ready to render any ego pose."""

    def __init__(self, preset: ScenePreset) -> None:
        self.preset = preset
        self.garage: Garage = build_garage(preset.layout)
        self.rig = avm_rig(preset.width, preset.height, preset.bev_px)
        self.materials = [b.material for b in self.garage.boxes] + ["ego"]
        colors = np.array([b.color for b in self.garage.boxes] + [(0.16, 0.17, 0.19)])
        self.rays = {n: TiledRays.build(c.model) for n, c in self.rig.cameras.items()}
        self.shader = Shader(self.garage, self.boxes_at(np.eye(4)), self.materials, colors, preset.layout.seed)
        self.sensor = Sensor(self.rig.names, {n: c.model for n, c in self.rig.cameras.items()}, preset.sensor,
                             preset.layout.seed)

    def boxes_at(self, pose: np.ndarray) -> BoxSet:
        """All boxes with the ego body (last) at ``pose``."""
        return BoxSet.from_boxes([*self.garage.boxes, ego_box(pose)])

    def camera_pose(self, pose: np.ndarray, name: str) -> np.ndarray:
        """T_world_camera of a camera at ego pose ``pose``."""
        return pose @ self.rig.cameras[name].T_vehicle_camera.numpy()

    def render(self, pose: np.ndarray, frame: int, cameras: list[str] | None = None,
               exposure_frame: int | None = None) -> dict[str, FrameRender]:
        """Ray-cast each camera at ego pose ``pose`` (T_world_vehicle) with 2x2 supersampling; ``frame`` seeds the
        sensor noise, ``exposure_frame`` (default ``frame``) picks the auto-exposure drift."""
        boxes = self.boxes_at(pose)
        out = {}
        for name in cameras or self.rig.names:
            rays = self.rays[name]
            hits = self._trace(pose, name, boxes)
            radiance = rays.untile_sub(self.shader.radiance(hits.columns(slice(0, _N_SUB)), boxes))
            valid = rays.untile(rays.valid[:, _N_SUB:])
            centre = hits.columns(slice(_N_SUB, None))
            image = self.sensor(name, frame, radiance, valid, exposure_frame)
            out[name] = FrameRender(image, rays.untile(centre.t).astype(np.float32) * valid,
                                    rays.untile(centre.prim), valid)
        return out


    def _trace(self, pose: np.ndarray, name: str, boxes: BoxSet) -> Hits:
        """All rays of camera ``name`` at ``pose``. With motion blur (``SensorOptions.motion_blur`` s of shutter),
        each of a pixel's 2x2 colour sub-samples is traced at its own instant of the shutter interval centred on
        the frame, the ego driving at the preset's speed along its heading (exact on straight stretches; the yaw
        rate is ignored); the centre rays (depth, ids) stay at the frame's pose."""
        rays = self.rays[name]
        travel = self.preset.sensor.motion_blur * self.preset.trajectory.speed
        if travel <= 0:
            return trace_camera(self.camera_pose(pose, name), rays, boxes, self.garage.height)
        hits = trace_camera(self.camera_pose(pose, name), rays, boxes, self.garage.height,
                            np.arange(_N_SUB, rays.rays.shape[1]))
        parts = [hits]
        k = SUB * SUB
        for j in range(k):
            moved = pose.copy()
            moved[:3, 3] += pose[:3, 0] * travel * ((j + 0.5) / k - 0.5)
            parts.insert(j, trace_camera(self.camera_pose(moved, name), rays, self.boxes_at(moved),
                                         self.garage.height, np.arange(j, _N_SUB, k)))
        order = np.argsort(np.concatenate([np.arange(j, _N_SUB, k) for j in range(k)] +
                                          [np.arange(_N_SUB, rays.rays.shape[1])]))
        join = lambda name: np.concatenate([getattr(h, name) for h in parts], 1)[:, order]  # noqa: E731
        return Hits(join("t"), join("prim"), join("face"), join("points"), join("dirs"))


def _box_dict(b: Box, kind: str) -> dict[str, Any]:
    return {"kind": kind, "center": [b.cx, b.cy], "size": [b.length, b.width], "z": [b.z0, b.z1], "yaw": b.yaw}


def scene_map(garage: Garage) -> dict[str, Any]:
    """World-frame map for the simulator: slots (with corners), marking points, obstacles, walls, lights."""
    slots = []
    for j, s in enumerate(garage.slots):
        a, b = garage.marks[s.p1], garage.marks[s.p2]
        d = np.array([np.cos(a.direction), np.sin(a.direction)]) * s.depth
        p1, p2 = np.array([a.x, a.y]), np.array([b.x, b.y])
        corners = [p1.tolist(), p2.tolist(), (p2 + d).tolist(), (p1 + d).tolist()]
        slots.append({"id": j, "p1": s.p1, "p2": s.p2, "type": s.kind, "angle": s.angle_deg, "depth": s.depth,
                      "occupied": s.occupied, "corners": corners})
    obstacles = [_box_dict(b, "pillar") for b in garage.boxes if b.material == "pillar"]
    obstacles += [_box_dict(b, "car") for b in garage.cars]
    obstacles += [_box_dict(b, "clutter") for b in garage.boxes if b.material == "clutter"]
    walls = [b for b in garage.boxes if b.material == "wall"]
    obstacles += [_box_dict(b, "wall") for b in walls]
    x0, x1, y0, y1 = 0.0, garage.length, garage.y_min, garage.y_max
    return {"frame": "world", "units": "m",
            "garage": {"x": [x0, x1], "y": [y0, y1], "height": garage.height, "lanes": garage.lanes},
            "marks": [{"id": i, "x": m.x, "y": m.y, "direction": m.direction, "shape": m.shape}
                      for i, m in enumerate(garage.marks)],
            "slots": slots, "obstacles": obstacles,
            "wall_segments": [[[x0, y0], [x1, y0]], [[x1, y0], [x1, y1]], [[x1, y1], [x0, y1]], [[x0, y1], [x0, y0]]],
            "lights": [{"x": L.x, "y": L.y, "z": garage.height, "intensity": L.intensity} for L in garage.lights]}


class _FrameWriter:
    """Renders frames of one preset and writes their images, depth, IPM BEV and labels into one dataset."""

    def __init__(self, preset: ScenePreset, root: Path) -> None:
        self.renderer = SceneRenderer(preset)
        self.writer = DatasetWriter(root)
        self.ipm = IPM(self.renderer.rig)
        self.weights = {n: w.numpy() for n, w in self.ipm.weights.items()}
        self.mask = self.ipm.mask.numpy()

    def write(self, pose: np.ndarray, frame: int, exposure_frame: int) -> None:
        """Render ``pose``, write everything under ``frame``'s file names."""
        renderer = self.renderer
        views = renderer.render(pose, frame, exposure_frame=exposure_frame)
        for name, v in views.items():
            self.writer.image(name, frame, v.image)
            self.writer.depth(name, frame, v.depth)
        self.writer.ipm(frame, self.ipm({n: torch.from_numpy(v.image) for n, v in views.items()}))
        origins = {n: renderer.camera_pose(pose, n)[:3, 3] for n in renderer.rig.names}
        self.writer.labels(frame, frame_labels(renderer.garage, pose, renderer.rig.bev, self.weights, self.mask,
                                               origins, renderer.boxes_at(pose)))


_FRAMES_PER_WORKER = 8
"""The default pool has at most one worker per 8 frames' worth of 640x480 views: a worker's start-up (imports, its
own renderer's textures) costs several such frames of CPU, and in serial mode the ray caster already uses every
core (docs/benchmarks.md#synth: 8 frames of scene1 ran 0.8x as fast on 2 workers as serially)."""

_WORKER: _FrameWriter | None = None
"""The pool worker's own renderer and writer, built once by ``_init_worker``."""


def _init_worker(preset: ScenePreset, root: Path) -> None:
    """Pool initializer: one thread per worker (the pool supplies the parallelism), then the renderer."""
    global _WORKER
    numba.set_num_threads(1)
    torch.set_num_threads(1)
    cv2.setNumThreads(1)
    _WORKER = _FrameWriter(preset, root)


def _work(pose: np.ndarray, frame: int, exposure_frame: int) -> None:
    assert _WORKER is not None, "pool worker used before its initializer ran"
    _WORKER.write(pose, frame, exposure_frame)


def usable_cores() -> int:
    """CPU cores this process may run on (its affinity mask where the OS has one)."""
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1


def write_frames(preset: ScenePreset, writer: DatasetWriter, poses: np.ndarray, frames: Sequence[int],
                 workers: int | None = None, progress: Callable[[int], Any] | None = None,
                 exposure_frames: Sequence[int] | None = None) -> None:
    """Render each pose, name the files by the matching frame id (also used for per-frame noise seeds), write
    images, depth, IPM BEV and labels; ``workers`` None = all usable cores (os.sched_getaffinity) but at most one
    per 8 frames' worth of 640x480 views (a small job such as ``tiny`` runs serially), 1 = serial in-process.

    ``exposure_frames``: the frame index whose auto-exposure drift each view uses (default: ``frames``), so an
    off-path view can share its recorded base frame's exposure. Frames are independent, so a process pool
    (spawned: numba and torch threads do not survive a fork) writes byte-identical files to a serial run.
    """
    frames = [int(f) for f in frames]
    exposure = frames if exposure_frames is None else [int(f) for f in exposure_frames]
    if not (len(poses) == len(frames) == len(exposure)):
        raise ValueError(f"write_frames: {len(poses)} poses, {len(frames)} frame ids and {len(exposure)} exposure "
                         "frames: expected one each per view")
    if workers is not None and workers < 1:
        raise ValueError(f"write_frames: workers must be at least 1, got {workers}")
    if workers is None:  # all cores, but no more workers than the work pays for
        work = len(frames) * preset.width * preset.height / (_FRAMES_PER_WORKER * 640 * 480)
        workers = min(usable_cores(), max(1, int(work)))
    n = min(workers, len(frames))
    jobs = list(zip(np.asarray(poses, np.float64), frames, exposure))
    if n <= 1:
        local = _FrameWriter(preset, writer.layout.root)
        for job in jobs:
            local.write(*job)
            if progress is not None:
                progress(1)
        return
    with ProcessPoolExecutor(n, mp_context=multiprocessing.get_context("spawn"), initializer=_init_worker,
                             initargs=(preset, writer.layout.root)) as pool:
        pending = [pool.submit(_work, *job) for job in jobs]
        try:
            for done in as_completed(pending):
                done.result()
                if progress is not None:
                    progress(1)
        except BaseException:
            pool.shutdown(wait=True, cancel_futures=True)
            raise


def generate(preset: ScenePreset, out: str | Path, overwrite: bool = False,
             progress: Callable[[int], Any] | None = None, workers: int | None = None) -> Path:
    """Write the scene of ``preset`` to ``out`` atomically; ``progress(n)`` is told of each finished frame;
    ``workers`` as in ``write_frames``.

    An existing ``out`` without ``overwrite`` fails before any work.
    """
    if Path(out).exists() and not overwrite:
        raise FileExistsError(f"{out} already exists (pass overwrite=True to replace it)")
    renderer = SceneRenderer(preset)
    poses, stamps = drive(renderer.garage, preset.trajectory, preset.frames)
    with atomic_directory(out, overwrite=overwrite) as tmp:
        writer = DatasetWriter(tmp)
        writer.rig(renderer.rig)
        writer.poses(poses, stamps)
        writer.map(scene_map(renderer.garage))
        write_frames(preset, writer, poses, range(len(poses)), workers, progress)
        xyz, rgb, normals = sample_points(renderer.garage, renderer.shader, renderer.boxes_at(poses[0]),
                                          renderer.materials, poses, preset.points, preset.layout.seed)
        writer.points(xyz, rgb, normals)
        frames = range(len(poses))
        writer.split([f for f in frames if f % 10], [f for f in frames if f % 10 == 0])
        writer.meta({"generator": "parksim synth", "generator_version": GENERATOR_VERSION,
                     "layout_version": LAYOUT_VERSION, "preset": preset.name, "seed": preset.layout.seed,
                     "frames": preset.frames, "width": preset.width, "height": preset.height,
                     "rate_hz": preset.trajectory.rate, "bev_px": preset.bev_px,
                     "sensor": dataclasses.asdict(preset.sensor), "layout": dataclasses.asdict(preset.layout),
                     "trajectory": dataclasses.asdict(preset.trajectory)})
    return Path(out)
