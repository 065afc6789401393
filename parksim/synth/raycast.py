"""Analytic ray casting of the garage: floor, ceiling and oriented boxes, first hit per ray.

Rays are grouped in tiles of 8x8 pixels (each pixel: 2x2 sub-sample rays for the colour
plus its centre ray for depth and ids). Per tile a cone bounds its rays; a box is tested
only against the tiles whose cone meets the box's bounding sphere, so each ray visits a
handful of boxes instead of all of them. The kernel is numba, parallel over tiles.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch
from numba import njit, prange

from ..camera import CameraModel
from .garage import Box

__all__ = ["BoxSet", "TiledRays", "Hits", "trace_camera", "trace_world", "box_id", "TILE", "SUB", "FLOOR", "CEILING",
           "MISS"]

TILE = 8
"""Tile side in pixels."""
SUB = 2
"""Supersampling factor per axis: SUB x SUB colour rays per pixel."""
MISS, FLOOR, CEILING = -1, 0, 1
"""Primitive ids below the boxes; box ``i`` has id ``2 + i``."""
_BOX0 = 2


@dataclass(frozen=True)
class BoxSet:
    """Boxes as flat arrays for the kernel: centres, half extents, (cos, sin) of yaw, bounding radii."""

    centres: np.ndarray
    halves: np.ndarray
    yaw_cs: np.ndarray
    radii: np.ndarray

    @classmethod
    def from_boxes(cls, boxes: Sequence[Box]) -> BoxSet:
        arr = np.array([[b.cx, b.cy, (b.z0 + b.z1) / 2, b.length / 2, b.width / 2, (b.z1 - b.z0) / 2, b.yaw]
                        for b in boxes], dtype=np.float64).reshape(-1, 7)
        halves = arr[:, 3:6].copy()
        return cls(arr[:, :3].copy(), halves, np.stack([np.cos(arr[:, 6]), np.sin(arr[:, 6])], 1),
                   np.linalg.norm(halves, axis=1))


_TABLE = 1 << 15  # samples of the radial table in radial_unproject


def radial_unproject(model: CameraModel, uv: np.ndarray) -> np.ndarray:
    """``model.unproject`` for many pixels at once: the lens is radial, so ``model.unproject`` is
    evaluated on a dense table of radii (along +u) and each pixel's angle theta is interpolated
    from it (error far below 1e-6 rad); pixels past the lens edge get the edge angle."""
    fx, fy, cx, cy = (float(v) for v in (model.fx, model.fy, model.cx, model.cy))
    mx, my = (uv[..., 0] - cx) / fx, (uv[..., 1] - cy) / fy
    rho = np.hypot(mx, my)
    grid = np.linspace(0.0, max(float(rho.max()), 1e-6), _TABLE)
    table_uv = torch.from_numpy(np.stack([cx + fx * grid, np.full_like(grid, cy)], -1))
    table = model.unproject(table_uv).numpy()
    theta = np.interp(rho, grid, np.arctan2(table[:, 0], table[:, 2]))
    scale = np.where(rho > 0, np.sin(theta) / np.maximum(rho, 1e-300), 1.0)
    return np.stack([mx * scale, my * scale, np.cos(theta)], -1)


@dataclass(frozen=True)
class TiledRays:
    """One camera's unit rays (camera frame) arranged in tiles, with per-tile bounding cones.

    ``rays[T, K, 3]``: the first ``TILE^2 * SUB^2`` entries of a tile are sub-sample rays,
    ordered (row, col, sub-row, sub-col); the last ``TILE^2`` are pixel-centre rays.
    """

    rays: np.ndarray
    valid: np.ndarray
    axis: np.ndarray
    half_angle: np.ndarray
    tiles_y: int
    tiles_x: int
    height: int
    width: int

    @classmethod
    def build(cls, model: CameraModel) -> TiledRays:
        """Unproject every sub-sample and centre through the exact lens model (full sphere)."""
        ty, tx = -(-model.height // TILE), -(-model.width // TILE)
        iy, ix = np.meshgrid(np.arange(ty * TILE), np.arange(tx * TILE), indexing="ij")
        # pixel grid -> (ty, tx, TILE, TILE) tile order
        tiled = lambda a: a.reshape(ty, TILE, tx, TILE).transpose(0, 2, 1, 3).reshape(ty * tx, TILE, TILE)  # noqa: E731
        v, u = tiled(iy).astype(np.float64), tiled(ix).astype(np.float64)
        offs = (np.arange(SUB) + 0.5) / SUB - 0.5
        su = u[:, :, :, None, None] + offs[None, None, None, None, :]
        sv = v[:, :, :, None, None] + offs[None, None, None, :, None]
        su, sv = np.broadcast_arrays(su, sv)
        n = ty * tx
        uv = np.concatenate([np.stack([su, sv], -1).reshape(n, -1, 2), np.stack([u, v], -1).reshape(n, -1, 2)], 1)
        uv_t = torch.from_numpy(uv)
        rays = radial_unproject(model, uv)
        inside = (uv[..., 0] < model.width - 0.5) & (uv[..., 1] < model.height - 0.5)
        # A pixel is valid when its centre is; its sub-samples then all get traced.
        centre_ok = (model.pixel_valid(uv_t[:, -TILE * TILE:]).numpy() & inside[:, -TILE * TILE:])
        valid = np.concatenate([np.repeat(centre_ok, SUB * SUB, axis=1), centre_ok], 1)
        axis = (rays * valid[..., None]).sum(1)
        axis /= np.maximum(np.linalg.norm(axis, axis=1, keepdims=True), 1e-12)
        cosines = np.where(valid, np.einsum("tkc,tc->tk", rays, axis), 1.0)
        half = np.arccos(np.clip(cosines.min(1), -1.0, 1.0))
        half[~valid.any(1)] = -1.0  # empty tile: never matches a box
        return cls(rays.astype(np.float32), valid, axis, half, ty, tx, model.height, model.width)

    def untile(self, values: np.ndarray) -> np.ndarray:
        """Per-tile centre values ``[T, TILE^2, ...]`` -> image ``[H, W, ...]``."""
        rest = values.shape[2:]
        img = values.reshape(self.tiles_y, self.tiles_x, TILE, TILE, *rest).swapaxes(1, 2)
        return img.reshape(self.tiles_y * TILE, self.tiles_x * TILE, *rest)[: self.height, : self.width]

    def untile_sub(self, values: np.ndarray) -> np.ndarray:
        """Per-tile sub-sample values ``[T, TILE^2 SUB^2, C]`` -> pixel averages ``[H, W, C]``."""
        c = values.shape[-1]
        mean = values.reshape(values.shape[0], TILE * TILE, SUB * SUB, c).mean(2)
        return self.untile(mean)


@dataclass(frozen=True)
class Hits:
    """First hits of a batch of rays: distance ``t`` along the unit ray, primitive id, face, world point."""

    t: np.ndarray
    prim: np.ndarray
    face: np.ndarray
    points: np.ndarray
    dirs: np.ndarray

    def columns(self, sl: slice) -> Hits:
        """The hits of a slice of each tile's rays (e.g. the sub-samples or the centres)."""
        return Hits(self.t[:, sl], self.prim[:, sl], self.face[:, sl], self.points[:, sl], self.dirs[:, sl])


