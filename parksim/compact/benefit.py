"""What each Gaussian contributes to the training images: its blending weight alpha * T summed over their pixels.

The benefit side of ``parksim compact --ranking benefit-cost`` (Mini-Splatting's importance). It is read off a
differentiable render: with every colour the constant 0.5 (SH DC 0, inside the SH clamp) the image is
sum_g w_g c_g per pixel, so d(sum of image)/d(SH DC of g) = C0 * (sum of g's weights), for each channel.
"""

from __future__ import annotations

import torch
from torch import Tensor

from ..data import DatasetReader
from ..gaussians import SH_C0, GaussianScene
from ..render import render
from ..rig import Rig

__all__ = ["summed_weights"]


def summed_weights(scene: GaussianScene, rig: Rig, reader: DatasetReader, progress: bool = False) -> Tensor:
    """[N] float64 (CPU): each Gaussian's blending weight summed over every pixel of every (train frame, camera)
    view, rendered on the scene's device."""
    from tqdm import tqdm

    means, quats, scales, opacity = (t.detach().to(torch.float32) for t in
                                     (scene.means, scene.quats, scene.log_scales, scene.opacity_logits))
    total = torch.zeros(len(scene), dtype=torch.float64)
    views = [(f, c) for f in reader.split["train"] for c in rig.names]
    for frame, camera in tqdm(views, desc="benefit", unit="view", disable=not progress, dynamic_ncols=True):
        dc = torch.zeros(len(scene), 1, 3, device=means.device, requires_grad=True)
        image = render(GaussianScene(means, quats, scales, opacity, dc, 0), rig, reader.view_pose(camera, frame),
                       cameras=[camera]).images[camera]
        (grad,) = torch.autograd.grad(image[..., 0].sum(), dc)
        total += grad[:, 0, 0].double().cpu() / SH_C0
    return total
