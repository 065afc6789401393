"""The paper's experiments on one dataset: novel-view scores and BEV slot detection of several reconstructions.

For each reconstruction (a scene bundle) it scores the test views (PSNR/SSIM over the whole valid image and
over slot regions, ``parksim.recon.evaluate``) and runs every given detector on the rendered BEVs of the test frames;
each detector also runs once on the ground-truth BEVs (the "GT-" rows). A dataset's off-path split (``parksim
offpath``) is scored the same way per offset group (one code path, ``_Split``, parameterised by the reader).
Writes ``tables.json`` (all numbers), ``tables.md`` (``parksim.recon.paper_tables``) and one ``panel_<detector>.png`` of
ground-truth vs rendered BEVs with labels and detections.
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
import torch

from parksim.bundle import Bundle, load
from parksim.data import DatasetReader
from parksim.fileio import write_json
from parksim.synth.offpath import group_frames, read_offpath

from .bev_detection import DetectionScore, TestBEV, gt_bevs, rendered_bevs, score_detector
from .bev_draw import caption, draw_detections, draw_labels, write_grid
from .config import load_config
from .detectors import DecodeOptions, Detections, Detector
from .detectors.protocols import ParkSimProtocol, Protocol
from .evaluate import evaluate_views, group_means, offpath_split
from .paper_tables import DETECTOR_TITLES, tables_markdown
from .reconstruct import CONFIG_FILE
from .response import CameraResponse
from .slot_aware import Variant

__all__ = ["RunInfo", "describe_run", "evaluate_runs", "VARIANT_TITLES"]

VARIANT_TITLES = {Variant.DIRECT_IPM: "Direct IPM L1 supervision",
                  Variant.FEATURE_ONLY: "Feature-level supervision only",
                  Variant.TEACHER_ONLY: "Teacher-only weighting", Variant.STUDENT_ONLY: "Student-only weighting",
                  Variant.FULL: "Full slot-aware"}
"""Row names of the paper's ablation table."""
_TEST = "test"
"""The one group of the recorded test frames."""


@dataclass(frozen=True)
class RunInfo:
    """What a bundle is: its row label, training phase, slot-aware variant and guide detector (kind), iterations."""

    label: str
    phase: str
    variant: str | None
    detector: str | None
    iterations: int


def describe_run(scene_dir: Path, label: str | None = None) -> RunInfo:
    """Read a bundle's phase from ``bundle.json`` and its variant and detector from its ``config.yaml``."""
    meta = json.loads((Path(scene_dir) / "bundle.json").read_text())
    phase, iterations = meta.get("phase", "photometric"), int(meta.get("iterations", 0))
    if phase != "slot_aware":
        return RunInfo(label or "Photometric only", phase, None, None, iterations)
    sa = load_config(Path(scene_dir) / CONFIG_FILE).slot_aware
    kind = sa.detector.kind if sa.detector is not None else None
    default = VARIANT_TITLES[sa.variant] + (f" w/ {DETECTOR_TITLES[kind]}" if kind else "")
    return RunInfo(label or default, phase, sa.variant.value, kind, iterations)


def _scores(score: DetectionScore) -> dict[str, Any]:
    return {"points": asdict(score.points), "slots": asdict(score.slots)}


def _annotated(item: TestBEV, det: Detections, title: str) -> np.ndarray:
    """The BEV as uint8 RGB with its labels, ``det`` and a caption."""
    img = np.ascontiguousarray((item.bev.clamp(0, 1).numpy() * 255.0 + 0.5).astype(np.uint8))
    draw_labels(img, item.labels)
    draw_detections(img, det)
    caption(img, f"{title}: {len(det.points)} pts, {len(det.slots)} slots")
    return img


def _by_group(model: Detector, bevs: list[TestBEV], groups: dict[str, list[int]], decode: DecodeOptions,
              protocol: Protocol) -> dict[str, DetectionScore]:
    """``score_detector`` over the BEVs of each group of frames (detections in the group's frame order)."""
    by_frame = {b.frame: b for b in bevs}
    return {g: score_detector(model, [by_frame[f] for f in frames], decode, protocol) for g, frames in groups.items()}