@njit(cache=True, inline="always")
def _slab(o: float, d: float, h: float) -> tuple[float, float]:
    """Entry and exit distances of a ray coordinate through the slab ``|x| <= h``."""
    if abs(d) < 1e-12:
        if abs(o) <= h:
            return -np.inf, np.inf
        return np.inf, -np.inf
    t1, t2 = (-h - o) / d, (h - o) / d
    return (t1, t2) if t1 < t2 else (t2, t1)


@njit(parallel=True, cache=True, error_model="numpy")
def _trace_kernel(origin, R, rays, valid, tile_ptr, tile_boxes, centres, halves, yaw_cs, ceiling,
                  t_out, prim_out, face_out, dir_out):
    """First hit per ray; faces 0..5 are +x, -x, +y, -y, +z, -z of the box (floor +z, ceiling -z)."""
    n_tiles, k_rays = rays.shape[0], rays.shape[1]
    ox, oy, oz = origin[0], origin[1], origin[2]
    for ti in prange(n_tiles):
        for k in range(k_rays):
            rx, ry, rz = rays[ti, k, 0], rays[ti, k, 1], rays[ti, k, 2]
            dx = R[0, 0] * rx + R[0, 1] * ry + R[0, 2] * rz
            dy = R[1, 0] * rx + R[1, 1] * ry + R[1, 2] * rz
            dz = R[2, 0] * rx + R[2, 1] * ry + R[2, 2] * rz
            dir_out[ti, k, 0], dir_out[ti, k, 1], dir_out[ti, k, 2] = dx, dy, dz
            if not valid[ti, k]:
                t_out[ti, k], prim_out[ti, k], face_out[ti, k] = 0.0, -1, 0
                continue
            best, prim, face = np.inf, -1, 0
            if dz < -1e-12:
                best, prim, face = -oz / dz, 0, 4
            elif dz > 1e-12:
                best, prim, face = (ceiling - oz) / dz, 1, 5
            for j in range(tile_ptr[ti], tile_ptr[ti + 1]):
                b = tile_boxes[j]
                c, s = yaw_cs[b, 0], yaw_cs[b, 1]
                px, py, pz = ox - centres[b, 0], oy - centres[b, 1], oz - centres[b, 2]
                lx, ly = c * px + s * py, -s * px + c * py
                ldx, ldy = c * dx + s * dy, -s * dx + c * dy
                a0, a1 = _slab(lx, ldx, halves[b, 0])
                b0, b1 = _slab(ly, ldy, halves[b, 1])
                c0, c1 = _slab(pz, dz, halves[b, 2])
                t_in, t_exit, f = a0, min(a1, b1, c1), (1 if ldx > 0 else 0)
                if b0 > t_in:
                    t_in, f = b0, (3 if ldy > 0 else 2)
                if c0 > t_in:
                    t_in, f = c0, (5 if dz > 0 else 4)
                if t_in <= t_exit and 1e-6 < t_in < best:
                    best, prim, face = t_in, 2 + b, f
            t_out[ti, k], prim_out[ti, k], face_out[ti, k] = best, prim, face


