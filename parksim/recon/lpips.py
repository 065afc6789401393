"""LPIPS (Zhang et al. 2018) in plain torch, from weights the user supplies by path.

Backbone: torchvision's ImageNet AlexNet (``alexnet-owt-7be5be79.pth``) or VGG16 (``vgg16-397923af.pth``)
state dict; heads: the LPIPS v0.1 linear layers (``alex.pth`` / ``vgg.pth`` of the ``lpips`` package).
Nothing is downloaded: without both files LPIPS is simply not computed.
"""

from __future__ import annotations

from pathlib import Path

import torch
import torch.nn.functional as F
from torch import Tensor, nn

__all__ = ["LPIPS", "LPIPSError"]

# (layer kind, out channels / kernel) in torchvision ``features`` index order; "M" = max-pool
_NETS = {
    "alex": ([("C", 64, 11, 4, 2), "R", "M3", ("C", 192, 5, 1, 2), "R", "M3", ("C", 384, 3, 1, 1), "R",
              ("C", 256, 3, 1, 1), "R", ("C", 256, 3, 1, 1), "R"], [1, 4, 7, 9, 11]),
    "vgg": ([("C", 64, 3, 1, 1), "R", ("C", 64, 3, 1, 1), "R", "M2", ("C", 128, 3, 1, 1), "R", ("C", 128, 3, 1, 1), "R",
             "M2"] + [("C", 256, 3, 1, 1), "R"] * 3 + ["M2"] + [("C", 512, 3, 1, 1), "R"] * 3 + ["M2"]
            + [("C", 512, 3, 1, 1), "R"] * 3, [3, 8, 15, 22, 29]),
}
_SHIFT = torch.tensor([-0.030, -0.088, -0.188]).view(1, 3, 1, 1)
_SCALE = torch.tensor([0.458, 0.448, 0.450]).view(1, 3, 1, 1)


class LPIPSError(ValueError):
    """LPIPS weight files are missing or do not fit the chosen network; the message names the file."""


def _features(spec: list) -> nn.Sequential:
    layers: list[nn.Module] = []
    channels = 3
    for item in spec:
        if item == "R":
            layers.append(nn.ReLU())
        elif isinstance(item, str):
            layers.append(nn.MaxPool2d(int(item[1]), 2))
        else:
            _, out, k, stride, pad = item
            layers.append(nn.Conv2d(channels, out, k, stride, pad))
            channels = out
    return nn.Sequential(*layers)


def _load(path: str | Path) -> dict[str, Tensor]:
    path = Path(path)
    if not path.is_file():
        raise LPIPSError(f"{path}: LPIPS weight file not found")
    try:
        return torch.load(path, map_location="cpu", weights_only=True)
    except Exception as e:  # torch.load raises many types for foreign files; all mean "unusable"
        raise LPIPSError(f"{path}: not a torch state dict ({type(e).__name__}: {e})") from None


class LPIPS:
    """``lpips(pred, gt, mask)``: LPIPS distance of HxWx3 [0,1] images, spatially averaged over ``mask``.

    The network runs on ``device`` (default the CPU); the images and mask must be there too.
    """

    def __init__(self, net: str, backbone_weights: str | Path, lpips_weights: str | Path,
                 device: torch.device | None = None) -> None:
        if net not in _NETS:
            raise LPIPSError(f"LPIPS network must be one of {sorted(_NETS)}, got {net!r}")
        spec, self.taps = _NETS[net]
        self.features = _features(spec).eval()
        backbone = {k[len("features."):]: v for k, v in _load(backbone_weights).items() if k.startswith("features.")}
        heads = _load(lpips_weights)
        try:
            self.features.load_state_dict(backbone)
            self.heads = [heads[f"lin{i}.model.1.weight"].float().to(device) for i in range(len(self.taps))]
        except (RuntimeError, KeyError) as e:
            raise LPIPSError(f"{backbone_weights} / {lpips_weights} do not fit LPIPS-{net}: {e}") from None
        self.features.to(device)
        self._shift, self._scale = _SHIFT.to(device), _SCALE.to(device)

    def _taps(self, x: Tensor) -> list[Tensor]:
        out = []
        for i, layer in enumerate(self.features):
            x = layer(x)
            if i in self.taps:
                out.append(x / (x.norm(dim=1, keepdim=True) + 1e-10))
            if i >= self.taps[-1]:
                break
        return out

    @torch.no_grad()
    def __call__(self, pred: Tensor, gt: Tensor, mask: Tensor) -> float:
        a, b = ((img.permute(2, 0, 1)[None].float() * 2 - 1 - self._shift) / self._scale for img in (pred, gt))
        m = mask[None, None].float()
        total = 0.0
        for fa, fb, w in zip(self._taps(a), self._taps(b), self.heads):
            d = F.conv2d((fa - fb) ** 2, w)
            mw = F.interpolate(m, size=d.shape[-2:], mode="area")
            total += float((d * mw).sum() / mw.sum().clamp(min=1e-6))
        return total
