"""Image quality metrics over masked pixels (PSNR, SSIM) and slot-region masks from the world slot map."""

from __future__ import annotations

import math
import weakref
from typing import Any

import torch
from torch import Tensor

from parksim.camera import CameraModel, pixel_grid
from parksim.rig import RigCamera

from .losses import masked_mean, ssim_map

__all__ = ["psnr", "psnr_tensor", "ssim", "slot_segments", "slot_region_mask", "SLOT_RADIUS"]

SLOT_RADIUS = 0.5
"""Slot regions: pixels seeing the floor within this distance (m) of a painted slot line."""
_CHUNK = 4096
_CELL_M = 2.0  # m: floor cells that slot-region points are sorted into, so each chunk covers a small area
_GROUND_TOLERANCE = 0.1  # m: how far behind the ground hit the true surface may be and still count as floor


def _batch(image: Tensor) -> Tensor:
    """HxWx3 -> 1x3xHxW."""
    return image.permute(2, 0, 1)[None]


def psnr(pred: Tensor, gt: Tensor, mask: Tensor) -> float:
    """PSNR (dB, peak 1) of HxWx3 images over the HxW boolean ``mask``; inf for a perfect match."""
    m = mask[None, None].to(pred.dtype)
    mse = float(masked_mean((_batch(pred) - _batch(gt)) ** 2, m))
    return math.inf if mse == 0 else -10.0 * math.log10(mse)


def psnr_tensor(pred: Tensor, gt: Tensor, mask: Tensor) -> Tensor:
    """``psnr`` as a 0-dim float64 tensor on the images' device (inf for a perfect match): nothing is read back to
    the host, so a GPU training step need not wait for it.

    Args:
        pred: ``[H, W, 3]`` image.
        gt: ``[H, W, 3]`` target, same device.
        mask: ``[H, W]`` bool, same device.

    Returns:
        PSNR in dB (peak 1).
    """
    mse = masked_mean((_batch(pred) - _batch(gt)) ** 2, mask[None, None].to(pred.dtype)).double()
    return -10.0 * torch.log10(mse)


def ssim(pred: Tensor, gt: Tensor, mask: Tensor) -> float:
    """Mean SSIM (11x11 Gaussian window) of HxWx3 images over the HxW boolean ``mask``."""
    return float(masked_mean(ssim_map(_batch(pred), _batch(gt)), mask[None, None].to(pred.dtype)))


def slot_segments(world_map: dict[str, Any]) -> Tensor:
    """Painted slot lines as world segments ``[S, 2, 2]`` (xy): the four edges of every slot's outline."""
    segs = []
    for slot in world_map.get("slots", []):
        c = slot["corners"]
        segs += [(c[i], c[(i + 1) % len(c)]) for i in range(len(c))]
    return torch.tensor(segs, dtype=torch.float64).reshape(-1, 2, 2)


def _near_segments(points: Tensor, segments: Tensor, radius: float) -> Tensor:
    """Bool ``[P]``: the 2D point ``[P, 2]`` lies within ``radius`` of a segment of ``[S, 2, 2]``.

    Points are sorted into 2 m floor cells and go in chunks of neighbours; a chunk is tested only against the
    segments whose bounding box comes within ``radius`` of the chunk's (any other segment is farther than ``radius``
    from all its points)."""
    lo_s, hi_s = segments.amin(1), segments.amax(1)
    cell = torch.floor((points - points.amin(0)) / _CELL_M).to(torch.int64)
    order = torch.argsort(cell[:, 0] * (int(cell[:, 1].max()) + 1) + cell[:, 1])
    points = points[order]
    near = torch.zeros(len(points), dtype=torch.bool)
    for start in range(0, len(points), _CHUNK):
        p = points[start:start + _CHUNK]
        keep = ((hi_s >= p.amin(0) - radius) & (lo_s <= p.amax(0) + radius)).all(dim=1)
        if not keep.any():
            continue
        a, ab = segments[keep, 0], segments[keep, 1] - segments[keep, 0]
        q = p[:, None]
        t = (((q - a) * ab).sum(-1) / (ab * ab).sum(-1).clamp(min=1e-12)).clamp(0, 1)
        near[start:start + _CHUNK] = (q - (a + t[..., None] * ab)).norm(dim=-1).amin(dim=1) <= radius
    out = torch.empty_like(near)
    out[order] = near
    return out


_RAYS: weakref.WeakKeyDictionary[CameraModel, tuple[Tensor, Tensor]] = weakref.WeakKeyDictionary()


def _pixel_rays(model: CameraModel) -> tuple[Tensor, Tensor]:
    """Unit rays ``[H, W, 3]`` (camera frame, float64) and lens validity ``[H, W]`` of every pixel centre, solved
    once per camera model: evaluation asks for them at every view, and unprojection is a Newton solve per pixel."""
    if model not in _RAYS:
        grid = pixel_grid(model.width, model.height)
        with torch.no_grad():
            _RAYS[model] = (model.unproject(grid).to(torch.float64), model.pixel_valid(grid))
    return _RAYS[model]


def slot_region_mask(camera: RigCamera, T_world_vehicle: Tensor, segments: Tensor, depth: Tensor | None = None,
                     radius: float = SLOT_RADIUS) -> Tensor:
    """Bool ``[H, W]``: the pixel's ray meets the floor (z = 0) within ``radius`` of a slot line.

    With ``depth`` (distance along the ray, 0 = unknown) the floor point must also be what the pixel
    sees, so slot lines hidden behind cars or pillars are not counted.
    """
    model = camera.model
    if len(segments) == 0:
        return torch.zeros(model.height, model.width, dtype=torch.bool)
    T = T_world_vehicle.to(torch.float64) @ camera.T_vehicle_camera
    rays_camera, valid = _pixel_rays(model)
    rays = rays_camera @ T[:3, :3].T
    origin = T[:3, 3]
    down = rays[..., 2] < -1e-6
    t = torch.where(down, -origin[2] / torch.where(down, rays[..., 2], -1.0), 0.0)
    hit = origin[:2] + t[..., None] * rays[..., :2]
    mask = down & valid
    points = hit[mask]
    if len(points):
        mask[mask.clone()] = _near_segments(points, segments.reshape(-1, 2, 2), radius)
    if depth is not None:
        mask &= (depth <= 0) | (depth.to(torch.float64) >= t - _GROUND_TOLERANCE)
    return mask
