"""3DGS as Markov Chain Monte Carlo (Kheradmand et al. 2024), following gsplat's ``MCMCStrategy``, on any device.

Every ``refine_every`` steps: dead Gaussians (opacity below ``min_opacity``) are relocated onto live ones
sampled by opacity, and ``grow_rate`` more are added the same way up to ``cap_max``; a sampled Gaussian
and its copies share its opacity and scale by the paper's correction so that the rendered distribution
is unchanged. Every step: position noise shaped by each covariance, gated to low-opacity Gaussians.
Loss regularisers on mean opacity and mean scale drive unneeded Gaussians to die. Everything runs on the
Gaussians' device with the step's generator (which must be on that device too); off the CPU the per-step noise is
computed for every Gaussian and gated there, so the step needs no host synchronisation.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from parksim.render.projection import covariance_sqrt

from .config import DensifyConfig
from .params import NAMES, GaussianParams
from .strategy_base import StepInfo, Strategy

__all__ = ["MCMCStrategy", "relocation_correction"]

_GATE_MIN = 1e-8
N_MAX = 51
"""Largest number of copies one Gaussian is split into per relocation (gsplat's table size)."""


def _relocation_weights() -> Tensor:
    """``W[n, k] = sum_{i=k+1..n} C(i-1, k) (-1)^k / sqrt(k+1)``: the scale correction is sum_k W[n,k] o^(k+1)."""
    W = torch.zeros(N_MAX + 1, N_MAX, dtype=torch.float64)
    for n in range(1, N_MAX + 1):
        for k in range(n):
            W[n, k] = sum(math.comb(i - 1, k) for i in range(k + 1, n + 1)) * (-1) ** k / math.sqrt(k + 1)
    return W


_WEIGHTS = _relocation_weights()
_DEVICE_WEIGHTS: dict[torch.device, Tensor] = {}


def _weights_on(device: torch.device) -> Tensor:
    """``_WEIGHTS`` on ``device`` (copied once per device)."""
    if device.type == "cpu":
        return _WEIGHTS
    if device not in _DEVICE_WEIGHTS:
        _DEVICE_WEIGHTS[device] = _WEIGHTS.to(device)
    return _DEVICE_WEIGHTS[device]


def relocation_correction(opacity: Tensor, scales: Tensor, copies: Tensor) -> tuple[Tensor, Tensor]:
    """Opacity and scales of each of ``copies`` Gaussians replacing one (Kheradmand et al., eq. 9).

    ``1 - (1 - o')^n = o`` keeps the opacity of the stack; the scale factor keeps the stack's
    rendered footprint. Computed in float64: the alternating binomial sum cancels badly in float32.
    """
    n = copies.clamp(1, N_MAX).long()
    o = opacity.to(torch.float64)
    new_o = 1.0 - (1.0 - o) ** (1.0 / n)
    powers = new_o[:, None] ** torch.arange(1, N_MAX + 1, dtype=torch.float64, device=o.device)
    denom = (_weights_on(n.device)[n] * powers).sum(dim=1)
    new_scales = (o / denom)[:, None] * scales.to(torch.float64)
    return new_o.to(opacity.dtype), new_scales.to(scales.dtype)


def _op_sigmoid(x: Tensor, k: float = 100.0, x0: float = 0.995) -> Tensor:
    """Sharp gate of the position noise: ~1 for nearly transparent Gaussians, ~0 for opaque ones."""
    return torch.sigmoid(k * (x - x0))


class MCMCStrategy(Strategy):
    """Relocate / add / perturb as in 3DGS-MCMC; see the module docstring."""

    def __init__(self, densify: DensifyConfig, extent: float) -> None:
        self.cfg = densify.mcmc

    def step_pre_backward(self, params: GaussianParams, info: StepInfo) -> Tensor:
        """Opacity and scale L1 regularisers (mean over Gaussians)."""
        return (self.cfg.opacity_reg * torch.sigmoid(params["opacity_logits"]).mean()
                + self.cfg.scale_reg * torch.exp(params["log_scales"]).mean())

    @torch.no_grad()
    def step_post_update(self, params: GaussianParams, info: StepInfo) -> dict[str, int]:
        """Refine on schedule, then inject position noise; returns counts of relocated and added Gaussians."""
        c, generator = self.cfg, info.generator
        stats = {}
        if c.refine_start < info.step < c.refine_stop and info.step % c.refine_every == 0:
            stats["relocated"] = self._relocate(params, generator)
            stats["added"] = self._add(params, generator)
        self._inject_noise(params, info.means_lr * c.noise_lr, generator)
        return stats

    def _sample(self, params: GaussianParams, candidates: Tensor, n: int,
                generator: torch.Generator) -> tuple[Tensor, dict[str, Tensor]]:
        """Pick ``n`` of ``candidates`` by opacity; return them and their corrected opacity/scale rows."""
        opacity = torch.sigmoid(params["opacity_logits"].detach())
        picked = candidates[torch.multinomial(opacity[candidates], n, replacement=True, generator=generator)]
        copies = torch.bincount(picked, minlength=len(params))[picked] + 1
        new_o, new_s = relocation_correction(opacity[picked], torch.exp(params["log_scales"].detach()[picked]), copies)
        eps = torch.finfo(torch.float32).eps
        new_o = new_o.clamp(min=self.cfg.min_opacity, max=1.0 - eps)
        return picked, {"opacity_logits": torch.logit(new_o), "log_scales": torch.log(new_s)}

    def _relocate(self, params: GaussianParams, generator: torch.Generator) -> int:
        """Move dead Gaussians onto live ones (and split the live ones' opacity and scale)."""
        dead = torch.sigmoid(params["opacity_logits"].detach()) <= self.cfg.min_opacity
        n_dead = int(dead.sum())
        if n_dead == 0 or n_dead == len(params):
            return 0
        picked, corrected = self._sample(params, (~dead).nonzero().squeeze(1), n_dead, generator)
        params.overwrite(picked, corrected)
        rows = {name: params[name].detach()[picked] for name in NAMES}
        params.overwrite(dead.nonzero().squeeze(1), rows)
        return n_dead

    def _add(self, params: GaussianParams, generator: torch.Generator) -> int:
        """Grow by ``grow_rate`` (up to ``cap_max``) with copies of Gaussians sampled by opacity."""
        n = len(params)
        n_new = max(0, min(self.cfg.cap_max, int((1.0 + self.cfg.grow_rate) * n)) - n)
        if n_new == 0:
            return 0
        picked, corrected = self._sample(params, torch.arange(n, device=params["means"].device), n_new, generator)
        params.overwrite(picked, corrected)
        params.append({name: params[name].detach()[picked] for name in NAMES})
        return n_new

    def _inject_noise(self, params: GaussianParams, scale: float, generator: torch.Generator) -> None:
        """Add ``scale * Sigma * eps * gate(opacity)`` to the means (Sigma = R S^2 R^T).

        Only Gaussians whose gate exceeds ``_GATE_MIN`` move (the rest would move by < 1e-8 of the noise): on the
        CPU those are picked out first, on a GPU the noise of the others is zeroed (no data-dependent shape).
        """
        if scale == 0:
            return
        means = params["means"]
        eps = torch.randn(means.shape, generator=generator, device=means.device)
        gate = _op_sigmoid(1.0 - torch.sigmoid(params["opacity_logits"].detach()))
        if means.device.type != "cpu":
            L = covariance_sqrt(params["quats"].detach(), params["log_scales"].detach())
            noise = (L @ (L.transpose(1, 2) @ (eps * gate[:, None] * scale)[:, :, None])).squeeze(2)
            means.data.add_(torch.where((gate > _GATE_MIN)[:, None], noise, 0.0))
            return
        moving = (gate > _GATE_MIN).nonzero().squeeze(1)
        L = covariance_sqrt(params["quats"].detach()[moving], params["log_scales"].detach()[moving])
        noise = (L @ (L.transpose(1, 2) @ (eps[moving] * gate[moving, None] * scale)[:, :, None])).squeeze(2)
        params["means"].data.index_add_(0, moving, noise)
