"""Case (b) of ``bench_render.py`` stage by stage on one thread (projection, binning, compositing, epilogue,
BEV), each package copy timed alternately with the others, and the compositor's Gaussian-pixel pairs:
evaluated (16-pixel tile rows each ellipse reaches, per tile up to its last contributor) against blended
(pairs that changed a pixel). Run through ``bench_render.py --stages``.
"""

from __future__ import annotations

import importlib
from collections.abc import Callable, Sequence
from typing import Any

import numba
import numpy as np
import torch
from bench_rasterize import _rows_evaluated

from parksim.bench.common import time_medians
from parksim.render.rasterize import TILE
from parksim.render.rasterize._kernels import _pair_alpha, _tile_box

STAGES = ("projection", "binning", "compositing", "epilogue", "BEV", "whole render")


@numba.njit(cache=True)
def _pairs_blended(offsets, gauss_ids, packed, tiles_x, last, width, height) -> int:
    """Gaussian-pixel pairs with alpha above ALPHA_MIN up to each pixel's last contributor (the blended ones)."""
    total = 0
    for tile in range(offsets.shape[0] - 1):
        x0, y0, x1, y1 = _tile_box(tile, tiles_x, width, height)
        for py in range(y0, y1 + 1):
            for px in range(x0, x1 + 1):
                for k in range(offsets[tile], last[py, px] + 1):
                    p = packed[gauss_ids[k]]
                    dx, dy = np.float32(px) - p[0], np.float32(py) - p[1]
                    power = np.float32(-0.5) * (p[2] * dx * dx + p[4] * dy * dy) - p[3] * dx * dy
                    total += int(_pair_alpha(p[5], power)[0] > 0.0)
    return total


class _Frame:
    """One package's (b) frame, split into its stages; each method runs one stage on the frame's data."""

    def __init__(self, pkg: str, rig: Any, scene: Any, pose: torch.Tensor, scale: float) -> None:
        mod = {name: importlib.import_module(f"{pkg}.{name}") for name in (
            "render.api", "render.project_fast", "render.projection", "render.rasterize.tiles",
            "render.rasterize._kernels", "render.scratch", "geometry")}
        self.mod, self.rig, self.scene, self.pose, self.scale = mod, rig, scene, pose, scale
        api, proj = mod["render.api"], mod["render.projection"]
        view = api._rig_view(rig, scale, tuple(rig.names))
        self.cams = [view.rig.cameras[n] for n in rig.names]
        self.lenses = [view.lens_mask(n).numpy() for n in rig.names]
        T = mod["geometry"].as_pose(pose)
        self.T_cam_world = [mod["geometry"].invert_transform(T @ c.T_vehicle_camera) for c in self.cams]
        self.cfgs = [proj.fused_config(proj.UTParams(), proj.NEAR_M, proj.FAR_M,
                                       float(max(c.model.width, c.model.height)), True) for c in self.cams]
        self.alloc = mod["render.scratch"].thread_scratch()
        self.projection()
        self.binning()
        self.planes = [(np.empty((c.model.height, c.model.width, 3), np.float32),
                        *(np.empty((c.model.height, c.model.width), t) for t in (np.float32, np.float32, np.int64)))
                       for c in self.cams]
        self.compositing()
        self.epilogue()

    def projection(self) -> None:
        s = self.scene
        self.proj = self.mod["render.project_fast"].project_views_fused(
            s.means, s.quats, s.log_scales, torch.sigmoid(s.opacity_logits), s.sh, s.sh_degree, self.T_cam_world,
            [c.model for c in self.cams], self.cfgs, alloc=self.alloc)

    def _image(self, k: int) -> tuple:
        p, m = self.proj, self.cams[k].model
        return p.means2d[k], p.conics[k], p.colors[k], p.opacities[k], p.depths[k], m.width, m.height

    def binning(self) -> None:
        tiles = self.mod["render.rasterize.tiles"]
        self.bins = [tiles.bin_gaussians(*self._image(k)) for k in range(len(self.cams))]

    def compositing(self) -> None:
        kernels = self.mod["render.rasterize._kernels"]
        for b, c, planes in zip(self.bins, self.cams, self.planes):
            order = np.argsort(-np.diff(b.offsets), kind="stable")
            kernels.forward(b.offsets, b.gauss_ids, b.packed, b.tiles_x, order, 1, c.model.width, c.model.height,
                            *planes)

    def epilogue(self) -> None:
        kernels = self.mod["render.rasterize._kernels"]
        self.images = {}
        for name, (rgb, depth, t_final, _), lens in zip(self.rig.names, self.planes, self.lenses):
            image, alpha, out_depth = np.empty_like(rgb), np.empty_like(t_final), np.empty_like(t_final)
            kernels.finish_image(rgb, depth, t_final, lens, np.zeros(3, np.float32), np.float32(1e-4),
                                 image, alpha, out_depth)
            self.images[name] = torch.from_numpy(image)

    def bev(self) -> None:
        self.mod["render.api"].bev_ipm(self.rig, self.scale, tuple(self.rig.names))(self.images)

    def whole(self) -> None:
        with torch.no_grad():
            self.mod["render.api"].render(self.scene, self.rig, self.pose, bev=True, scale=self.scale)

    def stage_fns(self) -> list[Callable[[], None]]:
        return [self.projection, self.binning, self.compositing, self.epilogue, self.bev, self.whole]

    def pairs(self) -> tuple[int, int, int]:
        """(tile intersections, pairs evaluated, pairs blended) over the frame's images."""
        isect = evaluated = blended = 0
        for b, c, planes in zip(self.bins, self.cams, self.planes):
            w, h, last = c.model.width, c.model.height, planes[3]
            isect += b.gauss_ids.shape[0]
            evaluated += TILE * _rows_evaluated(b.offsets, b.gauss_ids, b.packed, b.tiles_x, last, w, h)
            blended += _pairs_blended(b.offsets, b.gauss_ids, b.packed, b.tiles_x, last, w, h)
        return isect, evaluated, blended


def stage_table(stacks: Sequence[Any], rigs: Sequence[Any], arrays: Any, pose: torch.Tensor, scale: float,
                repeats: int) -> list[str]:
    """Markdown: per stage of (b), each stack's median process-CPU ms on one numba thread, and the pair counts."""
    threads = numba.get_num_threads()
    numba.set_num_threads(1)
    frames = [_Frame(s.name, r, s.scene(arrays), pose, scale) for s, r in zip(stacks, rigs)]
    fns = [fn for frame in frames for fn in frame.stage_fns()]
    timings = time_medians(fns, repeats)
    numba.set_num_threads(threads)
    n = len(STAGES)
    lines = ["Case (b) by stage, one numba thread, median process-CPU ms (wall ms) per frame:", "",
             "| stage | " + " | ".join(s.name for s in stacks) + " |", "| --- |" + " ---: |" * len(stacks)]
    for i, stage in enumerate(STAGES):
        cells = [f"{timings[f * n + i].cpu_ms:.1f} ({timings[f * n + i].wall_ms:.1f})" for f in range(len(frames))]
        lines.append(f"| {stage} | " + " | ".join(cells) + " |")
    isect, evaluated, blended = frames[0].pairs()
    lines += ["", f"{stacks[0].name}: {isect} tile intersections; compositor pairs evaluated {evaluated / 1e6:.2f} M, "
              f"blended {blended / 1e6:.2f} M ({evaluated / max(blended, 1):.1f} evaluated per blended)"]
    return lines
