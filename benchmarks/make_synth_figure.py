"""README figure: the four fisheye views and the GT BEV with its slot labels, one frame of a synthetic dataset.

Usage: python benchmarks/make_synth_figure.py [--data data/scene1] [--frame 40] [-o docs/synth_scene1.png]
       python benchmarks/make_synth_figure.py --data data/worn --frame 55 -o docs/synth_worn.jpg
(generate the scene first: ``parksim synth scene1 -o data/scene1``). A ``.jpg`` output is written at JPEG quality
85, which keeps the noisy photographic views of worn/busy small.
"""

from __future__ import annotations

import argparse
import math
import sys

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

from parksim.data import DatasetReader  # noqa: E402


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", default="data/scene1")
    ap.add_argument("--frame", type=int, default=40)
    ap.add_argument("-o", "--output", default="docs/synth_scene1.png")
    args = ap.parse_args()
    r = DatasetReader(args.data)
    fig = plt.figure(figsize=(14, 6.2), dpi=110)
    grid = fig.add_gridspec(2, 3, width_ratios=[1, 1, 1.15])
    for k, name in enumerate(r.rig.names):
        ax = fig.add_subplot(grid[k // 2, k % 2])
        ax.imshow(r.image(name, args.frame).numpy())
        ax.set_title(name, fontsize=10)
        ax.axis("off")
    ax = fig.add_subplot(grid[:, 2])
    ax.imshow(r.ipm(args.frame).numpy())
    labels = r.labels(args.frame)
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
    fig.suptitle(f"parksim synth {r.meta.get('preset', args.data)}, frame {args.frame}: 190 deg fisheyes (ray cast) "
                 "and their IPM", fontsize=12)
    fig.tight_layout()
    jpeg = str(args.output).lower().endswith((".jpg", ".jpeg"))
    fig.savefig(args.output, pil_kwargs={"quality": 85} if jpeg else None)
    print(f"wrote {args.output}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