@dataclass
class _Split:
    """A set of test poses to score every reconstruction on: the dataset's recorded test frames (one group) or its
    off-path split (groups by offset), with each detector's scores on its ground-truth BEVs per group."""

    reader: DatasetReader
    groups: dict[str, list[int]]
    gt: list[TestBEV]
    gt_scores: dict[str, dict[str, DetectionScore]]

    @classmethod
    def open(cls, reader: DatasetReader, groups: dict[str, list[int]], detectors: dict[str, Detector],
             decode: DecodeOptions, protocol: Protocol) -> _Split:
        gt = gt_bevs(reader, [f for frames in groups.values() for f in frames])
        return cls(reader, groups, gt, {n: _by_group(m, gt, groups, decode, protocol) for n, m in detectors.items()})

    def score(self, bundle: Bundle, detectors: dict[str, Detector], decode: DecodeOptions, protocol: Protocol,
              backend: str) -> tuple[dict[str, dict[str, Any]], list[TestBEV], dict[str, dict[str, DetectionScore]]]:
        """A reconstruction's image scores per group, its rendered BEVs and each detector's scores per group (on
        the bundle scene's device; the BEVs come back to the CPU for the detectors)."""
        reader = self.reader
        response = CameraResponse(reader.rig, 0.0, bundle.scene.means.device)
        response.load_dict(bundle.meta.get("camera_response", {}))
        frames = [f for fs in self.groups.values() for f in fs]
        views = [(f, c) for f in frames for c in reader.rig.names]
        method = bundle.projection
        quality = group_means(evaluate_views(bundle.scene, reader, views, response, backend, method=method),
                              self.groups)
        bevs = rendered_bevs(bundle.scene, reader, frames, response, backend, method)
        return quality, bevs, {n: _by_group(m, bevs, self.groups, decode, protocol) for n, m in detectors.items()}


def _offpath_split(data_dir: Path, detectors: dict[str, Detector], decode: DecodeOptions,
                   protocol: Protocol) -> tuple[_Split, dict[str, Any]] | None:
    """The dataset's off-path split opened for scoring, and what tables.json records of it; None without one."""
    split = offpath_split(data_dir)
    if split is None:
        return None
    info = read_offpath(split)
    groups = group_frames(info["frames"])
    opened = _Split.open(DatasetReader(split), {g: v["frames"] for g, v in groups.items()}, detectors, decode,
                         protocol)
    record = {"dataset": str(split), "skipped": info["skipped"],
              "groups": [{"group": g, "kind": v["kind"], "offset": v["offset"], "frames": len(v["frames"])}
                         for g, v in groups.items()],
              "gt": {n: {g: _scores(s) for g, s in by.items()} for n, by in opened.gt_scores.items()}}
    return opened, record


def evaluate_runs(runs: list[tuple[Path, str | None]], data_dir: Path, detectors: dict[str, Detector],
                  out_dir: Path, backend: str = "auto", panel_frames: int = 3,
                  decode: DecodeOptions = DecodeOptions(), protocol: Protocol = ParkSimProtocol(),
                  offpath: bool = True, device: torch.device | None = None) -> dict[str, Any]:
    """Score each ``(bundle folder, label or None)`` on the dataset's test frames; returns what ``tables.json`` holds.

    ``decode`` sets the detectors' operating point (confidence threshold) for every BEV alike; ``protocol`` the
    detection scoring rules (recorded in the result). With ``offpath`` and an off-path split in the dataset, every
    reconstruction and detector is also scored on it per offset group (``offpath`` in the result and each row).
    The reconstructions render and are scored on ``device`` (None: the CPU); the detectors run on the CPU.
    """
    reader = DatasetReader(data_dir)
    frames = reader.split["test"]
    test = _Split.open(reader, {_TEST: frames}, detectors, decode, protocol)
    off = _offpath_split(data_dir, detectors, decode, protocol) if offpath else None
    gt, gt_scores = test.gt, {name: by[_TEST] for name, by in test.gt_scores.items()}
    shown = sorted(range(len(gt)), key=lambda i: (-len(gt[i].labels.slots), gt[i].frame))[:panel_frames]
    panels = {name: [[_annotated(gt[i], s.detections[i], f"GT f{gt[i].frame}")] for i in shown]
              for name, s in gt_scores.items()}
    rows = []
    for scene_dir, label in runs:
        info = describe_run(scene_dir, label)
        bundle = load(scene_dir)
        bundle = replace(bundle, scene=bundle.scene.to(device=device))
        quality, bevs, scores = test.score(bundle, detectors, decode, protocol, backend)
        detection = {}
        for name, by in scores.items():
            detection[name] = _scores(by[_TEST])
            for panel, i in zip(panels[name], shown):
                panel.append(_annotated(bevs[i], by[_TEST].detections[i], info.label))
        row = {**asdict(info), "dir": str(scene_dir), **quality[_TEST], "detection": detection}
        if off is not None:
            off_quality, _, off_scores = off[0].score(bundle, detectors, decode, protocol, backend)
            row["offpath"] = {"quality": off_quality,
                              "detection": {n: {g: _scores(s) for g, s in by.items()} for n, by in off_scores.items()}}
        rows.append(row)
    result = {"scene": Path(data_dir).name, "dataset": str(data_dir), "test_frames": frames,
              "threshold": decode.threshold, "protocol": protocol.describe(),
              "gt": {name: _scores(s) for name, s in gt_scores.items()}, "runs": rows}
    if off is not None:
        result["offpath"] = off[1]
    out_dir.mkdir(parents=True, exist_ok=True)
    write_json(out_dir / "tables.json", result)
    (out_dir / "tables.md").write_text(tables_markdown([result]))
    for name, grid in panels.items():
        write_grid(out_dir / f"panel_{name}.png", grid)
    return result
