"""Inputs of the render benchmarks: garage-like Gaussian scenes built from a dataset's surface points (random
scenes have other statistics than trained ones), trained bundles, an SH-degree cap of a scene, and untrained
bundles sampled on a synth garage's surfaces (for the simulator and planner benchmarks).
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import torch

from ..gaussians import SH_C0, GaussianScene

__all__ = ["garage_scene", "cap_sh_degree", "read_points", "mean_spacing", "surface_scene", "surface_bundle"]


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


def surface_scene(preset: str, n: int, seed: int = 0) -> tuple[GaussianScene, dict]:
    """``n`` flat Gaussians sampled on the surfaces of a synth preset's garage (floor, ceiling, pillars, walls, parked
    cars), coloured by its shader (slot lines included), and the garage's world map: a scene without training.

    Args:
        preset: a synth preset (``tiny``, ``scene1`` ...).
        n: number of Gaussians.
        seed: seed of the surface samples.

    Returns:
        The float32 scene (SH degree 0, flat along each surface's normal) and the world map (``scene_map``).
    """
    from ..geometry import quaternion_from_rotation
    from ..synth.generate import scene_map
    from ..synth.layout import build_garage
    from ..synth.points import sample_points
    from ..synth.presets import get_preset
    from ..synth.raycast import BoxSet
    from ..synth.rig import ego_box
    from ..synth.shading import Shader

    layout = get_preset(preset).layout
    garage = build_garage(layout)
    boxes = BoxSet.from_boxes([*garage.boxes, ego_box(np.eye(4))])
    materials = [b.material for b in garage.boxes] + ["ego"]
    colors = np.array([b.color for b in garage.boxes] + [(0.16, 0.17, 0.19)])
    shader = Shader(garage, boxes, materials, colors, layout.seed)
    span = np.stack([np.eye(4), np.eye(4)])
    span[1, 0, 3] = garage.length
    xyz, rgb, normals = sample_points(garage, shader, boxes, materials, span, n, seed, noise=0.005)
    nrm = normals / np.linalg.norm(normals, axis=1, keepdims=True)
    helper = np.where(np.abs(nrm[:, 2:3]) < 0.9, [[0.0, 0.0, 1.0]], [[1.0, 0.0, 0.0]])
    t1 = np.cross(helper, nrm)
    t1 /= np.linalg.norm(t1, axis=1, keepdims=True)
    frames = np.stack([t1, np.cross(nrm, t1), nrm], axis=2)   # third axis: the normal, the flat one
    sigma = 0.7 * math.sqrt(garage.length * (garage.y_max - garage.y_min) * 2.6 / n)
    log_scales = torch.tensor([math.log(sigma), math.log(sigma), math.log(0.01)], dtype=torch.float64).expand(n, 3)
    sh = ((torch.from_numpy(rgb).double() / 255.0 - 0.5) / SH_C0)[:, None, :]
    scene = GaussianScene(torch.from_numpy(xyz), quaternion_from_rotation(torch.from_numpy(frames)),
                          log_scales.clone(), torch.full((n,), 2.5, dtype=torch.float64), sh, 0).to(torch.float32)
    return scene, scene_map(garage)


def surface_bundle(out: Path, preset: str, n: int, seed: int = 0, size: tuple[int, int] | None = None,
                   bev_px: int | None = None) -> Path:
    """``surface_scene`` written as a scene bundle with the preset's rig and world map; the simulator benchmarks
    (and the tests' ``make_bundle``) drive planners and servers on it.

    Args:
        out: bundle folder to write (gaussians.ply, rig.json, map.json, bundle.json).
        preset: a synth preset (``tiny``, ``scene1`` ...).
        n: number of Gaussians.
        seed: seed of the surface samples.
        size: camera ``(width, height)``, default the preset's.
        bev_px: BEV side in pixels, default the preset's.

    Returns:
        ``out``. The Gaussians are stored spatially sorted, as ``parksim reconstruct`` stores them.
    """
    from .. import bundle as bundle_io
    from ..synth.presets import get_preset
    from ..synth.rig import avm_rig

    p = get_preset(preset)
    scene, world_map = surface_scene(preset, n, seed)
    width, height = size or (p.width, p.height)
    meta = {"source": f"synthetic garage {preset!r} (surface samples, not trained)", "gaussians": n}
    return bundle_io.save(out, bundle_io.Bundle(scene.spatially_sorted(), avm_rig(width, height, bev_px or p.bev_px),
                                                world_map, meta))
