"""One slot-aware training step for a frame (paper "Slot-aware Reconstruction" + "Training", lines 228-430).

Render the frame's four fisheye views, apply the learned camera response (so the rendered views are the
I_sur_hat that L_rgb compares), build I_ipm_hat = Phi_IPM(I_sur_hat) and the ground truth
I_ipm_gt = Phi_IPM(I_sur) with the same IPM (the paper: "using the same IPM mapping"), run the frozen
detector on both (teacher without gradient, student with gradient when L_align is on), build W_mix'
(corners, plus edge tubes for a GCN detector), and return L_rgb, L_align, L_ipm, L_cam and their total.
Slot weights live only where the IPM sees the ground (``IPM.mask``) and, in the cameras, on valid pixels.
Frames whose ground truth has no slot skip the detector and the slot terms (L_rgb only).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import TypeVar

import torch
from torch import Tensor, nn

from parksim.data import DatasetReader
from parksim.gaussians import GaussianScene
from parksim.render import bev_ipm, render
from parksim.rig import Rig

from ..detectors import Detector, GCNDetector
from ..losses import photometric_loss, sum_terms
from .config import SlotAwareConfig
from .losses import align_loss, cam_loss, ipm_loss, total_loss
from .variants import spec_of
from .weights import edge_weights, mix, shape_confidence, upsample

__all__ = ["SlotFrame", "SlotAwareTerms", "SlotAwareStep", "freeze", "frame_has_slots"]

Response = Callable[[Tensor, str], Tensor]
_Net = TypeVar("_Net", bound=nn.Module)

@dataclass
class SlotFrame:
    """Ground truth of one frame: fisheye ``images`` (HxWx3), valid-pixel ``masks`` (HxW) and whether it has slots."""

    images: dict[str, Tensor]
    masks: dict[str, Tensor]
    has_slots: bool

@dataclass
class SlotAwareTerms:
    """Loss terms of one step (zero when off or skipped) and the rendered views they were computed on."""

    total: Tensor
    rgb: Tensor
    align: Tensor
    ipm: Tensor
    cam: Tensor
    images: dict[str, Tensor]
    skipped: bool

    def record(self) -> dict[str, float | bool]:
        """Plain numbers for the metrics log."""
        return {"loss": float(self.total.detach()), "rgb_loss": float(self.rgb.detach()),
                "align_loss": float(self.align.detach()), "ipm_loss": float(self.ipm.detach()),
                "cam_loss": float(self.cam.detach()), "slot_skipped": self.skipped}

def freeze(detector: _Net) -> _Net:
    """Eval mode, no parameter gradients: the detector guides, it is never trained here."""
    detector.eval()
    detector.requires_grad_(False)
    return detector

def frame_has_slots(reader: DatasetReader, frame: int) -> bool:
    """Whether the frame's labels hold a slot; frames of a dataset without labels count as having slots."""
    return not reader.has_labels or bool(reader.labels(frame)["slots"])

def _nchw(bev: Tensor) -> Tensor:
    """HxWx3 BEV -> the detector's ``[1, 3, H, W]``."""
    return bev.permute(2, 0, 1)[None]

