"""``parksim bench ipm``: the differentiable IPM on the real surround-view sample (four 960x640 fisheyes), built
once per BEV resolution, then per call, forward and forward + backward, against OpenCV ``remap`` with the same
sampling grids and blend weights in the same run (the speed reference; not differentiable).

The rig is fitted once from the sample's calibration pattern (``parksim.calib.sample_rig``); each ``--m-per-px``
is a BEV over the sample's 12 m x 16 m stitched extent. The three calls alternate (``time_medians``). The largest
difference between the IPM and the OpenCV blend is recorded against 2e-3 (bilinear taps of the same grids).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from ..common import progress, time_medians
from ..record import Figure
from ..suite import Context, Outcome, Suite

__all__ = ["IPMSuite", "IPMOptions", "opencv_stitch", "AGREEMENT"]

AGREEMENT = 2e-3
"""Largest |IPM - cv2.remap blend| accepted (images in [0, 1])."""


@dataclass(frozen=True)
class IPMOptions:
    """Options of ``parksim bench ipm``."""

    sample: Path | None = field(default=None, metadata={
        "help": "surround-view sample folder (images/, yaml/; default: the packaged sample)"})
    m_per_px: list[float] = field(default_factory=lambda: [0.02, 0.01], metadata={
        "help": "BEV ground sampling distances (m per pixel)", "low": 1e-4, "quick": [0.05]})
    repeats: int = field(default=21, metadata={"help": "timed calls (median)", "low": 1, "quick": 1})


def opencv_stitch(ipm: Any, images: dict[str, Any]) -> Any:
    """The IPM's blend done with ``cv2.remap`` (not differentiable): the speed reference.

    Args:
        ipm: a built ``parksim.ipm.IPM``.
        images: per camera ``(H, W, 3)`` float32 numpy images.

    Returns:
        The BEV ``(bev_h, bev_w, 3)`` float32.
    """
    import cv2
    import numpy as np

    out = None
    for name in ipm.cameras:
        uv = ipm.pixel_coords[name].numpy().astype(np.float32)
        warped = cv2.remap(images[name], uv[..., 0], uv[..., 1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)
        term = warped * ipm.weights[name].numpy()[..., None]
        out = term if out is None else out + term
    return out


def _closures(ipm: Any, images: dict[str, Any], grad_images: dict[str, Any],
              np_images: dict[str, Any]) -> list[Callable[[], Any]]:
    """The IPM's call, its call + backward, and the cv2.remap blend of the same grids."""
    return [lambda: ipm(images), lambda: ipm(grad_images).sum().backward(), lambda: opencv_stitch(ipm, np_images)]


class IPMSuite(Suite):
    """IPM build, call and backward on the real sample, against cv2.remap of the same grids."""

    name = "ipm"
    help = "IPM on the real 4-fisheye sample: build, call, backward, vs cv2.remap of the same grids"
    description = ("The differentiable IPM on the packaged surround-view sample (4 x 960x640 fisheyes) at 2 and 1 "
                   "cm/px: build time, median forward call and forward+backward, against OpenCV remap with the same "
                   "sampling grids and weights (the reference, timed alternately), and their largest difference.")
    Options = IPMOptions

    def run(self, options: IPMOptions, context: Context) -> Outcome:
        """Fit the rig once, then measure each resolution."""
        import numpy as np

        from ...assets import SAMPLE_DIR
        from ...calib.sample_rig import load_sample_images, sample_bev_spec, sample_rig
        from ...ipm import IPM

        sample = options.sample or SAMPLE_DIR
        rig, _ = sample_rig(sample)
        images = load_sample_images(sample, rig)
        np_images = {n: v.numpy() for n, v in images.items()}
        grad_images = {n: v.clone().requires_grad_(True) for n, v in images.items()}
        figures: list[Figure] = []
        rows: list[dict[str, Any]] = []
        with progress(len(options.m_per_px), "bench ipm", context.quiet) as bar:
            for m_per_px in options.m_per_px:
                spec = sample_bev_spec(m_per_px=m_per_px)
                start = time.perf_counter()
                ipm = IPM(rig, spec)
                build_s = time.perf_counter() - start
                call, backward, ref = time_medians(_closures(ipm, images, grad_images, np_images), options.repeats)
                diff = float(np.abs(opencv_stitch(ipm, np_images) - ipm(images).numpy()).max())
                bev = f"4 x 960x640 sample -> {spec.width}x{spec.height} BEV ({m_per_px * 100:g} cm/px)"
                figures += [
                    Figure(f"IPM call, {bev}", call.wall_ms, "ms", cpu=call.cpu_ms, reference=ref.wall_ms,
                           reference_cpu=ref.cpu_ms, reference_label="cv2.remap, same grids and blend, same run"),
                    Figure(f"IPM call + backward, {bev}", backward.wall_ms, "ms", cpu=backward.cpu_ms),
                    Figure(f"IPM build, {bev}", build_s, "s"),
                    Figure(f"IPM max |difference| to the cv2.remap blend, {bev}", diff, "abs",
                           goal=f"<= {AGREEMENT:g}")]
                rows.append({"m_per_px": m_per_px, "bev": [spec.width, spec.height], "build_s": build_s,
                             "call": call, "backward": backward, "cv2_remap": ref, "max_abs_diff": diff})
                bar.update(1)
        return Outcome(figures, {"sample": str(sample), "rows": rows})
