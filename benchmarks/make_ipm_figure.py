"""README figure: the real sample's four fisheye images and the BEV our IPM stitches from them.

Run: .venv/bin/python benchmarks/make_ipm_figure.py [SAMPLE_DIR] [-o docs/sample_ipm.jpg]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

from parksim.assets import SAMPLE_DIR  # noqa: E402
from parksim.calib.sample_rig import load_sample_images, sample_rig  # noqa: E402
from parksim.ipm import IPM  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("sample", nargs="?", type=Path, default=SAMPLE_DIR)
    ap.add_argument("-o", "--output", type=Path, default=Path("docs/sample_ipm.jpg"))
    args = ap.parse_args()
    rig, _ = sample_rig(args.sample, m_per_px=0.02)
    images = load_sample_images(args.sample, rig)
    bev = IPM(rig)(images)
    fig = plt.figure(figsize=(12, 6.4), dpi=110)
    for i, name in enumerate(["front", "rear", "left", "right"]):
        ax = fig.add_axes([0.01 + 0.3 * (i % 2), 0.5 - 0.48 * (i // 2) + 0.02, 0.29, 0.43])
        ax.imshow(images[name].numpy())
        ax.set_title(f"{name} (fisheye input)", fontsize=9)
        ax.axis("off")
    ax = fig.add_axes([0.63, 0.02, 0.36, 0.92])
    ax.imshow(bev.numpy())
    ax.set_title("BEV by parksim.ipm (2 cm/px, poses from the homographies)", fontsize=9)
    ax.axis("off")
    args.output.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(args.output, pil_kwargs={"quality": 85})
    print(f"wrote {args.output}")


if __name__ == "__main__":
    main()
