"""Render frames for a planner: in-process from a bundle (``LocalSim``) or from ``parksim serve`` (``RemoteSim``).

Both return the same ``Frame`` (uint8 RGB views, optional float32 depth, optional uint8 BEV) for
the same request, bit for bit: the server renders with ``LocalSim`` and ships the arrays in an
``.npz`` whose layout ``NPZ_LAYOUT`` is defined here once (``encode_npz`` / ``decode_npz``).
"""

from __future__ import annotations

import io
import json
import math
import threading
import time
from collections import OrderedDict
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

__all__ = ["Frame", "RequestError", "LocalSim", "RemoteSim", "encode_npz", "decode_npz", "pose_text", "NPZ_LAYOUT"]

NPZ_LAYOUT = """\
images/<camera>  uint8 [H, W, 3]     one per camera asked for
depth/<camera>   float32 [H, W]      metres along the ray; only when depth was asked for
bev              uint8 [Hb, Wb, 3]   only when the BEV was asked for
meta             0-d unicode array   JSON: scene, poses, cameras, bev, scale, sizes, timings_ms, batch
batch (POST /render): every array but meta gains a leading pose axis B, e.g. images/<camera> [B, H, W, 3]"""
"""Keys, dtypes and shapes of a render ``.npz`` (uncompressed ``numpy.savez``)."""
_NPZ_ARRAY_OVERHEAD = 512
"""Bytes an array adds to an ``.npz`` beyond its data, at most: zip entry and .npy header."""
_META_CHARS = (2048, 512, 128)
"""Characters of ``meta`` JSON at most: fixed part, per pose, per view (``meta`` is stored as UTF-32)."""

MIN_IMAGE_SIDE = 4
"""Smallest rendered image side (px) a ``scale`` may produce."""
SUBSETS_KEPT = 16
"""Visibility-cell subsets of the scene a ``LocalSim`` keeps (a planner moves through a few cells at a time)."""
"""BEV (IPM) grids kept per scene, one per recently used scale."""


class RequestError(ValueError):
    """A render request names an unknown camera or a scale the scene cannot be rendered at."""


@dataclass
class Frame:
    """One rendered pose: uint8 HxWx3 ``images`` per camera, float32 ``depth`` (m), uint8 ``bev``, ``timings`` (s)."""

    images: dict[str, np.ndarray] = field(default_factory=dict)
    depth: dict[str, np.ndarray] = field(default_factory=dict)
    bev: np.ndarray | None = None
    timings: dict[str, float] = field(default_factory=dict)


def pose_text(pose: Sequence[float]) -> str:
    """``x,y,yaw`` (or 6 values) with exact float round-trip, as ``GET /render?pose=`` takes it."""
    return ",".join(repr(float(v)) for v in pose)


def encode_npz(frames: Sequence[Frame], meta: dict[str, Any], batch: bool) -> bytes:
    """Pack frames (stacked along a leading axis when ``batch``) and ``meta`` into uncompressed ``.npz`` bytes."""
    first = frames[0]
    arrays: dict[str, np.ndarray] = {}

    def put(key: str, items: list[np.ndarray]) -> None:
        arrays[key] = np.stack(items) if batch else items[0]

    for name in first.images:
        put(f"images/{name}", [f.images[name] for f in frames])
    for name in first.depth:
        put(f"depth/{name}", [f.depth[name] for f in frames])
    bevs = [f.bev for f in frames if f.bev is not None]
    if bevs:   # the frames of one request all have a BEV or none has
        put("bev", bevs)
    arrays["meta"] = np.array(json.dumps({**meta, "batch": len(frames) if batch else None}))
    buf = io.BytesIO()
    np.savez(buf, allow_pickle=False, **arrays)   # plain arrays only, as readers load them without pickle
    return buf.getvalue()


def decode_npz(data: bytes) -> tuple[list[Frame], dict[str, Any]]:
    """Inverse of ``encode_npz``: one frame per pose (a single-pose reply gives a list of one) and the metadata."""
    with np.load(io.BytesIO(data), allow_pickle=False) as z:
        meta = json.loads(str(z["meta"]))
        arrays = {k: z[k] for k in z.files if k != "meta"}
    n = meta["batch"] or 1
    pick = (lambda a, i: a[i]) if meta["batch"] else (lambda a, i: a)
    frames = []
    for i in range(n):
        f = Frame(timings={k: v / 1000 for k, v in meta.get("timings_ms", {}).items()})
        for key, arr in arrays.items():
            kind, _, name = key.partition("/")
            if kind == "images":
                f.images[name] = pick(arr, i)
            elif kind == "depth":
                f.depth[name] = pick(arr, i)
            else:
                f.bev = pick(arr, i)
        frames.append(f)
    return frames, meta


