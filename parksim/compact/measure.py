"""How much each Gaussian shows: its largest blending weight (alpha * T) in any camera over a set of poses.

Projection is ``render()``'s (same culling, unscented transform, per camera); colours are not needed, so
SH evaluation and compositing of colour are skipped and the weight pass (``rasterize.contribution``) runs
on the projected footprints instead.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch
from torch import Tensor

from ..gaussians import GaussianScene
from ..geometry import as_pose, invert_transform
from ..render.projection import project_gaussians
from ..render.rasterize.contribution import max_weights
from ..rig import Rig

__all__ = ["pose_weights", "cell_weights"]


@torch.no_grad()
def pose_weights(scene: GaussianScene, rig: Rig, pose: Tensor | Sequence[float],
                 cameras: Sequence[str] | None = None) -> Tensor:
    """[N] float32: each Gaussian's largest blending weight over the pixels of ``cameras`` (default all) at ``pose``."""
    T_world_vehicle = as_pose(pose)
    opacity = torch.sigmoid(scene.opacity_logits)
    best = torch.zeros(len(scene), dtype=torch.float32)
    for name in cameras if cameras is not None else rig.names:
        cam = rig.cameras[name]
        T_camera_world = invert_transform(T_world_vehicle @ cam.T_vehicle_camera).to(scene.means.dtype)
        R, t = T_camera_world[:3, :3], T_camera_world[:3, 3]
        proj = project_gaussians(torch.addmm(t, scene.means, R.T), (scene.quats, scene.log_scales, R), cam.model)
        rows = proj.valid.nonzero().squeeze(1)
        index = proj.index[rows]
        w = max_weights(proj.means2d[rows], proj.conics[rows], opacity[index], proj.depths[rows],
                        cam.model.width, cam.model.height)
        best[index] = torch.maximum(best[index], w)   # a Gaussian appears at most once per camera
    return best


def cell_weights(scene: GaussianScene, rig: Rig, poses: np.ndarray, cells: np.ndarray, n_cells: int,
                 progress: bool = False) -> Tensor:
    """[n_cells, N] float32: per cell, each Gaussian's largest weight over that cell's poses (a tqdm bar if asked)."""
    from tqdm import tqdm

    out = torch.zeros(n_cells, len(scene), dtype=torch.float32)
    for pose, c in tqdm(list(zip(poses, cells)), desc="measuring", unit="pose", disable=not progress,
                        dynamic_ncols=True):
        torch.maximum(out[int(c)], pose_weights(scene, rig, pose.tolist()), out=out[int(c)])
    return out
