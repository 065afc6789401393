"""What each Gaussian shows and costs at serving poses: its largest blending weight (alpha * T) in any camera,
and the Gaussian-pixel pairs it makes the compositor evaluate, over a set of poses.

Projection is ``render()``'s (same culling, unscented transform, per camera); colours are not needed, so
SH evaluation and compositing of colour are skipped and the weight pass (``rasterize.contribution``) runs
on the projected footprints instead. Pairs are counted on the compositor's tile bins: per tile a Gaussian
touches, its pixel rows in that tile times the tile width (the 16-pixel row spans the compositor walks), an
upper bound that ignores early termination.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from ..gaussians import GaussianScene
from ..geometry import as_pose, invert_transform
from ..render.project_fast import keep_torch_threads
from ..render.projection import project_gaussians
from ..render.rasterize.constants import TILE
from ..render.rasterize.contribution import max_weights
from ..render.rasterize.tiles import bin_gaussians
from ..rig import Rig

__all__ = ["PoseMeasure", "pose_measure", "pose_weights", "cell_weights", "tile_pairs"]


@dataclass(frozen=True)
class PoseMeasure:
    """Per Gaussian at one pose: largest blending weight over the cameras, and pairs summed over the cameras."""

    weights: Tensor   # [N] float32
    pairs: Tensor     # [N] float64


def tile_pairs(means2d: Tensor, conics: Tensor, opacities: Tensor, depths: Tensor, width: int, height: int) -> Tensor:
    """[M] float64: Gaussian-pixel pairs each projected Gaussian spans in the compositor's tiles (0 if culled)."""
    def f32(t: Tensor) -> np.ndarray:
        return np.ascontiguousarray(t.detach().to("cpu", torch.float32).numpy())

    m = means2d.shape[0]
    with keep_torch_threads():
        bins = bin_gaussians(f32(means2d), f32(conics), np.zeros((m, 3), np.float32), f32(opacities), f32(depths),
                             width, height)
    tile = np.repeat(np.arange(len(bins.offsets) - 1), np.diff(bins.offsets))
    g = bins.gauss_ids.astype(np.int64)
    top = (tile // bins.tiles_x) * TILE
    first, last = bins.packed[g, 10].astype(np.int64), bins.packed[g, 11].astype(np.int64)
    rows = np.clip(np.minimum(top + TILE - 1, last) - np.maximum(top, first) + 1, 0, None)
    pairs = np.bincount(g, weights=rows * TILE, minlength=m)
    return torch.from_numpy(pairs.astype(np.float64, copy=False))   # numpy gives int64 zeros when g is empty


@torch.no_grad()
def pose_measure(scene: GaussianScene, rig: Rig, pose: Tensor | Sequence[float],
                 cameras: Sequence[str] | None = None) -> PoseMeasure:
    """Each Gaussian's largest blending weight and its summed pairs over the pixels of ``cameras`` (default all).

    The projection runs on the scene's device, the weight and pair kernels on the CPU; the results are CPU tensors.
    """
    T_world_vehicle = as_pose(pose)
    opacity = torch.sigmoid(scene.opacity_logits)
    best = torch.zeros(len(scene), dtype=torch.float32)
    pairs = torch.zeros(len(scene), dtype=torch.float64)
    for name in cameras if cameras is not None else rig.names:
        cam = rig.cameras[name]
        T_camera_world = invert_transform(T_world_vehicle @ cam.T_vehicle_camera).to(scene.means.device,
                                                                                     scene.means.dtype)
        R, t = T_camera_world[:3, :3], T_camera_world[:3, 3]
        proj = project_gaussians(torch.addmm(t, scene.means, R.T), (scene.quats, scene.log_scales, R), cam.model)
        rows = proj.valid.nonzero().squeeze(1)
        index = proj.index[rows]
        footprint = (proj.means2d[rows], proj.conics[rows], opacity[index], proj.depths[rows],
                     cam.model.width, cam.model.height)
        index = index.cpu()
        best[index] = torch.maximum(best[index], max_weights(*footprint))   # a Gaussian appears once per camera
        pairs.index_add_(0, index, tile_pairs(*footprint))
    return PoseMeasure(best, pairs)


def pose_weights(scene: GaussianScene, rig: Rig, pose: Tensor | Sequence[float],
                 cameras: Sequence[str] | None = None) -> Tensor:
    """[N] float32: each Gaussian's largest blending weight over the pixels of ``cameras`` (default all) at ``pose``."""
    return pose_measure(scene, rig, pose, cameras).weights


def cell_weights(scene: GaussianScene, rig: Rig, poses: np.ndarray, cells: np.ndarray, n_cells: int,
                 progress: bool = False) -> tuple[Tensor, Tensor]:
    """Per cell, each Gaussian's largest weight over that cell's poses ([n_cells, N] float32), and its pairs
    summed over all poses ([N] float64); a tqdm bar if asked."""
    from tqdm import tqdm

    out = torch.zeros(n_cells, len(scene), dtype=torch.float32)
    pairs = torch.zeros(len(scene), dtype=torch.float64)
    for pose, c in tqdm(list(zip(poses, cells)), desc="measuring", unit="pose", disable=not progress,
                        dynamic_ncols=True):
        m = pose_measure(scene, rig, pose.tolist())
        torch.maximum(out[int(c)], m.weights, out=out[int(c)])
        pairs += m.pairs
    return out, pairs
