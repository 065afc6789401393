"""IPM speed: build once per rig, then per call; against OpenCV remap with the same grids in the same run.

Run: .venv/bin/python benchmarks/bench_ipm.py [SAMPLE_DIR] [--repeats 21]
Prints a Markdown table (median ms) for the real sample's 4 x 960x640 fisheyes at 2 cm/px and 1 cm/px.
"""

from __future__ import annotations

import argparse
import os
import platform
import statistics
import time
from datetime import date
from pathlib import Path

import cv2
import numpy as np
import torch

from parksim.assets import SAMPLE_DIR
from parksim.calib.sample_rig import load_sample_images, sample_rig
from parksim.ipm import IPM


def median_ms(fn, repeats: int) -> float:
    fn()  # warm-up
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        fn()
        times.append((time.perf_counter() - t) * 1e3)
    return statistics.median(times)


def opencv_stitch(ipm: IPM, images: dict[str, np.ndarray]) -> np.ndarray:
    """The same blend with cv2.remap (not differentiable): the speed reference."""
    out = None
    for name in ipm.cameras:
        uv = ipm.pixel_coords[name].numpy().astype(np.float32)
        warped = cv2.remap(images[name], uv[..., 0], uv[..., 1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)
        term = warped * ipm.weights[name].numpy()[..., None]
        out = term if out is None else out + term
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("sample", nargs="?", type=Path, default=SAMPLE_DIR)
    ap.add_argument("--repeats", type=int, default=21)
    args = ap.parse_args()
    print(f"machine: {platform.machine()}, {os.cpu_count()} cores, torch {torch.__version__} "
          f"({torch.get_num_threads()} threads), load {os.getloadavg()[0]:.1f}; date {date.today()}\n")
    print("| BEV | build (s) | parksim IPM call (ms) | with backward (ms) | cv2.remap same blend (ms) | ratio |")
    print("|---|---|---|---|---|---|")
    for m_per_px in (0.02, 0.01):
        rig, _ = sample_rig(args.sample, m_per_px=m_per_px)
        images = load_sample_images(args.sample, rig)
        t = time.perf_counter()
        ipm = IPM(rig)
        build = time.perf_counter() - t
        call = median_ms(lambda: ipm(images), args.repeats)
        grad_imgs = {n: v.clone().requires_grad_(True) for n, v in images.items()}
        backward = median_ms(lambda: ipm(grad_imgs).sum().backward(), args.repeats)
        np_imgs = {n: v.numpy() for n, v in images.items()}
        ref = median_ms(lambda: opencv_stitch(ipm, np_imgs), args.repeats)
        diff = np.abs(opencv_stitch(ipm, np_imgs) - ipm(images).numpy()).max()
        print(f"| {rig.bev.width}x{rig.bev.height} ({m_per_px * 100:.0f} cm/px) | {build:.2f} | {call:.1f} | "
              f"{backward:.1f} | {ref:.1f} | {call / ref:.2f} |")
        assert diff < 2e-3, f"IPM and OpenCV reference disagree by {diff}"


if __name__ == "__main__":
    main()
