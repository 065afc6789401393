"""Draw the figures of README.md and docs/README.md into docs/.

    python docs/make_figures.py                      # all of them
    python docs/make_figures.py synth ipm            # some of them

Figures (one function each):

- ``ipm``: ``sample_ipm.jpg``, the real surround-view sample's four fisheye images and the BEV ``parksim.ipm``
  stitches from them.
- ``synth``: ``synth_scene1.png``, ``synth_worn.jpg``, ``synth_busy.jpg``: the four fisheye views of one frame of
  a synthetic garage and its ground-truth BEV with the slot labels (datasets made with ``parksim synth`` under
  ``--data-root`` when missing).
- ``render``: ``render_scene1.jpg``, a trained bundle rendered at a test frame (four views + BEV) above the ground
  truth (``--bundle``; its dataset from the bundle's metadata unless ``--render-data``).
- ``detector``: ``detector_bev.png``, a ground-truth test BEV of scene1 with its labels (green: circle = the
  match tolerance, line = entrance p1 -> p2) and the detections (red) of both detectors in ``--models``
  (DMPR-PS-style left, GCN-style right).
"""

from __future__ import annotations

import argparse
import math
from pathlib import Path
from typing import Any

DOCS = Path(__file__).resolve().parent
SYNTH = (("scene1", 40, "synth_scene1.png"), ("worn", 85, "synth_worn.jpg"), ("busy", 70, "synth_busy.jpg"))
"""Synth preset, frame and file of each synth figure."""
DETECTORS = (("dmpr", "DMPR-PS-style"), ("gcn", "GCN-Parking-style"))


def _save(fig: Any, path: Path) -> Path:
    """Write a matplotlib figure (JPEG at quality 85 for ``.jpg``: the noisy photographic views stay small)."""
    from parksim.bench.common import pyplot

    jpeg = path.suffix.lower() in (".jpg", ".jpeg")
    fig.savefig(path, pil_kwargs={"quality": 85} if jpeg else None)
    pyplot().close(fig)
    return path


