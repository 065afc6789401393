"""``parksim bench knobs``: latency against error over the knobs a user can turn.

Each point changes one knob from the full-quality setting (first input, scale 1, full SH, UT projection,
all cameras, no BEV, auto backend, most threads): input bundle (e.g. compaction levels), resolution scale,
SH degree cap, UT vs EWA, cameras/BEV requested, rasterizer backend, thread count. A point records the
median latency (wall and process CPU; all points called in turn each round, so a change of load hits them
alike), the error against the full-quality render (PSNR, max abs; a scaled render is upsampled bilinearly
first) and, for trained bundles, the PSNR against the dataset's ground truth.
"""

from __future__ import annotations

import math
import os
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

from ...checked_options import CheckedOptions
from ..common import progress, pyplot, save_figure, set_threads, time_medians
from ..datasets import ensure_dataset
from ..record import Figure
from ..suite import Context, Outcome, Suite

if TYPE_CHECKING:
    from torch import Tensor

    from ...bundle import Bundle
    from ...gaussians import GaussianScene
    from ...render import RenderResult
    from ...rig import Rig

__all__ = ["KnobsSuite", "KnobsOptions", "Knobs", "knob_grid", "PSNR_CAP_DB"]

PSNR_CAP_DB = 80.0
"""Where the plot puts renders identical to the reference (PSNR = inf)."""


@dataclass(frozen=True)
class KnobsOptions(CheckedOptions):
    """Options of ``parksim bench knobs``."""

    bundle: list[Path] = field(default_factory=list, metadata={
        "help": "scene bundles to compare, comma-separated (e.g. compaction levels); the first is the reference"})
    dataset: Path | None = field(default=None, metadata={
        "help": "dataset giving pose, rig and ground truth (default: the first bundle's, else synth scene1 at "
                "320x240 under --work, synth tiny under --quick; with no bundle a garage-like scene of "
                "--gaussians is built from its points)"})
    gaussians: int = field(default=200_000, metadata={
        "help": "Gaussians of the built scene when no --bundle is given", "low": 1, "quick": 500})
    frame: int | None = field(default=None, metadata={
        "help": "dataset frame whose pose is rendered (default: the first test frame)", "low": 0})
    scales: list[float] = field(default_factory=lambda: [1.0, 0.75, 0.5, 0.25], metadata={
        "help": "resolution scales of the fisheye views", "low": 0.0, "open_low": True, "quick": [1.0, 0.5]})
    sh_degrees: list[int] = field(default_factory=lambda: [0, 1, 2], metadata={
        "help": "SH degree caps (values >= the scene's degree are skipped)", "low": 0, "quick": [0]})
    methods: list[str] = field(default_factory=lambda: ["ut", "ewa"], metadata={
        "help": "projections: ut (unscented) or ewa (Jacobian)"})
    camera_sets: list[str] = field(default_factory=lambda: ["front", "front+rear", "all+bev"], metadata={
        "help": "camera subsets requested ('+'-joined names or all; suffix +bev adds the BEV)",
        "quick": ["front", "all+bev"]})
    backends: list[str] = field(default_factory=lambda: ["auto"], metadata={
        "help": "rasterizer backends (auto, numba, torch = dense reference: small scenes only, gsplat: CUDA)",
        "quick": ["auto", "torch"]})
    threads: list[int] = field(default_factory=lambda: sorted({1, os.cpu_count() or 1}), metadata={
        "help": "numba/torch thread counts", "low": 1, "quick": [1]})
    repeats: int = field(default=5, metadata={"help": "timed renders per point (median), after --warmup", "low": 1,
                                              "quick": 1})
    warmup: int = field(default=1, metadata={"help": "untimed renders first (JIT, caches)", "low": 0})


