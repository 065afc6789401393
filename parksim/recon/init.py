"""Initial Gaussians: one per sparse point (dataset PLY or COLMAP model), or random in the scene bounds."""

from __future__ import annotations

import math

import numpy as np
import torch
from torch import Tensor

from parksim.data import DatasetReader
from parksim.gaussians import SH_C0, GaussianScene

from .config import InitConfig

__all__ = ["initial_scene", "scene_bounds", "knn_mean_distance"]

_KNN = 3
_CHUNK = 2048


def knn_mean_distance(xyz: Tensor, k: int = _KNN) -> Tensor:
    """Mean distance of each point to its ``k`` nearest other points (chunked brute force, float64, on ``xyz``'s
    device)."""
    pts = xyz.to(torch.float64)
    out = torch.empty(len(pts), dtype=torch.float64, device=pts.device)
    k_eff = min(k, len(pts) - 1)
    if k_eff < 1:
        return torch.full((len(pts),), 0.1, dtype=torch.float64, device=pts.device)
    for start in range(0, len(pts), _CHUNK):
        d = torch.cdist(pts[start:start + _CHUNK], pts)
        nearest = d.topk(k_eff + 1, dim=1, largest=False).values[:, 1:]
        out[start:start + _CHUNK] = nearest.mean(dim=1)
    return out


def scene_bounds(reader: DatasetReader) -> tuple[list[float], list[float]]:
    """World box of the scene: the garage extent from map.json, else the camera path padded by 8 m, 0-3 m high."""
    if reader.layout.map.is_file() and "garage" in reader.map:
        g = reader.map["garage"]
        return [g["x"][0], g["y"][0], 0.0], [g["x"][1], g["y"][1], float(g.get("height", 3.0))]
    xy = reader.camera_centres()[:, :2]
    lo, hi = xy.min(0).values - 8.0, xy.max(0).values + 8.0
    return [float(lo[0]), float(lo[1]), 0.0], [float(hi[0]), float(hi[1]), 3.0]


def _from_points(xyz: Tensor, rgb: Tensor, cfg: InitConfig, sh_degree: int,
                 device: torch.device | None) -> GaussianScene:
    """Isotropic Gaussians at ``xyz`` with colours ``rgb`` in [0, 1], sized by their nearest neighbours, built on
    ``device`` (None: the points')."""
    xyz, rgb = xyz.to(device), rgb.to(device)
    n = len(xyz)
    scale = knn_mean_distance(xyz).clamp(min=1e-4) * cfg.scale_factor
    sh = torch.zeros(n, (sh_degree + 1) ** 2, 3, dtype=torch.float64, device=xyz.device)
    sh[:, 0] = (rgb.to(torch.float64) - 0.5) / SH_C0
    quats = torch.zeros(n, 4, dtype=torch.float64, device=xyz.device)
    quats[:, 0] = 1.0
    return GaussianScene(xyz.to(torch.float64), quats, torch.log(scale)[:, None].repeat(1, 3),
                         torch.full((n,), math.log(cfg.opacity / (1 - cfg.opacity)), dtype=torch.float64,
                                    device=xyz.device),
                         sh, sh_degree).to(torch.float32)


def _sparse_points(reader: DatasetReader, cfg: InitConfig) -> tuple[np.ndarray, np.ndarray, str]:
    """(xyz, rgb uint8, description) from the source the config names."""
    if cfg.source == "colmap":
        from .colmap import read_colmap_points

        if cfg.colmap_model is None:
            raise ValueError("init.source is 'colmap' but init.colmap_model is not set")
        xyz, rgb = read_colmap_points(cfg.colmap_model)
        return xyz, rgb, f"COLMAP model {cfg.colmap_model}"
    xyz, rgb = reader.points
    return xyz, rgb, str(reader.layout.points)


def initial_scene(reader: DatasetReader, cfg: InitConfig, sh_degree: int, generator: torch.Generator,
                  device: torch.device | None = None) -> tuple[GaussianScene, str]:
    """The initial scene (on ``device``; None: the CPU) and a one-line description of where it came from.

    Points are drawn and subsampled on the CPU with ``generator`` whatever the device, so a run starts from the
    same points everywhere; the nearest-neighbour sizes are computed on ``device``.
    """
    source = cfg.source
    if source == "auto":
        source = "points" if reader.layout.points.is_file() else "random"
    if source == "random":
        lo, hi = (torch.tensor(b, dtype=torch.float64) for b in scene_bounds(reader))
        xyz = lo + (hi - lo) * torch.rand(cfg.random_count, 3, generator=generator, dtype=torch.float64)
        rgb = torch.rand(cfg.random_count, 3, generator=generator, dtype=torch.float64)
        return (_from_points(xyz, rgb, cfg, sh_degree, device),
                f"{cfg.random_count} random points in the scene bounds")
    xyz_np, rgb_np, what = _sparse_points(reader, cfg.model_copy(update={"source": source}))
    xyz, rgb = torch.from_numpy(xyz_np).to(torch.float64), torch.from_numpy(rgb_np).to(torch.float64) / 255.0
    if len(xyz) == 0:
        raise ValueError(f"{what}: the sparse point cloud is empty")
    if len(xyz) > cfg.max_points:
        keep = torch.randperm(len(xyz), generator=generator)[:cfg.max_points]
        xyz, rgb = xyz[keep], rgb[keep]
    return _from_points(xyz, rgb, cfg, sh_degree, device), f"{len(xyz)} points from {what}"
