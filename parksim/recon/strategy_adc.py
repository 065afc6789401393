"""Adaptive density control of the original 3DGS (Kerbl et al. 2023): clone, split, prune, opacity reset.

Runs on the Gaussians' device with the step's generator (on that device too); its accumulators follow them there.

The renderer does not expose screen-space mean gradients, so the view-space gradient 3DGS thresholds is
estimated from the world-space one: |dL/d ndc| ~= |dL/dx| * distance / focal * width / 2 (the Gaussian's
image-plane motion per metre of lateral motion), in the first rendered view of each iteration.
"""

from __future__ import annotations

import math
from typing import Any

import torch
from torch import Tensor

from parksim.geometry import rotation_from_quaternion

from .config import DensifyConfig
from .params import NAMES, GaussianParams
from .strategy_base import StepInfo, Strategy

__all__ = ["ADCStrategy"]

_SPLIT_SHRINK = 1.6  # 3DGS: split children get scale / (0.8 * 2)
_RESET_OPACITY = 0.01


class ADCStrategy(Strategy):
    """Clone small / split large Gaussians with high view-space gradients; prune transparent and huge ones."""

    def __init__(self, densify: DensifyConfig, extent: float) -> None:
        self.cfg, self.extent = densify.adc, extent
        self.grad_sum = torch.zeros(0)
        self.count = torch.zeros(0)

    @torch.no_grad()
    def step_post_backward(self, params: GaussianParams, info: StepInfo) -> None:
        """Accumulate the estimated view-space gradient norm of every Gaussian the first view touched."""
        device = params["means"].device
        if len(self.grad_sum) != len(params):
            self.grad_sum, self.count = torch.zeros(len(params), device=device), torch.zeros(len(params), device=device)
        grad = params["means"].grad
        if grad is None or not info.views:
            return
        view = info.views[0]
        dist = (params["means"].detach() - view.centre.to(device=device, dtype=torch.float32)).norm(dim=1)
        norm = grad.norm(dim=1) * dist / view.focal * view.width / 2
        seen = grad.abs().sum(dim=1) > 0
        self.grad_sum += torch.where(seen, norm, 0.0)
        self.count += seen.float()

    @torch.no_grad()
    def step_post_update(self, params: GaussianParams, info: StepInfo) -> dict[str, int]:
        """Densify and prune on schedule; reset opacities every ``reset_every`` steps."""
        c, step, device = self.cfg, info.step, params["means"].device
        stats: dict[str, int] = {}
        if c.refine_start < step < c.refine_stop and step % c.refine_every == 0:
            stats = self._refine(params, step, info.generator)
            self.grad_sum, self.count = torch.zeros(len(params), device=device), torch.zeros(len(params), device=device)
        if step < c.refine_stop and step % c.reset_every == 0:
            limit = math.log(_RESET_OPACITY / (1 - _RESET_OPACITY))
            clamped = params["opacity_logits"].detach().clamp(max=limit)
            params.overwrite(torch.arange(len(params), device=device), {"opacity_logits": clamped})
        return stats

    def _refine(self, params: GaussianParams, step: int, generator: torch.Generator) -> dict[str, int]:
        """One 3DGS densification round: clone, split, then prune."""
        c = self.cfg
        avg = self.grad_sum / self.count.clamp(min=1)
        hot = avg >= c.grad_threshold
        room = max(0, c.cap_max - len(params))
        max_scale = torch.exp(params["log_scales"].detach()).amax(dim=1)
        small = max_scale <= c.percent_dense * self.extent
        clone = (hot & small).nonzero().squeeze(1)[:room]
        split = (hot & ~small).nonzero().squeeze(1)[:max(0, room - len(clone)) // 2]
        n = len(params)
        rows = {name: params[name].detach()[clone] for name in NAMES}
        children = self._split_children(params, split, generator)
        params.append({name: torch.cat([rows[name], children[name]]) for name in NAMES})
        opacity = torch.sigmoid(params["opacity_logits"].detach())
        drop = opacity < c.min_opacity
        drop[split] = True
        if step > c.reset_every:
            drop |= torch.exp(params["log_scales"].detach()).amax(dim=1) > c.max_screen_fraction * self.extent
        drop[n:] &= opacity[n:] < c.min_opacity
        params.keep(~drop)
        return {"cloned": len(clone), "split": len(split), "pruned": int(drop.sum())}

    @staticmethod
    def _split_children(params: GaussianParams, index: Tensor, generator: torch.Generator) -> dict[str, Tensor]:
        """Two children per Gaussian: positions sampled from it, scales shrunk by 1.6."""
        rows = {name: params[name].detach()[index].repeat_interleave(2, dim=0) for name in NAMES}
        scales = torch.exp(rows["log_scales"])
        offset = torch.randn(scales.shape, generator=generator, device=scales.device) * scales
        rows["means"] = rows["means"] + (rotation_from_quaternion(rows["quats"]) @ offset[:, :, None]).squeeze(2)
        rows["log_scales"] = rows["log_scales"] - math.log(_SPLIT_SHRINK)
        return rows

    def state_dict(self) -> dict[str, Any]:
        """Gradient accumulators (they span refine intervals, so a resume needs them)."""
        return {"grad_sum": self.grad_sum.clone(), "count": self.count.clone()}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restore ``state_dict`` output (on the device the Gaussians are on: the trainer moves it there)."""
        self.grad_sum, self.count = state["grad_sum"].clone(), state["count"].clone()