@dataclass(frozen=True)
class Knobs:
    """One render setting; ``knob`` names the knob changed from the full-quality setting."""

    knob: str
    input: int = 0
    scale: float = 1.0
    sh_degree: int | None = None
    method: str = "ut"
    cameras: tuple[str, ...] | None = None
    bev: bool = False
    backend: str = "auto"
    threads: int = 1

    @property
    def label(self) -> str:
        """The changed knob and its value, e.g. ``scale 0.5`` (the figures' targets start with it)."""
        value = {"input": f"input {self.input}", "scale": f"scale {self.scale:g}", "sh": f"SH <= {self.sh_degree}",
                 "method": f"{self.method.upper()} projection",
                 "cameras": "cameras " + "+".join(self.cameras or ("all",)) + (" + BEV" if self.bev else ""),
                 "backend": f"{self.backend} backend",
                 "threads": f"{self.threads} thread{'s' if self.threads > 1 else ''}"}
        return "full quality, all cameras" if self.knob == "full" else value[self.knob]

    @property
    def same_output(self) -> bool:
        """Whether the point renders what the full-quality point renders (only then on the Pareto front)."""
        return self.knob not in ("cameras",)


@dataclass(frozen=True)
class _Input:
    """A scene to render: a trained bundle (with its dataset's ground truth) or a built garage scene."""

    label: str
    scene: GaussianScene
    bundle: Bundle | None


def knob_grid(options: KnobsOptions, n_inputs: int, sh_degree: int) -> list[Knobs]:
    """The full-quality point, then each knob's other values with everything else at full quality.

    Args:
        options: the knob values to try.
        n_inputs: number of scenes compared (input 0 is the reference).
        sh_degree: the reference scene's SH degree (caps at or above it are skipped).

    Returns:
        The points, the full-quality one first.
    """
    base = Knobs("full", threads=max(options.threads))
    points = [base]
    points += [replace(base, knob="input", input=i) for i in range(1, n_inputs)]
    points += [replace(base, knob="scale", scale=s) for s in options.scales if s != 1.0]
    points += [replace(base, knob="sh", sh_degree=d) for d in options.sh_degrees if d < sh_degree]
    points += [replace(base, knob="method", method=m) for m in options.methods if m != "ut"]
    for spec in options.camera_sets:
        names, bev = spec.removesuffix("+bev"), spec.endswith("+bev")
        cams = None if names == "all" else tuple(names.split("+"))
        if (cams, bev) != (None, False):
            points.append(replace(base, knob="cameras", cameras=cams, bev=bev))
    points += [replace(base, knob="backend", backend=b) for b in options.backends if b != "auto"]
    points += [replace(base, knob="threads", threads=t) for t in options.threads if t != base.threads]
    return points


def _inputs(options: KnobsOptions, context: Context) -> tuple[list[_Input], Rig, Path]:
    """The scenes to compare (bundles first), the rig they share and the dataset giving pose and ground truth."""
    from ...bundle import load as load_bundle
    from ...rig import Rig
    from ..scenes import garage_scene

    bundles = [load_bundle(path) for path in options.bundle]
    inputs = [_Input(f"{path.name} ({len(b.scene):,} G)", b.scene, b) for path, b in zip(options.bundle, bundles)]
    dataset = options.dataset
    if dataset is None and bundles:
        if "dataset" not in bundles[0].meta:
            raise ValueError("bench knobs: give --dataset (pose, rig and ground truth); the first --bundle does not "
                             "name the dataset it was trained from")
        dataset = Path(bundles[0].meta["dataset"])
    if dataset is None:
        dataset = ensure_dataset(context, "scene1", "320x240")
    if not inputs:
        inputs.append(_Input(f"garage from {dataset.name} ({options.gaussians:,} G)",
                             garage_scene(dataset, options.gaussians, context.seed), None))
    first = inputs[0].bundle
    rig = first.rig if first is not None else Rig.load(dataset / "rig.json")
    return inputs, rig, dataset


def _closure(inputs: list[_Input], rig: Rig, pose: Tensor, k: Knobs) -> Callable[[], RenderResult]:
    """A no-grad render of the point's input at its knob settings (its thread count set first)."""
    import torch

    from ...render import render
    from ..scenes import cap_sh_degree

    item = inputs[k.input]
    scene = cap_sh_degree(item.scene, k.sh_degree) if k.sh_degree is not None else item.scene

    def once() -> RenderResult:
        set_threads(k.threads)
        with torch.no_grad():
            return render(scene, rig, pose, cameras=k.cameras, bev=k.bev, scale=k.scale, backend=k.backend,
                          method=k.method)

    return once


