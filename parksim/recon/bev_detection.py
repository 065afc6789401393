"""Slot detection on test-frame BEVs: rendered (IPM of a reconstruction's views) vs ground truth.

The ground-truth BEV is the IPM of the dataset's fisheye images through the same mapping as the rendered one
(the paper's I_ipm^gt, its "GT-" rows), so the two differ only by what the reconstruction gets wrong.
Scores follow the detectors' own metrics (``parksim.recon.detectors.evaluate``): precision and recall at the
operating threshold, AP over a low-threshold sweep, summed over frames (not averaged per frame).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from parksim.data import DatasetReader
from parksim.gaussians import GaussianScene
from parksim.render import bev_ipm

from .detectors import DecodeOptions, Detections, Detector, SlotLabels
from .detectors.evaluate import Evaluator, Metrics
from .detectors.protocols import ParkSimProtocol, Protocol
from .evaluate import Response, render_view

__all__ = ["TestBEV", "DetectionScore", "gt_bevs", "rendered_bevs", "score_detector"]


@dataclass
class TestBEV:
    """One test frame's BEV (HxWx3 in [0, 1]) with its slot labels in BEV pixels."""

    frame: int
    bev: Tensor
    labels: SlotLabels


@dataclass
class DetectionScore:
    """A detector's metrics over a set of BEVs and its detections on each (in the BEVs' order)."""

    points: Metrics
    slots: Metrics
    detections: list[Detections]


def _labels(reader: DatasetReader, frame: int) -> SlotLabels:
    bev = reader.rig.bev
    return SlotLabels.from_parksim(reader.labels(frame), bev.width, bev.height, bev.m_per_px)


def _check(reader: DatasetReader, frames: list[int]) -> None:
    if not reader.has_labels:
        raise ValueError(f"{reader.layout.root}: BEV detection needs slot labels (labels/)")
    if not frames:
        raise ValueError(f"{reader.layout.root}: no test frames in split.json")


@torch.no_grad()
def gt_bevs(reader: DatasetReader, frames: list[int]) -> list[TestBEV]:
    """IPM of the dataset's images of each frame."""
    _check(reader, frames)
    ipm = bev_ipm(reader.rig)
    return [TestBEV(f, ipm({c: reader.image(c, f) for c in ipm.cameras}), _labels(reader, f)) for f in frames]


@torch.no_grad()
def rendered_bevs(scene: GaussianScene, reader: DatasetReader, frames: list[int], response: Response | None,
                  backend: str = "auto", method: str = "ut") -> list[TestBEV]:
    """IPM of the scene's views of each frame (projection ``method``), through the learned camera response and
    clipped to [0, 1]; rendered on the scene's device, returned on the CPU (where the detectors and drawing run)."""
    _check(reader, frames)
    ipm = bev_ipm(reader.rig)
    return [TestBEV(f, ipm({c: render_view(scene, reader, f, c, response, backend, method=method).clamp(0.0, 1.0)
                            for c in ipm.cameras}).cpu(), _labels(reader, f)) for f in frames]


@torch.no_grad()
def score_detector(model: Detector, bevs: list[TestBEV], decode: DecodeOptions = DecodeOptions(),
                   protocol: Protocol = ParkSimProtocol()) -> DetectionScore:
    """Detect on every BEV and score against its labels under ``protocol`` (which sets the border margin)."""
    model.eval()
    evaluator = Evaluator(protocol)
    decode = protocol.decode_options(decode)
    sweep_opts = protocol.sweep_options(decode)
    detections = []
    for item in bevs:
        image = item.bev.permute(2, 0, 1)[None]
        maps, extras = model.run(image)
        size = (image.shape[-1], image.shape[-2])
        det = model.decode(maps, extras, size, item.labels.m_per_px, decode)[0]
        evaluator.add(det, model.decode(maps, extras, size, item.labels.m_per_px, sweep_opts)[0], item.labels)
        detections.append(det)
    result = evaluator.result()
    return DetectionScore(result["points"], result["slots"], detections)
