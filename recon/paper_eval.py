"""The paper's experiments on one dataset: novel-view scores and BEV slot detection of several reconstructions.

For each reconstruction (a scene bundle) it scores the test views (PSNR/SSIM over the whole valid image and
over slot regions, ``recon.evaluate``) and runs every given detector on the rendered BEVs of the test frames;
each detector also runs once on the ground-truth BEVs (the "GT-" rows). Writes ``tables.json`` (all numbers),
``tables.md`` (``recon.paper_tables``) and one ``panel_<detector>.png`` of ground-truth vs rendered BEVs
with labels and detections.
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

from parksim.bundle import load
from parksim.data import DatasetReader
from parksim.fileio import write_json

from .bev_detection import DetectionScore, TestBEV, gt_bevs, rendered_bevs, score_detector
from .bev_draw import caption, draw_detections, draw_labels, write_grid
from .config import load_config
from .detectors import DecodeOptions, Detections, DMPRDetector
from .detectors.protocols import ParkSimProtocol, Protocol
from .evaluate import evaluate_views, summarize
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


def evaluate_runs(runs: list[tuple[Path, str | None]], data_dir: Path, detectors: dict[str, DMPRDetector],
                  out_dir: Path, backend: str = "auto", panel_frames: int = 3,
                  decode: DecodeOptions = DecodeOptions(), protocol: Protocol = ParkSimProtocol()) -> dict[str, Any]:
    """Score each ``(bundle folder, label or None)`` on the dataset's test frames; returns what ``tables.json`` holds.

    ``decode`` sets the detectors' operating point (confidence threshold) for every BEV alike; ``protocol`` the
    detection scoring rules (recorded in the result).
    """
    reader = DatasetReader(data_dir)
    frames = reader.split["test"]
    gt = gt_bevs(reader, frames)
    gt_scores = {name: score_detector(model, gt, decode, protocol) for name, model in detectors.items()}
    shown = sorted(range(len(gt)), key=lambda i: (-len(gt[i].labels.slots), gt[i].frame))[:panel_frames]
    panels = {name: [[_annotated(gt[i], s.detections[i], f"GT f{gt[i].frame}")] for i in shown]
              for name, s in gt_scores.items()}
    views = [(f, c) for f in frames for c in reader.rig.names]
    rows = []
    for scene_dir, label in runs:
        info = describe_run(scene_dir, label)
        bundle = load(scene_dir)
        response = CameraResponse(reader.rig, 0.0)
        response.load_dict(bundle.meta.get("camera_response", {}))
        quality = summarize(evaluate_views(bundle.scene, reader, views, response, backend), reader.rig.names, frames)
        bevs = rendered_bevs(bundle.scene, reader, frames, response, backend)
        detection = {}
        for name, model in detectors.items():
            score = score_detector(model, bevs, decode, protocol)
            detection[name] = _scores(score)
            for row, i in zip(panels[name], shown):
                row.append(_annotated(bevs[i], score.detections[i], info.label))
        rows.append({**asdict(info), "dir": str(scene_dir), **quality["overall"], "detection": detection})
    result = {"scene": Path(data_dir).name, "dataset": str(data_dir), "test_frames": frames,
              "threshold": decode.threshold, "protocol": protocol.describe(),
              "gt": {name: _scores(s) for name, s in gt_scores.items()}, "runs": rows}
    out_dir.mkdir(parents=True, exist_ok=True)
    write_json(out_dir / "tables.json", result)
    (out_dir / "tables.md").write_text(tables_markdown([result]))
    for name, grid in panels.items():
        write_grid(out_dir / f"panel_{name}.png", grid)
    return result