def _cull(origin: np.ndarray, R: np.ndarray, rays: TiledRays, boxes: BoxSet) -> tuple[np.ndarray, np.ndarray]:
    """CSR lists of the boxes whose bounding sphere meets each tile's cone."""
    rel = (boxes.centres - origin) @ R  # camera frame
    dist = np.linalg.norm(rel, axis=1)
    inside = dist <= boxes.radii
    spread = np.arcsin(np.clip(boxes.radii / np.maximum(dist, 1e-9), 0.0, 1.0))
    cos_a = (rays.axis @ rel.T) / np.maximum(dist, 1e-9)
    angle = np.arccos(np.clip(cos_a, -1.0, 1.0))
    hit = (angle <= rays.half_angle[:, None] + spread[None, :] + 1e-6) | inside[None, :]
    hit &= rays.half_angle[:, None] >= 0
    tile_idx, box_idx = np.nonzero(hit)
    ptr = np.zeros(len(rays.axis) + 1, dtype=np.int64)
    np.cumsum(np.bincount(tile_idx, minlength=len(rays.axis)), out=ptr[1:])
    return ptr, box_idx.astype(np.int64)


def _run(origin: np.ndarray, R: np.ndarray, rays: np.ndarray, valid: np.ndarray, ptr: np.ndarray,
         box_idx: np.ndarray, boxes: BoxSet, ceiling: float) -> Hits:
    shape = rays.shape[:2]
    t = np.empty(shape, np.float64)
    prim = np.empty(shape, np.int32)
    face = np.empty(shape, np.int8)
    dirs = np.empty((*shape, 3), np.float64)
    _trace_kernel(origin.astype(np.float64), R.astype(np.float64), rays, valid, ptr, box_idx, boxes.centres,
                  boxes.halves, boxes.yaw_cs, float(ceiling), t, prim, face, dirs)
    t = np.where(prim >= 0, t, 0.0)
    return Hits(t, prim, face, origin + t[..., None] * dirs, dirs)


def trace_camera(T_world_camera: np.ndarray, rays: TiledRays, boxes: BoxSet, ceiling: float,
                 columns: np.ndarray | None = None) -> Hits:
    """Trace one camera's tiled rays (all, or the given ``columns`` of every tile) from its world pose (4x4)."""
    origin, R = T_world_camera[:3, 3], T_world_camera[:3, :3]
    ptr, idx = _cull(origin, R, rays, boxes)
    if columns is None:
        return _run(origin, R, rays.rays, rays.valid, ptr, idx, boxes, ceiling)
    return _run(origin, R, np.ascontiguousarray(rays.rays[:, columns]), np.ascontiguousarray(rays.valid[:, columns]),
                ptr, idx, boxes, ceiling)


def trace_world(origin: np.ndarray, dirs: np.ndarray, boxes: BoxSet, ceiling: float) -> Hits:
    """Trace unit rays ``dirs[N, 3]`` (world frame) from one origin against every box."""
    n = len(dirs)
    ptr = np.array([0, len(boxes.radii)], dtype=np.int64)
    idx = np.arange(len(boxes.radii), dtype=np.int64)
    hits = _run(np.asarray(origin, np.float64), np.eye(3), np.asarray(dirs, np.float32).reshape(1, n, 3),
                np.ones((1, n), bool), ptr, idx, boxes, ceiling)
    return Hits(hits.t[0], hits.prim[0], hits.face[0], hits.points[0], hits.dirs[0])


def box_id(index: int) -> int:
    """Primitive id of box ``index`` in a ``BoxSet``."""
    return _BOX0 + index
