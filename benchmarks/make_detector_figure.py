"""Draw a ground-truth BEV test frame with its slot labels and both detectors' detections -> docs/detector_bev.png.

Green: labels (circle = the 10 px-at-600 px match tolerance, line = slot entrance p1 -> p2 with a tick at p1).
Red: detections (dot, direction arrow, entrance line). Left panel DMPR-PS-style, right GCN-Parking-style.

    python benchmarks/make_detector_figure.py --models data/detectors --data data/det_scene1
"""

from __future__ import annotations

import argparse
from pathlib import Path

import cv2
import numpy as np
import torch

from parksim.recon.bev_draw import WHITE, draw_detections, draw_labels
from parksim.recon.detectors import load_detector
from parksim.recon.detectors.dataset import BEVItem, iter_items


def panel(item: BEVItem, model: torch.nn.Module, title: str) -> np.ndarray:
    """One annotated BEV."""
    bev = torch.from_numpy(item.image).permute(2, 0, 1).float()[None] / 255.0
    det = model.detect(bev, item.labels.m_per_px)[0]
    img = item.image.copy()
    draw_labels(img, item.labels)
    draw_detections(img, det)
    cv2.putText(img, f"{title}: {len(det.points)} points, {len(det.slots)} slots", (10, 28),
                cv2.FONT_HERSHEY_SIMPLEX, 0.7, WHITE, 2, cv2.LINE_AA)
    return img


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--models", type=Path, default=Path("data/detectors"))
    ap.add_argument("--data", type=Path, default=Path("data/det_scene1"))
    ap.add_argument("--out", type=Path, default=Path("docs/detector_bev.png"))
    args = ap.parse_args(argv)
    torch.set_num_threads(2)
    item = max(iter_items(args.data, "test"), key=lambda it: (len(it.labels.slots), len(it.labels.marks)))
    panels = [panel(item, load_detector(args.models / arch), title) for arch, title in
              (("dmpr", "DMPR-PS-style"), ("gcn", "GCN-Parking-style"))]
    out = np.concatenate([panels[0], np.full((panels[0].shape[0], 8, 3), 255, np.uint8), panels[1]], axis=1)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(args.out), cv2.cvtColor(out, cv2.COLOR_RGB2BGR))
    print(f"wrote {args.out} ({item.name})")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
