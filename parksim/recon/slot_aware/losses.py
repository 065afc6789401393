"""Slot-aware losses (paper "Training", reference lines 372-430): L_align, L_ipm, L_cam and the total.

Readings of the text:
* L_align (KL(pi^s || pi^t), line 388): Omega = the ``k`` grid cells with the largest teacher weight W^t;
  pi = softmax(W[Omega] / temperature) for W^s and W^t; KL(p || q) = sum p (log p - log q). The teacher is a
  constant (ground-truth BEV, frozen detector), so the gradient flows through the student path W^s.
* L_ipm (line 400) and L_cam (line 412): ||W * |pred - gt| ||_1 / ||W||_1 with W broadcast over the colour
  channels (numerator and denominator alike), i.e. a W-weighted mean absolute error. L_cam treats the four
  fisheye views as one image I_sur: one sum over all cameras in the numerator and in the denominator.
"""

from __future__ import annotations

from collections.abc import Mapping

import torch
from torch import Tensor

from ..losses import sum_terms

__all__ = ["align_loss", "weighted_l1", "ipm_loss", "cam_loss", "total_loss"]

_EPS = 1e-12


def align_loss(student: Tensor, teacher: Tensor, k: int, temperature: float = 1.0) -> Tensor:
    """KL(pi^s || pi^t) over the teacher's top-``k`` cells of weight maps of any (equal) shape."""
    s, t = student.flatten(), teacher.flatten()
    omega = t.detach().topk(min(k, t.numel())).indices
    log_ps = torch.log_softmax(s[omega] / temperature, dim=0)
    log_pt = torch.log_softmax(t[omega] / temperature, dim=0)
    return (log_ps.exp() * (log_ps - log_pt)).sum()


def _weighted_sums(pred: Tensor, gt: Tensor, weights: Tensor) -> tuple[Tensor, Tensor]:
    """Numerator and denominator of the weighted L1 of HxWxC images under an HxW weight map."""
    w = weights.unsqueeze(-1).expand_as(pred)
    return (w * (pred - gt).abs()).sum(), w.sum()


def weighted_l1(pred: Tensor, gt: Tensor, weights: Tensor) -> Tensor:
    """||W * |pred - gt| ||_1 / ||W||_1 for HxWxC images and an HxW weight map."""
    num, den = _weighted_sums(pred, gt, weights)
    return num / den.clamp_min(_EPS)


def ipm_loss(pred_bev: Tensor, gt_bev: Tensor, weights: Tensor) -> Tensor:
    """L_ipm: slot-weighted L1 between the rendered and the ground-truth IPM images."""
    return weighted_l1(pred_bev, gt_bev, weights)


def cam_loss(preds: Mapping[str, Tensor], gts: Mapping[str, Tensor], weights: Mapping[str, Tensor]) -> Tensor:
    """L_cam: the back-projected weights on the fisheye views, normalised over all cameras together."""
    sums = [_weighted_sums(preds[c], gts[c], weights[c]) for c in weights]
    return sum_terms(n for n, _ in sums) / sum_terms(d for _, d in sums).clamp_min(_EPS)


def total_loss(rgb: Tensor, align: Tensor, ipm: Tensor, cam: Tensor, lambda_align: float = 0.001,
               lambda_ipm: float = 0.1, lambda_cam: float = 0.1) -> Tensor:
    """L = L_rgb + lambda_align L_align + lambda_ipm L_ipm + lambda_cam L_cam (paper's final loss)."""
    return rgb + lambda_align * align + lambda_ipm * ipm + lambda_cam * cam