def draw_ipm(out: Path) -> list[Path]:
    """The real sample's four fisheye images and the BEV stitched from them (2 cm/px)."""
    from parksim.assets import SAMPLE_DIR
    from parksim.bench.common import pyplot
    from parksim.calib.sample_rig import load_sample_images, sample_rig
    from parksim.ipm import IPM

    rig, _ = sample_rig(SAMPLE_DIR, m_per_px=0.02)
    images = load_sample_images(SAMPLE_DIR, rig)
    bev = IPM(rig)(images)
    fig = pyplot().figure(figsize=(12, 6.4), dpi=110)
    for i, name in enumerate(["front", "rear", "left", "right"]):
        ax = fig.add_axes([0.01 + 0.3 * (i % 2), 0.5 - 0.48 * (i // 2) + 0.02, 0.29, 0.43])
        ax.imshow(images[name].numpy())
        ax.set_title(f"{name} (fisheye input)", fontsize=9)
        ax.axis("off")
    ax = fig.add_axes([0.63, 0.02, 0.36, 0.92])
    ax.imshow(bev.clamp(0, 1).numpy())
    ax.set_title("BEV by parksim.ipm (2 cm/px, poses from the homographies)", fontsize=9)
    ax.axis("off")
    return [_save(fig, out / "sample_ipm.jpg")]


def draw_synth_frame(data: Path, frame: int, path: Path) -> Path:
    """One frame of a synthetic dataset: its four views and the GT BEV with marking points and slots."""
    from parksim.bench.common import pyplot
    from parksim.data import DatasetReader

    r = DatasetReader(data)
    fig = pyplot().figure(figsize=(14, 6.2), dpi=110)
    grid = fig.add_gridspec(2, 3, width_ratios=[1, 1, 1.15])
    for k, name in enumerate(r.rig.names):
        ax = fig.add_subplot(grid[k // 2, k % 2])
        ax.imshow(r.image(name, frame).numpy())
        ax.set_title(name, fontsize=10)
        ax.axis("off")
    ax = fig.add_subplot(grid[:, 2])
    ax.imshow(r.ipm(frame).numpy())
    labels = r.labels(frame)
    marks = labels["marks"]
    for s in labels["slots"]:
        a, b = marks[s["p1"]], marks[s["p2"]]
        ax.plot([a["x"], b["x"]], [a["y"], b["y"]], "-", color="lime", lw=2)
        for m in (a, b):
            ax.plot([m["x"], m["x"] + 60 * math.cos(m["direction"])], [m["y"], m["y"] + 60 * math.sin(m["direction"])],
                    "--", color="lime", lw=1)
    for m in marks:
        ax.plot(m["x"], m["y"], "o", ms=7, mfc="none", mec="red", mew=2)
        ax.text(m["x"] + 6, m["y"] - 6, m["shape"], color="red", fontsize=9, weight="bold")
    ax.set_title(f"GT IPM (BEV) with DMPR-PS labels: {len(marks)} marking points, {len(labels['slots'])} slots",
                 fontsize=10)
    ax.axis("off")
    fig.suptitle(f"parksim synth {r.meta.get('preset', data.name)}, frame {frame}: 190 deg fisheyes (ray cast) "
                 "and their IPM", fontsize=12)
    fig.tight_layout()
    return _save(fig, path)


def draw_synth(out: Path, data_root: Path) -> list[Path]:
    """One frame each of scene1, worn and busy (``SYNTH``), the datasets made under ``data_root`` when missing."""
    from parksim.bench.datasets import synth_dataset

    return [draw_synth_frame(synth_dataset(preset, data_root, None), frame, out / name)
            for preset, frame, name in SYNTH]


def draw_render(out: Path, bundle: Path, data: Path | None, frame: int | None) -> list[Path]:
    """A trained bundle at a test frame (views + BEV) above the ground truth; ``data`` defaults to the dataset the
    bundle was trained on, ``frame`` to its middle test frame."""
    import torch

    from parksim.bench.common import pyplot
    from parksim.bundle import load
    from parksim.data import DatasetReader
    from parksim.render import render

    scene = load(bundle)
    reader = DatasetReader(data or Path(scene.meta["dataset"]))
    tests = reader.split["test"]
    frame = tests[len(tests) // 2] if frame is None else frame
    with torch.no_grad():
        result = render(scene.scene, scene.rig, reader.pose(frame), bev=True)
    assert result.bev is not None   # asked for
    names = scene.rig.names
    fig, axes = pyplot().subplots(2, len(names) + 1, figsize=(3.2 * (len(names) + 1), 5.4), dpi=100)
    rows = [("rendered", result.images, result.bev),
            ("ground truth", {n: reader.image(n, frame) for n in names}, reader.ipm(frame))]
    for row, (label, views, bev) in enumerate(rows):
        for col, name in enumerate(names):
            axes[row, col].imshow(views[name].clamp(0, 1).numpy())
            axes[row, col].set_title(f"{name} ({label})", fontsize=9)
        axes[row, -1].imshow(bev.clamp(0, 1).numpy())
        axes[row, -1].set_title(f"BEV ({label})", fontsize=9)
    for ax in axes.flat:
        ax.axis("off")
    fig.suptitle(f"{len(scene.scene)} Gaussians, test frame {frame} (not trained on)", fontsize=10)
    fig.tight_layout()
    return [_save(fig, out / "render_scene1.jpg")]


def draw_detector(out: Path, models: Path, data_root: Path) -> list[Path]:
    """The scene1 test BEV with the most slots, labels and each detector's detections side by side."""
    import cv2
    import numpy as np
    import torch

    from parksim.bench.datasets import synth_dataset
    from parksim.recon.bev_draw import WHITE, draw_detections, draw_labels
    from parksim.recon.detectors import load_detector
    from parksim.recon.detectors.dataset import iter_items

    items = iter_items(synth_dataset("scene1", data_root, None), "test")
    item = max(items, key=lambda it: (len(it.labels.slots), len(it.labels.marks)))
    bev = torch.from_numpy(item.image).permute(2, 0, 1).float()[None] / 255.0
    panels = []
    for arch, title in DETECTORS:
        with torch.no_grad():
            det = load_detector(models / arch).detect(bev, item.labels.m_per_px)[0]
        img = item.image.copy()
        draw_labels(img, item.labels)
        draw_detections(img, det)
        cv2.putText(img, f"{title}: {len(det.points)} points, {len(det.slots)} slots", (10, 28),
                    cv2.FONT_HERSHEY_SIMPLEX, 0.7, WHITE, 2, cv2.LINE_AA)
        panels.append(img)
    gap = np.full((panels[0].shape[0], 8, 3), 255, np.uint8)
    path = out / "detector_bev.png"
    cv2.imwrite(str(path), cv2.cvtColor(np.concatenate([panels[0], gap, panels[1]], axis=1), cv2.COLOR_RGB2BGR))
    return [path]


def main(argv: list[str] | None = None) -> int:
    """Parse the command line and draw the chosen figures."""
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("figures", nargs="*", choices=["ipm", "synth", "render", "detector"],
                    help="figures to draw (default: all)")
    ap.add_argument("--out", type=Path, default=DOCS, help="folder the images go to (default: this docs/ folder)")
    ap.add_argument("--data-root", type=Path, default=Path("data"),
                    help="where the synth datasets are kept (made here when missing)")
    ap.add_argument("--bundle", type=Path, default=Path("scenes/scene1"),
                    help="trained bundle of the render figure (e.g. `parksim reconstruct data/scene1 -o "
                         "scenes/scene1 --config cpu_30min`)")
    ap.add_argument("--render-data", type=Path, help="dataset of the render figure (default: the bundle's)")
    ap.add_argument("--frame", type=int, help="test frame of the render figure (default: the middle one)")
    ap.add_argument("--models", type=Path, default=Path("detectors"),
                    help="folder with the trained dmpr/ and gcn/ detectors (`parksim bench detectors --models "
                         "detectors` trains them)")
    args = ap.parse_args(argv)
    import torch

    torch.set_num_threads(2)
    draw = {"ipm": lambda: draw_ipm(args.out), "synth": lambda: draw_synth(args.out, args.data_root),
            "render": lambda: draw_render(args.out, args.bundle, args.render_data, args.frame),
            "detector": lambda: draw_detector(args.out, args.models, args.data_root)}
    args.out.mkdir(parents=True, exist_ok=True)
    for name in args.figures or list(draw):
        for path in draw[name]():
            print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