class SlotAwareStep:
    """The slot-aware losses of one frame for a rig, a frozen detector and a ``SlotAwareConfig``."""

    def __init__(self, rig: Rig, detector: Detector | None, cfg: SlotAwareConfig, ssim_lambda: float = 0.2,
                 backend: str = "auto", response: Response | None = None, cameras: Sequence[str] | None = None) -> None:
        self.rig, self.cfg, self.ssim_lambda, self.backend, self.response = rig, cfg, ssim_lambda, backend, response
        self.spec = spec_of(cfg.variant)
        if self.spec.uses_detector and detector is None:
            raise ValueError(f"slot-aware variant {cfg.variant.value!r} needs a detector (slot_aware.detector)")
        self.detector = freeze(detector) if detector is not None else None
        self.ipm = bev_ipm(rig, cameras=cameras)  # the same grids render(..., bev=True) uses, built once

    def __call__(self, scene: GaussianScene, pose: Tensor | Sequence[float], frame: SlotFrame) -> SlotAwareTerms:
        """Render ``frame`` at ``pose`` and compute its loss terms (differentiable in the scene's tensors)."""
        preds = render(scene, self.rig, pose, cameras=self.ipm.cameras, backend=self.backend).images
        if self.response is not None:
            preds = {c: self.response(img, c) for c, img in preds.items()}
        rgb = sum_terms(photometric_loss(_nchw(preds[c]), _nchw(frame.images[c]), frame.masks[c][None, None],
                                         self.ssim_lambda) for c in preds) / len(preds)
        zero = rgb.new_zeros(())
        if self.spec.uses_detector and not frame.has_slots:
            return SlotAwareTerms(rgb, rgb, zero, zero, zero, preds, skipped=True)
        pred_bev, gt_bev = self.ipm(preds), self.ipm(frame.images)
        align, weights = zero, None
        if self.spec.uses_detector:
            w_student, w_teacher = self._corners(pred_bev), self._corners(gt_bev, teacher=True)
            if self.spec.align:
                align = align_loss(w_student, w_teacher, self.cfg.align_top_k, self.cfg.align_temperature)
            if self.spec.weights == "slot":
                weights = self._slot_weights(w_teacher, w_student, gt_bev, pred_bev)
        elif self.spec.weights == "uniform":
            weights = self.ipm.mask.to(pred_bev)
        ipm = ipm_loss(pred_bev, gt_bev, weights) if self.spec.ipm and weights is not None else zero
        cam = zero
        if self.spec.cam and weights is not None:
            cam_weights = {c: w * frame.masks[c] for c, w in self.ipm.to_cameras(weights).items()}
            cam = cam_loss(preds, frame.images, cam_weights)
        c = self.cfg
        total = total_loss(rgb, align, ipm, cam, c.lambda_align, c.lambda_ipm, c.lambda_cam)
        return SlotAwareTerms(total, rgb, align, ipm, cam, preds, skipped=False)

    def _share(self, configured: float) -> float:
        """Teacher share: the variant's override (teacher-only 1, student-only 0) or the configured alpha/beta."""
        return configured if self.spec.teacher_share is None else self.spec.teacher_share

    def _corners(self, bev: Tensor, teacher: bool = False) -> Tensor:
        """Shaped corner weights ``[1, 1, G, G]``; with gradient only on the student path of L_align."""
        assert self.detector is not None
        with torch.set_grad_enabled(not teacher and self.spec.align and torch.is_grad_enabled()):
            conf = self.detector.confidence(_nchw(bev))
        return shape_confidence(conf, self.cfg.tau, self.cfg.temperature, self.cfg.gamma)

    @torch.no_grad()
    def _edges(self, bev: Tensor) -> Tensor:
        """GCN edge-tube map ``[H, W]`` of one BEV (constant: the tubes depend on detected corner locations only).

        The tubes are drawn on the CPU (each around a decoded corner pair, a host-side list) and moved to ``bev``'s
        device."""
        assert isinstance(self.detector, GCNDetector)
        points, scores = self.detector.edges(_nchw(bev))[0]
        c = self.cfg
        tubes = edge_weights(points.cpu(), scores.cpu(), c.edge_top_k, (bev.shape[0], bev.shape[1]), c.edge_sigma,
                             c.edge_samples)
        return tubes.to(bev.device)

    def _slot_weights(self, w_teacher: Tensor, w_student: Tensor, gt_bev: Tensor, pred_bev: Tensor) -> Tensor:
        """W_mix' = upsample(W_mix) + lambda_edge W_edge on the IPM's ground area, ``[H, W]``."""
        size = (gt_bev.shape[0], gt_bev.shape[1])
        weights = upsample(mix(w_teacher, w_student, self._share(self.cfg.alpha)), size)[0, 0]
        if isinstance(self.detector, GCNDetector) and self.cfg.lambda_edge > 0 and self.cfg.edge_top_k > 0:
            edges = mix(self._edges(gt_bev), self._edges(pred_bev), self._share(self.cfg.beta))
            weights = weights + self.cfg.lambda_edge * edges
        return weights * self.ipm.mask.to(weights)