def _upsampled(image: Tensor, like: Tensor) -> Tensor:
    """``image`` ``(h, w, 3)`` resized bilinearly to ``like``'s ``(H, W, 3)`` (unchanged when equal)."""
    import torch.nn.functional as F

    if image.shape == like.shape:
        return image
    chw = F.interpolate(image.permute(2, 0, 1)[None], size=like.shape[:2], mode="bilinear", align_corners=False)
    return chw[0].permute(1, 2, 0)


def _errors(images: dict[str, Tensor], reference: dict[str, Tensor]) -> tuple[float, float]:
    """PSNR (dB, peak 1) and max abs error of the images against the reference's same cameras."""
    import torch

    diffs = torch.cat([(_upsampled(img, reference[c]) - reference[c]).flatten() for c, img in images.items()])
    mse = float((diffs ** 2).mean())
    return (math.inf if mse == 0 else -10 * math.log10(mse)), float(diffs.abs().max())


class _GroundTruth:
    """PSNR of a bundle's renders against the dataset's images at one frame, through the learned camera response."""

    def __init__(self, dataset: Path, frame: int, rig: Rig) -> None:
        from ...data import DatasetReader
        from ...recon.masks import scene_mask

        reader = DatasetReader(dataset)
        self.images = {c: reader.image(c, frame) for c in rig.names}
        self.masks = {c: scene_mask(rig.cameras[c], rig.bev) for c in rig.names}
        self.rig = rig

    def psnr(self, images: dict[str, Tensor], bundle: Bundle) -> float:
        """Mean over the rendered cameras of the masked PSNR (the bundle's response applied when it has one)."""
        from ...recon.metrics import psnr
        from ...recon.response import CameraResponse

        response = None
        if "camera_response" in bundle.meta:
            response = CameraResponse(self.rig, 0.0)
            response.load_dict(bundle.meta["camera_response"])
        scores = []
        for c, img in images.items():
            full = _upsampled(img, self.images[c])
            pred = (response(full, c) if response is not None else full).clamp(0, 1)
            scores.append(psnr(pred, self.images[c], self.masks[c]))
        return sum(scores) / len(scores)


def _pareto(points: list[dict[str, Any]]) -> None:
    """Mark (``pareto`` = True) the same-output points no other is both faster and more accurate than."""
    same = [p for p in points if p["same_output"]]
    for p in points:
        p["pareto"] = p["same_output"] and not any(
            q is not p and q["wall_ms"] <= p["wall_ms"] and q["psnr_vs_full"] >= p["psnr_vs_full"]
            and (q["wall_ms"] < p["wall_ms"] or q["psnr_vs_full"] > p["psnr_vs_full"]) for q in same)


def _figures(points: list[dict[str, Any]]) -> list[Figure]:
    """The full-quality latency (and PSNR vs ground truth, for a bundle), then per knob its fastest point's
    latency against full quality's and its PSNR against the full-quality render."""
    full = points[0]
    figures = [Figure(f"{full['label']}: latency", full["wall_ms"], "ms", cpu=full["cpu_ms"])]
    if full["psnr_vs_gt"] is not None:
        figures.append(Figure(f"{full['label']}: PSNR vs ground truth", full["psnr_vs_gt"], "dB", better="higher"))
    for knob in dict.fromkeys(p["knob"] for p in points[1:]):
        fastest = min((p for p in points if p["knob"] == knob), key=lambda p: p["wall_ms"])
        figures += [Figure(f"{fastest['label']}: latency", fastest["wall_ms"], "ms", cpu=fastest["cpu_ms"],
                           reference=full["wall_ms"], reference_label="full quality", reference_cpu=full["cpu_ms"]),
                    Figure(f"{fastest['label']}: PSNR vs full quality", fastest["psnr_vs_full"], "dB",
                           better="higher")]
    return figures