class LocalSim:
    """A loaded bundle that renders frames in-process; shares render()'s cached scaled rigs and IPM grids."""

    def __init__(self, bundle: Any, scene_id: str = "scene") -> None:
        from .bundle import Bundle, load

        self.bundle: Bundle = bundle if isinstance(bundle, Bundle) else load(bundle)
        self.id = scene_id
        self.bounds = self._bounds()
        self._subsets: OrderedDict[int, Any] = OrderedDict()
        self._subsets_lock = threading.Lock()

    @classmethod
    def from_dir(cls, directory: str | Path) -> LocalSim:
        """Load the bundle folder ``directory``; its name is the scene id."""
        return cls(Path(directory), Path(directory).name)

    def _bounds(self) -> dict[str, list[float]]:
        """Scene extent (m): the map's garage floor and height, else the 1st-99th percentile of the Gaussians."""
        garage = (self.bundle.map or {}).get("garage")
        if garage:
            return {"x": list(map(float, garage["x"])), "y": list(map(float, garage["y"])),
                    "z": [0.0, float(garage.get("height", 3.0))]}
        means = self.bundle.scene.means.detach().double()
        lo, hi = (means.quantile(q, dim=0).tolist() for q in (0.01, 0.99))
        return {axis: [lo[i], hi[i]] for i, axis in enumerate("xyz")}

    @property
    def cameras(self) -> list[str]:
        return self.bundle.rig.names

    def scene_at(self, pose: Sequence[float]) -> Any:
        """The Gaussians to render at ``pose``: its visibility cell's subset when the bundle has a grid, else all.

        Only planar poses (z = 0, level) use a cell: the grid was measured at such poses.
        """
        from .geometry import as_pose
        from .visibility import PLANAR_TOL

        grid, scene = self.bundle.visibility, self.bundle.scene
        if grid is None:
            return scene
        T = as_pose(list(pose))
        planar = abs(float(T[2, 3])) <= PLANAR_TOL and 1.0 - float(T[2, 2]) <= PLANAR_TOL
        cell = grid.cell_of(float(T[0, 3]), float(T[1, 3])) if planar else None
        if cell is None:
            return scene
        with self._subsets_lock:
            if cell in self._subsets:
                self._subsets.move_to_end(cell)
                return self._subsets[cell]
        import torch

        subset = scene.subset(torch.from_numpy(grid.members(cell)).long())
        with self._subsets_lock:
            self._subsets[cell] = subset
            while len(self._subsets) > SUBSETS_KEPT:
                self._subsets.popitem(last=False)
        return subset

    def image_size(self, camera: str, scale: float) -> tuple[int, int]:
        """(width, height) of ``camera`` rendered at ``scale``."""
        model = self.bundle.rig.cameras[camera].model
        return round(model.width * scale), round(model.height * scale)

    def check(self, cameras: Sequence[str] | None, scale: float) -> list[str]:
        """The cameras to return (all when None); ``RequestError`` names an unknown camera or a too small scale."""
        names = list(self.cameras if cameras is None else cameras)
        unknown = [n for n in names if n not in self.bundle.rig.cameras]
        if unknown:
            raise RequestError(f"unknown camera(s) {unknown}; scene {self.id!r} has {self.cameras}")
        twice = sorted({n for n in names if names.count(n) > 1})
        if twice:
            raise RequestError(f"camera(s) {twice} asked for twice: name each camera once")
        if not (math.isfinite(scale) and scale > 0):
            raise RequestError(f"scale must be a positive finite number, got {scale}")
        small = [n for n in self.cameras if min(self.image_size(n, scale)) < MIN_IMAGE_SIDE]
        if small:
            raise RequestError(f"scale {scale} makes camera(s) {small} smaller than {MIN_IMAGE_SIDE} px")
        return names

    def reply_bytes(self, poses: int, cameras: Sequence[str], bev: bool, scale: float, depth: bool) -> int:
        """Upper bound of the ``encode_npz`` size of ``poses`` frames of checked ``cameras`` (before rendering them).

        Pixels x channels (uint8 RGB, float32 depth) per view and pose, plus headers and ``meta``.
        """
        pixels = sum(w * h for w, h in (self.image_size(n, scale) for n in cameras))
        data = pixels * (3 + 4 * depth) + 3 * self.bundle.rig.bev.width * self.bundle.rig.bev.height * bev
        views = len(cameras) * (1 + depth) + bev
        fixed, per_pose, per_view = _META_CHARS
        meta = 4 * (fixed + per_pose * poses + per_view * views)
        return poses * data + _NPZ_ARRAY_OVERHEAD * (views + 1) + meta

    def info(self) -> dict[str, Any]:
        """What ``GET /scenes/{id}`` returns: rig, image sizes, BEV spec, bounds, slot map, metadata, recorded
        path (None for a bundle without one) and the ego footprint (``VehicleParams.extent``, as the env drives it)."""
        from .vehicle import VehicleParams

        b = self.bundle
        return {"id": self.id, "gaussians": len(b.scene), "cameras": self.cameras, "rig": b.rig.to_dict(),
                "bev": b.rig.bev.to_dict(), "bounds": self.bounds, "map": b.map, "meta": b.meta,
                "recorded_path": b.meta.get("recorded_path"), "footprint": list(VehicleParams().extent)}

    def render(self, pose: Sequence[float], cameras: Sequence[str] | None = None, bev: bool = False,
               scale: float = 1.0, depth: bool = False) -> Frame:
        """Render ``cameras`` (all when None; the BEV needs them all, so they are all rendered then) at ``pose``."""
        from .imageio import to_uint8
        from .render import bev_ipm, render

        names = self.check(cameras, scale)
        needed = self.cameras if bev else names
        frame = Frame()
        start = time.perf_counter()
        if needed:
            res = render(self.scene_at(pose), self.bundle.rig, list(pose), cameras=needed, scale=scale,
                         method=self.bundle.projection)
            frame.images = {n: to_uint8(res.images[n]) for n in names}
            if depth:
                frame.depth = {n: res.depth[n].detach().numpy().astype(np.float32) for n in names}
        frame.timings["views"] = time.perf_counter() - start
        if bev:
            start = time.perf_counter()
            frame.bev = to_uint8(bev_ipm(self.bundle.rig, scale)(res.images))
            frame.timings["bev"] = time.perf_counter() - start
        return frame


