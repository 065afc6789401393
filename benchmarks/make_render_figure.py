"""README figure: a trained scene rendered at a test frame (four fisheye views + BEV) next to the ground truth.

Run: .venv/bin/python benchmarks/make_render_figure.py SCENE_BUNDLE DATA_DIR [-o docs/render_scene1.jpg]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import torch  # noqa: E402

from parksim.bundle import load  # noqa: E402
from parksim.data import DatasetReader  # noqa: E402
from parksim.render import render  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("bundle", type=Path)
    ap.add_argument("data", type=Path)
    ap.add_argument("--frame", type=int, help="test frame (default: the middle one)")
    ap.add_argument("-o", "--output", type=Path, default=Path("docs/render_scene1.jpg"))
    args = ap.parse_args()
    bundle, reader = load(args.bundle), DatasetReader(args.data)
    tests = reader.split["test"]
    frame = args.frame if args.frame is not None else tests[len(tests) // 2]
    with torch.no_grad():
        out = render(bundle.scene, bundle.rig, reader.pose(frame), bev=True)
    names = bundle.rig.names
    fig, axes = plt.subplots(2, len(names) + 1, figsize=(3.2 * (len(names) + 1), 5.4), dpi=100)
    for row, (label, views, bev) in enumerate([("rendered", out.images, out.bev),
                                               ("ground truth", {n: reader.image(n, frame) for n in names},
                                                reader.ipm(frame))]):
        for col, name in enumerate(names):
            axes[row, col].imshow(views[name].clamp(0, 1).numpy())
            axes[row, col].set_title(f"{name} ({label})", fontsize=9)
        axes[row, -1].imshow(bev.clamp(0, 1).numpy())
        axes[row, -1].set_title(f"BEV ({label})", fontsize=9)
    for ax in axes.flat:
        ax.axis("off")
    fig.suptitle(f"{len(bundle.scene)} Gaussians, test frame {frame} (not trained on)", fontsize=10)
    fig.tight_layout()
    args.output.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(args.output, pil_kwargs={"quality": 85})
    print(f"wrote {args.output}")


if __name__ == "__main__":
    main()
