"""Trainable Gaussian parameters with their Adam optimizer, and the surgery densification needs.

Each attribute is its own leaf tensor and Adam param group (so each has its own learning rate);
growing, pruning or overwriting Gaussians keeps the optimizer's moments aligned row by row.
"""

from __future__ import annotations

import torch
from torch import Tensor

from parksim.gaussians import GaussianScene

__all__ = ["GaussianParams", "NAMES"]

NAMES = ("means", "quats", "log_scales", "opacity_logits", "sh0", "shN")
"""Attribute names; also the optimizer's param-group names."""


class GaussianParams:
    """The trainable attributes (float32 leaves) and one Adam optimizer with a param group per attribute.

    The tensors live on one device (``device``, default the given tensors'); Adam's fused kernel runs there.
    """

    def __init__(self, tensors: dict[str, Tensor], lrs: dict[str, float], device: torch.device | None = None) -> None:
        self.tensors = {k: tensors[k].detach().to(device=device, dtype=torch.float32).clone().requires_grad_(True)
                        for k in NAMES}
        self.optimizer = torch.optim.Adam([{"params": [self.tensors[k]], "lr": lrs[k], "name": k} for k in NAMES],
                                          eps=1e-15, fused=True)

    @classmethod
    def from_scene(cls, scene: GaussianScene, max_sh_degree: int, lrs: dict[str, float],
                   device: torch.device | None = None) -> GaussianParams:
        """Split SH into DC and rest, zero-padding the rest up to ``max_sh_degree``; on ``device`` (default the
        scene's)."""
        n, k = len(scene), (max_sh_degree + 1) ** 2
        rest = torch.zeros(n, k - 1, 3, dtype=scene.sh.dtype, device=scene.sh.device)
        m = min(k, scene.sh.shape[1]) - 1
        rest[:, :m] = scene.sh[:, 1:m + 1]
        return cls({"means": scene.means, "quats": scene.quats, "log_scales": scene.log_scales,
                    "opacity_logits": scene.opacity_logits, "sh0": scene.sh[:, :1], "shN": rest}, lrs, device)

    def __len__(self) -> int:
        return self.tensors["means"].shape[0]

    def __getitem__(self, name: str) -> Tensor:
        return self.tensors[name]

    def scene(self, sh_degree: int) -> GaussianScene:
        """A differentiable ``GaussianScene`` view using SH up to ``sh_degree``."""
        t = self.tensors
        k = (sh_degree + 1) ** 2
        sh = torch.cat([t["sh0"], t["shN"][:, :k - 1]], dim=1)
        return GaussianScene(t["means"], t["quats"], t["log_scales"], t["opacity_logits"], sh, sh_degree)

    def set_lr(self, name: str, lr: float) -> None:
        """Set one attribute's learning rate."""
        for group in self.optimizer.param_groups:
            if group["name"] == name:
                group["lr"] = lr

    def _replace(self, name: str, value: Tensor, state_fn) -> None:
        """Swap attribute ``name`` for ``value`` and remap its Adam moments with ``state_fn(moment) -> moment``."""
        old = self.tensors[name]
        new = value.detach().contiguous().requires_grad_(True)
        state = self.optimizer.state.pop(old, None)
        for group in self.optimizer.param_groups:
            if group["name"] == name:
                group["params"] = [new]
        if state is not None:
            for key in ("exp_avg", "exp_avg_sq"):
                state[key] = state_fn(state[key])
            self.optimizer.state[new] = state
        self.tensors[name] = new

    def keep(self, mask: Tensor) -> None:
        """Drop the Gaussians where ``mask`` is False."""
        for name in NAMES:
            self._replace(name, self.tensors[name][mask], lambda m: m[mask])

    def append(self, rows: dict[str, Tensor]) -> None:
        """Add Gaussians (one tensor per attribute); their moments start at zero."""
        for name in NAMES:
            extra = rows[name].to(torch.float32)
            self._replace(name, torch.cat([self.tensors[name].detach(), extra]),
                          lambda m, e=extra: torch.cat([m, torch.zeros_like(e)]))

    def overwrite(self, index: Tensor, rows: dict[str, Tensor]) -> None:
        """Set the Gaussians at ``index`` to ``rows`` (any subset of attributes); their moments restart at zero."""
        for name, value in rows.items():
            data = self.tensors[name].detach().clone()
            data[index] = value.to(torch.float32)

            def reset(m: Tensor) -> Tensor:
                m = m.clone()
                m[index] = 0
                return m

            self._replace(name, data, reset)

    @torch.no_grad()
    def snapshot(self) -> GaussianScene:
        """A detached copy of the full scene (all SH coefficients)."""
        s = self.scene(self.max_sh_degree)
        return GaussianScene(s.means.clone(), s.quats.clone(), s.log_scales.clone(), s.opacity_logits.clone(),
                             s.sh.clone(), s.sh_degree)

    @property
    def max_sh_degree(self) -> int:
        return int(round((self.tensors["shN"].shape[1] + 1) ** 0.5)) - 1
