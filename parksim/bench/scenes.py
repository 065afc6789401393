"""Inputs of the render benchmarks: garage-like Gaussian scenes built from a dataset's surface points (random
scenes have other statistics than trained ones), trained bundles, and an SH-degree cap of a scene.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import torch

from ..gaussians import SH_C0, GaussianScene

__all__ = ["garage_scene", "cap_sh_degree", "read_points", "mean_spacing"]


def read_points(dataset: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Positions, unit normals and RGB in [0, 1] of the dataset's ``points3d.ply``."""
    from plyfile import PlyData

    v = PlyData.read(str(dataset / "points3d.ply"))["vertex"]
    xyz = np.stack([v["x"], v["y"], v["z"]], -1).astype(np.float64)
    normals = np.stack([v["nx"], v["ny"], v["nz"]], -1).astype(np.float64)
    normals /= np.maximum(np.linalg.norm(normals, axis=-1, keepdims=True), 1e-12)
    rgb = np.stack([v["red"], v["green"], v["blue"]], -1).astype(np.float64) / 255.0
    return xyz, normals, rgb


def mean_spacing(xyz: np.ndarray, sample: int = 2000, seed: int = 0) -> float:
    """Median nearest-neighbour distance of a sample of the points to all of them."""
    pts = torch.from_numpy(xyz)
    idx = torch.randperm(len(pts), generator=torch.Generator().manual_seed(seed))[:sample]
    d = torch.cdist(pts[idx], pts)
    d[torch.arange(len(idx)), idx] = math.inf
    return float(d.min(dim=1).values.median())


def garage_scene(dataset: Path, n: int, seed: int = 0, sh_degree: int = 3) -> GaussianScene:
    """N Gaussians on the dataset's surfaces, sized like a trained scene: points resampled and jittered in
    their tangent plane, flat discs along the surface (tangent sigma ~ the spacing at N, normal sigma 10 % of
    it), mostly opaque, SH of degree ``sh_degree`` with the points' colours; stored spatially sorted, as
    ``parksim reconstruct`` stores trained scenes."""
    from ..geometry import quaternion_from_rotation

    xyz, normals, rgb = read_points(dataset)
    rng = np.random.default_rng(seed)
    spacing = mean_spacing(xyz)
    pick = rng.integers(0, len(xyz), n)
    nrm = normals[pick]
    helper = np.where(np.abs(nrm[:, 2:3]) < 0.9, [[0.0, 0.0, 1.0]], [[1.0, 0.0, 0.0]])
    t1 = np.cross(nrm, helper)
    t1 /= np.linalg.norm(t1, axis=-1, keepdims=True)
    t2 = np.cross(nrm, t1)
    spin = rng.uniform(0.0, 2 * math.pi, (n, 1))
    t1, t2 = np.cos(spin) * t1 + np.sin(spin) * t2, -np.sin(spin) * t1 + np.cos(spin) * t2
    radius = spacing * np.sqrt(rng.random((n, 1)))
    angle = rng.uniform(0.0, 2 * math.pi, (n, 1))
    means = xyz[pick] + radius * (np.cos(angle) * t1 + np.sin(angle) * t2)
    sigma = 0.6 * spacing * math.sqrt(len(xyz) / n) * np.exp(0.4 * rng.standard_normal((n, 2)))
    log_scales = np.log(np.concatenate([sigma, 0.1 * sigma.min(-1, keepdims=True)], -1))
    quats = quaternion_from_rotation(torch.from_numpy(np.stack([t1, t2, nrm], -1)))
    sh = 0.05 * rng.standard_normal((n, (sh_degree + 1) ** 2, 3))
    sh[:, 0] = (rgb[pick] - 0.5) / SH_C0
    opacity_logits = rng.normal(2.5, 1.5, n)
    means_t, quats_t, scales_t, opac_t, sh_t = (torch.as_tensor(a).to(torch.float32).contiguous()
                                                 for a in (means, quats, log_scales, opacity_logits, sh))
    return GaussianScene(means_t, quats_t, scales_t, opac_t, sh_t, sh_degree=sh_degree).spatially_sorted()


def cap_sh_degree(scene: GaussianScene, degree: int) -> GaussianScene:
    """The scene with its SH truncated to ``degree`` (view-dependent colour dropped above it; cheaper colour)."""
    degree = min(degree, scene.sh_degree)
    return GaussianScene(scene.means, scene.quats, scene.log_scales, scene.opacity_logits,
                         scene.sh[:, :(degree + 1) ** 2].contiguous(), sh_degree=degree)