class KnobsSuite(Suite):
    """Latency against error, one knob changed at a time from full quality."""

    name = "knobs"
    help = "latency vs error over the knobs a user can turn (Pareto plot)"
    description = ("Change one knob at a time from full quality (first input, scale 1, full SH, UT, all cameras, no "
                   "BEV, auto backend, most threads) and record the median latency, the error against the "
                   "full-quality render (PSNR, max abs) and, for trained bundles, the PSNR against the dataset's "
                   "ground truth at one test frame. Figures: the full-quality latency and, per knob, its fastest "
                   "point's latency (full quality as the reference) and PSNR vs full quality.")
    Options = KnobsOptions

    def run(self, options: KnobsOptions, context: Context) -> Outcome:
        """Time every knob point in alternating rounds, then score each point's render."""
        from ...data import DatasetReader

        inputs, rig, dataset = _inputs(options, context)
        reader = DatasetReader(dataset)
        frame = options.frame if options.frame is not None else (reader.split["test"] or reader.frames)[0]
        pose = reader.pose(frame)
        gt = _GroundTruth(dataset, frame, rig) if any(i.bundle is not None for i in inputs) else None
        grid = knob_grid(options, len(inputs), inputs[0].scene.sh_degree)
        set_threads(max(options.threads))
        closures = [_closure(inputs, rig, pose, k) for k in grid]
        with progress(options.warmup + options.repeats, "bench knobs (rounds over all points)", context.quiet) as bar:
            timings = time_medians(closures, options.repeats, options.warmup, tick=lambda: bar.update(1))
        renders = [once().images for once in closures]
        set_threads(max(options.threads))
        points: list[dict[str, Any]] = []
        for k, timing, images in zip(grid, timings, renders):
            item = inputs[k.input]
            psnr_full, max_err = _errors(images, renders[0])
            points.append({"knob": k.knob, "label": k.label, "input": item.label, "same_output": k.same_output,
                           "wall_ms": timing.wall_ms, "cpu_ms": timing.cpu_ms, "psnr_vs_full": psnr_full,
                           "max_abs_vs_full": max_err,
                           "psnr_vs_gt": gt.psnr(images, item.bundle) if gt and item.bundle else None})
        _pareto(points)
        model = rig.cameras[rig.names[0]].model
        data = {"dataset": str(dataset), "frame": frame, "inputs": [i.label for i in inputs],
                "rig": {"cameras": rig.names, "size": [model.width, model.height]},
                "full_quality": {"input": 0, "scale": 1.0, "sh_degree": inputs[0].scene.sh_degree, "method": "ut",
                                 "cameras": "all", "bev": False, "backend": "auto", "threads": max(options.threads)},
                "points": points}
        return Outcome(_figures(points), data, lambda png: _plot(points, png))


def _plot(points: list[dict[str, Any]], png: Path) -> None:
    """Latency against PSNR vs full quality (Pareto front drawn) and against ground truth."""
    plt = pyplot()
    with_gt = [p for p in points if p["psnr_vs_gt"] is not None]
    fig, axes = plt.subplots(1, 2 if with_gt else 1, figsize=(12 if with_gt else 7, 4.8), squeeze=False)
    ax = axes[0, 0]
    for p in points:
        y = min(p["psnr_vs_full"], PSNR_CAP_DB)
        ax.scatter(p["wall_ms"], y, marker="o" if p["same_output"] else "x", color="C3" if p["pareto"] else "C0")
        ax.annotate(p["label"], (p["wall_ms"], y), fontsize=7, xytext=(3, 3), textcoords="offset points")
    front = sorted((p for p in points if p["pareto"]), key=lambda p: p["wall_ms"])
    ax.plot([p["wall_ms"] for p in front], [min(p["psnr_vs_full"], PSNR_CAP_DB) for p in front], "C3-", lw=1,
            label="Pareto front (x: renders other cameras/BEV)")
    ax.set(xscale="log", xlabel="median latency (ms, wall)",
           ylabel=f"PSNR vs full quality (dB; exact = {PSNR_CAP_DB:g})",
           title="knobs: latency vs error against the full-quality render")
    ax.legend(fontsize=7)
    ax.grid(True, alpha=0.3)
    if with_gt:
        ax = axes[0, 1]
        for p in with_gt:
            ax.scatter(p["wall_ms"], p["psnr_vs_gt"], color="C2")
            ax.annotate(p["label"], (p["wall_ms"], p["psnr_vs_gt"]), fontsize=7, xytext=(3, 3),
                        textcoords="offset points")
        ax.set(xscale="log", xlabel="median latency (ms, wall)", ylabel="PSNR vs ground truth (dB)",
               title="against the dataset's image")
        ax.grid(True, alpha=0.3)
    save_figure(fig, png)