class RemoteSim:
    """HTTP client of ``parksim serve`` with the ``LocalSim`` interface (``info``, ``render``, and ``render_batch``)."""

    def __init__(self, base_url: str = "http://127.0.0.1:8000", scene: str | None = None,
                 api_key: str | None = None, timeout: float = 60.0, http: Any = None) -> None:
        import httpx

        headers = {"X-API-Key": api_key} if api_key else {}
        self.http = http if http is not None else httpx.Client(base_url=base_url, timeout=timeout, headers=headers)
        self.id = scene or self._get("/scenes").json()["scenes"][0]["id"]
        self._info = self._get(f"/scenes/{self.id}").json()

    def _get(self, url: str, **params: Any) -> Any:
        return self._check(self.http.get(url, params=params))

    @staticmethod
    def _check(response: Any) -> Any:
        """Raise ``RequestError`` with the server's message on a 4xx/5xx reply."""
        if response.status_code >= 400:
            try:
                detail = response.json().get("detail", response.text)
            except ValueError:
                detail = response.text
            raise RequestError(f"server answered {response.status_code}: {detail}")
        return response

    @property
    def cameras(self) -> list[str]:
        return list(self._info["cameras"])

    @property
    def bounds(self) -> dict[str, list[float]]:
        return self._info["bounds"]

    def info(self) -> dict[str, Any]:
        """The scene's description as the server gives it (same keys as ``LocalSim.info``)."""
        return self._info

    def render(self, pose: Sequence[float], cameras: Sequence[str] | None = None, bev: bool = False,
               scale: float = 1.0, depth: bool = False) -> Frame:
        """``GET /render`` for one pose."""
        params: dict[str, Any] = {"pose": pose_text(pose), "scene": self.id, "bev": bev, "scale": repr(float(scale)),
                                  "depth": depth}
        if cameras is not None:
            params["cameras"] = ",".join(cameras)
        return decode_npz(self._get("/render", **params).content)[0][0]

    def render_batch(self, poses: Sequence[Sequence[float]], cameras: Sequence[str] | None = None,
                     bev: bool = False, scale: float = 1.0, depth: bool = False) -> list[Frame]:
        """``POST /render`` for several poses in one request."""
        body = {"scene": self.id, "poses": [list(map(float, p)) for p in poses], "cameras": cameras, "bev": bev,
                "scale": float(scale), "depth": depth}
        return decode_npz(self._check(self.http.post("/render", json=body)).content)[0]

    def close(self) -> None:
        self.http.close()
