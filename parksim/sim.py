"""The simulator core: a loaded bundle that renders ``Frame`` objects in-process (``LocalSim``).

The HTTP server renders with it, the gymnasium env drives it directly, and ``RemoteSim``
(``parksim.client``) offers the same interface over HTTP, returning the same frames bit for bit.
"""

from __future__ import annotations

import dataclasses
import math
import threading
import time
from collections import OrderedDict
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from .frames import Frame, RequestError, npz_bytes_bound

if TYPE_CHECKING:
    import torch

    from .render.actors import Actor

__all__ = ["LocalSim", "MIN_IMAGE_SIDE", "SUBSETS_KEPT", "RESPONSES_KEPT"]

MIN_IMAGE_SIDE = 4
"""Smallest rendered image side (px) a ``scale`` may produce."""
SUBSETS_KEPT = 16
"""Visibility-cell subsets of the scene a ``LocalSim`` keeps (a planner moves through a few cells at a time)."""
RESPONSES_KEPT = 8
"""Camera responses at distinct render scales a ``LocalSim`` keeps (each holds a radius map per camera)."""


class LocalSim:
    """A loaded bundle that renders frames in-process; shares render()'s cached scaled rigs and IPM grids."""

    def __init__(self, bundle: Any, scene_id: str = "scene", device: str | torch.device = "auto") -> None:
        """Resolve the device, load (or take) the bundle, measure the scene's bounds and move the Gaussians there.

        Renders run where the Gaussians are; frames are always numpy arrays on the CPU (one copy back per image).

        Args:
            bundle: a ``Bundle``, or a bundle folder to ``load``. A given ``Bundle`` is not changed: on another
                device the simulator keeps a copy whose scene lives there.
            scene_id: the scene's name in ``info()`` and error messages.
            device: ``"auto"``, ``"cpu"`` or ``"cuda[:N]"`` (``parksim.device.resolve_device``), or a torch device.

        Raises:
            DeviceError: a bad device name, or a CUDA device this machine lacks (before the bundle is read).
            BundleError: a folder that ``parksim.bundle.load`` refuses.
        """
        from .bundle import Bundle, load
        from .device import resolve_device

        self.device = resolve_device(device)
        self.bundle: Bundle = bundle if isinstance(bundle, Bundle) else load(bundle)
        self.id = scene_id
        self.bounds = self._bounds()
        if self.bundle.scene.means.device != self.device:
            self.bundle = dataclasses.replace(self.bundle, scene=self.bundle.scene.to(device=self.device))
        self._subsets: OrderedDict[int, Any] = OrderedDict()
        self._subsets_lock = threading.Lock()
        self._responses: OrderedDict[float, Any] = OrderedDict()
        self._responses_lock = threading.Lock()

    @classmethod
    def from_dir(cls, directory: str | Path, device: str | torch.device = "auto") -> LocalSim:
        """Load the bundle folder ``directory``; its name is the scene id.

        Args:
            directory: the bundle folder.
            device: where it renders, as for ``LocalSim``.

        Returns:
            The simulator.
        """
        return cls(Path(directory), Path(directory).name, device)

    def _bounds(self) -> dict[str, list[float]]:
        """Scene extent (m): the map's garage box, else robust statistics of the Gaussian means.

        Without a garage: the 1st-99th percentile of the means that lie within the scene's robust extent
        (``parksim.bundle.absurd_gaussians``), so outliers cannot widen it.

        Returns:
            ``{"x": [lo, hi], "y": [lo, hi], "z": [lo, hi]}`` in metres.
        """
        import torch

        from .bundle import absurd_gaussians, garage_box

        box = garage_box(self.bundle.map)
        if box is not None:
            return {axis: [float(box[0, i]), float(box[1, i])] for i, axis in enumerate("xyz")}
        scene = self.bundle.scene
        keep = ~absurd_gaussians(scene)["mean"]
        means = scene.means.detach().double()[torch.from_numpy(keep).to(scene.means.device)]
        lo, hi = (means.quantile(q, dim=0).tolist() for q in (0.01, 0.99))
        return {axis: [lo[i], hi[i]] for i, axis in enumerate("xyz")}

    @property
    def cameras(self) -> list[str]:
        """Camera names in rig order."""
        return self.bundle.rig.names

    def scene_at(self, pose: Sequence[float]) -> Any:
        """The Gaussians to render at ``pose``: its visibility cell's subset when the bundle has a grid, else all.

        Only planar poses (z = 0, level) use a cell: the grid was measured at such poses.

        Args:
            pose: ``(x, y, yaw)`` or ``(x, y, z, roll, pitch, yaw)`` (metres, radians).

        Returns:
            A ``GaussianScene``: the cell's subset (kept for the next ``SUBSETS_KEPT`` cells) or the whole scene.
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

        subset = scene.subset(torch.from_numpy(grid.members(cell)).long().to(scene.means.device))
        with self._subsets_lock:
            self._subsets[cell] = subset
            while len(self._subsets) > SUBSETS_KEPT:
                self._subsets.popitem(last=False)
        return subset

    def response(self, scale: float) -> Any:
        """The bundle's learned camera response (``camera_response``) for views rendered at ``scale``.

        As ``parksim eval`` applies it: per camera an RGB gain and radial vignetting, its radius maps built for the
        camera scaled by ``scale``. ``render_batch`` applies it to every view before the uint8 conversion and the BEV.

        Args:
            scale: image size relative to the rig's cameras.

        Returns:
            A frozen ``parksim.recon.response.CameraResponse`` on the simulator's device (the same object for the
            next ``RESPONSES_KEPT`` scales), or None when the bundle has none (a third-party PLY).
        """
        data = self.bundle.meta.get("camera_response")
        if not data:
            return None
        with self._responses_lock:
            if scale in self._responses:
                self._responses.move_to_end(scale)
                return self._responses[scale]
        from .recon.response import CameraResponse

        response = CameraResponse.frozen(self.bundle.rig, data, self.device, scale)
        with self._responses_lock:
            self._responses[scale] = response
            while len(self._responses) > RESPONSES_KEPT:
                self._responses.popitem(last=False)
        return response

    def image_size(self, camera: str, scale: float) -> tuple[int, int]:
        """(width, height) of ``camera`` rendered at ``scale``.

        Args:
            camera: a camera name of the rig.
            scale: image size relative to the rig's camera.

        Returns:
            ``(width, height)`` in pixels, rounded.
        """
        model = self.bundle.rig.cameras[camera].model
        return round(model.width * scale), round(model.height * scale)

    def check(self, cameras: Sequence[str] | None, scale: float) -> list[str]:
        """The cameras to return (all when None); ``RequestError`` names an unknown camera or a too small scale.

        Args:
            cameras: the names asked for, or None for all.
            scale: the image size asked for, relative to the rig's cameras.

        Returns:
            The camera names to render, in the order asked.

        Raises:
            RequestError: an unknown camera, a camera named twice, a scale that is not a positive finite number,
                or one that makes a camera smaller than ``MIN_IMAGE_SIDE`` px.
        """
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

        Args:
            poses: frames in the reply.
            cameras: the checked camera names (``check``).
            bev: the reply holds the BEV.
            scale: image size relative to the rig's cameras.
            depth: the reply holds depth maps.

        Returns:
            Bytes, an upper bound (``frames.npz_bytes_bound``).
        """
        pixels = sum(w * h for w, h in (self.image_size(n, scale) for n in cameras))
        data = pixels * (3 + 4 * depth) + 3 * self.bundle.rig.bev.width * self.bundle.rig.bev.height * bev
        return npz_bytes_bound(poses, data, len(cameras) * (1 + depth) + bev)

    def info(self) -> dict[str, Any]:
        """What ``GET /scenes/{id}`` returns.

        Returns:
            JSON values: ``id``, ``gaussians`` (count), ``cameras``, ``rig``, ``bev`` spec, ``bounds`` (m),
            ``map``, ``meta``, ``recorded_path`` (None for a bundle without one), ``footprint``, the ego's
            ``VehicleParams.extent`` as the env drives it, and ``dropped``, the absurd Gaussians dropped on load
            per reason (``Bundle.dropped``).
        """
        from .vehicle import VehicleParams

        b = self.bundle
        return {"id": self.id, "gaussians": len(b.scene), "cameras": self.cameras, "rig": b.rig.to_dict(),
                "bev": b.rig.bev.to_dict(), "bounds": self.bounds, "map": b.map, "meta": b.meta,
                "recorded_path": b.meta.get("recorded_path"), "footprint": list(VehicleParams().extent),
                "dropped": dict(b.dropped)}

    def render(self, pose: Sequence[float], cameras: Sequence[str] | None = None, bev: bool = False,
               scale: float = 1.0, depth: bool = False, actors: Sequence[Actor] | None = None) -> Frame:
        """Render ``cameras`` (all when None; the BEV needs them all, so they are all rendered then) at ``pose``.

        Args:
            pose: ``(x, y, yaw)`` or ``(x, y, z, roll, pitch, yaw)`` of the vehicle (metres, radians).
            cameras: names of the images to return (default: all).
            bev: also return the BEV (IPM of all cameras).
            scale: image size relative to the rig's cameras.
            depth: also return depth maps.
            actors: Gaussian actors drawn with the scene (``parksim.render.render``'s ``actors``).

        Returns:
            The frame: uint8 ``[H, W, 3]`` images through the bundle's camera response (``response``), float32
            ``[H, W]`` depth (m) when asked, uint8 ``[Hb, Wb, 3]`` BEV of those images when asked, and ``timings``
            (s) of the views and the BEV.

        Raises:
            RequestError: as ``check``.
        """
        return self.render_batch([pose], cameras, bev, scale, depth, actors)[0]

    def render_batch(self, poses: Sequence[Sequence[float]], cameras: Sequence[str] | None = None,
                     bev: bool = False, scale: float = 1.0, depth: bool = False,
                     actors: Sequence[Actor] | None = None) -> list[Frame]:
        """``render`` at several poses, together where they share a scene.

        The poses that share a scene (all of them without visibility cells, those of one cell with them) are
        rendered by one ``parksim.render.render_batch`` (one projection pass; on a GPU one kernel launch and one
        rasterizer call), and the BEVs in one batched IPM on a GPU.

        Args:
            poses: B poses, each as ``render`` takes.
            cameras: as ``render``.
            bev: as ``render``.
            scale: as ``render``.
            depth: as ``render``.
            actors: as ``render``, the same at every pose.

        Returns:
            B frames as ``render`` gives, each equal to ``render`` at its pose; each frame's ``timings`` are the
            batch's divided by B.

        Raises:
            RequestError: as ``check``.
        """
        import torch

        from .imageio import to_uint8
        from .render import bev_ipm, render_batch

        names = self.check(cameras, scale)
        needed = self.cameras if bev else names
        frames = [Frame() for _ in poses]
        start = time.perf_counter()
        results: list[Any] = [None] * len(poses)
        if needed:
            groups: dict[int, tuple[Any, list[int]]] = {}
            for i, pose in enumerate(poses):
                scene = self.scene_at(pose)
                groups.setdefault(id(scene), (scene, []))[1].append(i)
            response = self.response(scale)
            for scene, members in groups.values():
                rendered = render_batch(scene, self.bundle.rig, [list(poses[i]) for i in members], cameras=needed,
                                        scale=scale, method=self.bundle.projection, actors=actors)
                for i, res in zip(members, rendered):
                    if response is not None:
                        res.images = {n: response(image, n) for n, image in res.images.items()}
                    results[i] = res
            for frame, res in zip(frames, results):
                frame.images = {n: to_uint8(res.images[n]) for n in names}
                if depth:
                    frame.depth = {n: res.depth[n].detach().cpu().numpy().astype(np.float32) for n in names}
        share = (time.perf_counter() - start) / max(len(poses), 1)
        for frame in frames:
            frame.timings["views"] = share
        if bev:
            start = time.perf_counter()
            ipm = bev_ipm(self.bundle.rig, scale)
            if self.device.type == "cuda" and len(results) > 1:
                bevs = list(ipm({n: torch.stack([r.images[n] for r in results]) for n in self.cameras}))
            else:
                bevs = [ipm(r.images) for r in results]
            share = (time.perf_counter() - start) / len(poses)
            for frame, image in zip(frames, bevs):
                frame.bev = to_uint8(image)
                frame.timings["bev"] = share
        return frames
