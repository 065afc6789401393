"""``parksim bench render``: latency against error over the knobs a user can turn.

Each point changes one knob from the full-quality setting (first input, scale 1, full SH, UT projection,
all cameras, no BEV, auto backend, most threads): input bundle (e.g. compaction levels), resolution scale,
SH degree cap, UT vs EWA, cameras/BEV requested, rasterizer backend, thread count. A point records the
median latency after a warm-up, the error against the full-quality render (PSNR, max abs; a scaled render
is upsampled bilinearly first) and, for trained bundles, the PSNR against the dataset's ground truth.
"""

from __future__ import annotations

import argparse
import math
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import torch
import torch.nn.functional as F

from ..bundle import Bundle
from ..bundle import load as load_bundle
from ..data import DatasetReader
from ..gaussians import GaussianScene
from ..render import RenderResult, render
from ..rig import Rig
from .common import md_table, metadata, progress, pyplot, save_figure, set_threads, time_medians, write_result
from .scenes import cap_sh_degree, garage_scene

__all__ = ["run", "Knobs", "Input", "GroundTruth", "knob_grid", "PSNR_CAP_DB"]

PSNR_CAP_DB = 80.0
"""Where the plot puts renders identical to the reference (PSNR = inf)."""


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
        """Short description of the changed knob's value."""
        value = {"input": f"input {self.input}", "scale": f"scale {self.scale:g}", "sh": f"SH <= {self.sh_degree}",
                 "method": self.method, "cameras": "+".join(self.cameras or ("all",)) + (" + BEV" if self.bev else ""),
                 "backend": self.backend, "threads": f"{self.threads} thread{'s' if self.threads > 1 else ''}"}
        return "full quality" if self.knob == "full" else value[self.knob]

    @property
    def same_output(self) -> bool:
        """Whether the point renders what the full-quality point renders (only then on the Pareto front)."""
        return self.knob not in ("cameras",)


@dataclass(frozen=True)
class Input:
    """A scene to render: a trained bundle (with its dataset's ground truth) or a built garage scene."""

    label: str
    scene: GaussianScene
    bundle: Bundle | None


def knob_grid(args: argparse.Namespace, n_inputs: int, sh_degree: int, camera_names: list[str]) -> list[Knobs]:
    """The full-quality point, then each knob's other values with everything else at full quality."""
    base = Knobs("full", threads=max(args.threads))
    points = [base]
    points += [replace(base, knob="input", input=i) for i in range(1, n_inputs)]
    points += [replace(base, knob="scale", scale=s) for s in args.scales if s != 1.0]
    points += [replace(base, knob="sh", sh_degree=d) for d in args.sh_degrees if d < sh_degree]
    points += [replace(base, knob="method", method=m) for m in args.methods if m != "ut"]
    for spec in args.camera_sets:
        names, bev = spec.removesuffix("+bev"), spec.endswith("+bev")
        cams = None if names == "all" else tuple(names.split("+"))
        if (cams, bev) != (None, False):
            points.append(replace(base, knob="cameras", cameras=cams, bev=bev))
    points += [replace(base, knob="backend", backend=b) for b in args.backends if b != "auto"]
    points += [replace(base, knob="threads", threads=t) for t in args.threads if t != base.threads]
    return points


def _inputs(args: argparse.Namespace) -> tuple[list[Input], Rig, Path]:
    """The scenes to compare (bundles first), the rig they share and the dataset giving pose and ground truth."""
    bundles = [load_bundle(path) for path in args.bundle]
    inputs = [Input(f"{path.name} ({len(b.scene):,} G)", b.scene, b) for path, b in zip(args.bundle, bundles)]
    dataset = args.dataset or (Path(bundles[0].meta["dataset"]) if bundles and "dataset" in bundles[0].meta else None)
    if dataset is None:
        raise ValueError("bench render: give --dataset (pose, rig and ground truth), or a --bundle trained from one")
    if not inputs:
        inputs.append(Input(f"garage from {dataset.name} ({args.gaussians:,} G)",
                            garage_scene(dataset, args.gaussians, args.seed), None))
    rig = inputs[0].bundle.rig if inputs[0].bundle is not None else Rig.load(dataset / "rig.json")
    return inputs, rig, dataset


def _closure(inputs: list[Input], rig: Rig, pose: torch.Tensor, k: Knobs) -> Callable[[], RenderResult]:
    """A no-grad render of the point's input at its knob settings (its thread count set first)."""
    item = inputs[k.input]
    scene = cap_sh_degree(item.scene, k.sh_degree) if k.sh_degree is not None else item.scene

    def once() -> RenderResult:
        set_threads(k.threads)
        with torch.no_grad():
            return render(scene, rig, pose, cameras=k.cameras, bev=k.bev, scale=k.scale, backend=k.backend,
                          method=k.method)

    return once


def _upsampled(image: torch.Tensor, like: torch.Tensor) -> torch.Tensor:
    """``image`` (HxWx3) resized bilinearly to ``like``'s size (unchanged when equal)."""
    if image.shape == like.shape:
        return image
    chw = F.interpolate(image.permute(2, 0, 1)[None], size=like.shape[:2], mode="bilinear", align_corners=False)
    return chw[0].permute(1, 2, 0)


def _errors(images: dict[str, torch.Tensor], reference: dict[str, torch.Tensor]) -> tuple[float, float]:
    """PSNR (dB, peak 1) and max abs error of the images against the reference's same cameras."""
    diffs = torch.cat([(_upsampled(img, reference[c]) - reference[c]).flatten() for c, img in images.items()])
    mse = float((diffs ** 2).mean())
    return (math.inf if mse == 0 else -10 * math.log10(mse)), float(diffs.abs().max())


class GroundTruth:
    """PSNR of a bundle's renders against the dataset's images at one frame, through the learned camera response."""

    def __init__(self, dataset: Path, frame: int, rig: Rig) -> None:
        from parksim.recon.masks import scene_mask

        reader = DatasetReader(dataset)
        self.images = {c: reader.image(c, frame) for c in rig.names}
        self.masks = {c: scene_mask(rig.cameras[c], rig.bev) for c in rig.names}
        self.rig = rig

    def psnr(self, images: dict[str, torch.Tensor], bundle: Bundle) -> float:
        """Mean over the rendered cameras of the masked PSNR (the bundle's response applied when it has one)."""
        from parksim.recon.metrics import psnr
        from parksim.recon.response import CameraResponse

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


def run(args: argparse.Namespace) -> Any:
    """Measure every knob point and write ``render.json/md/png``."""
    inputs, rig, dataset = _inputs(args)
    reader = DatasetReader(dataset)
    frame = args.frame if args.frame is not None else (reader.split["test"] or reader.frames)[0]
    pose = reader.pose(frame)
    gt = GroundTruth(dataset, frame, rig) if any(i.bundle is not None for i in inputs) else None
    grid = knob_grid(args, len(inputs), inputs[0].scene.sh_degree, rig.names)
    set_threads(max(args.threads))
    meta = {**metadata(args.command_line), "dataset": str(dataset), "frame": frame,
            "inputs": [i.label for i in inputs]}
    closures = [_closure(inputs, rig, pose, k) for k in grid]
    with progress(args.warmup + args.repeats, "bench render (rounds over all points)", args.quiet) as bar:
        timings = time_medians(closures, args.repeats, args.warmup, tick=lambda: bar.update(1))
    renders = [once().images for once in closures]
    points: list[dict[str, Any]] = []
    for k, timing, images in zip(grid, timings, renders):
        item = inputs[k.input]
        psnr_full, max_err = _errors(images, renders[0])
        points.append({"knob": k.knob, "label": k.label, "input": item.label, "same_output": k.same_output,
                       "wall_ms": timing.wall_ms, "cpu_ms": timing.cpu_ms, "psnr_vs_full": psnr_full,
                       "max_abs_vs_full": max_err,
                       "psnr_vs_gt": gt.psnr(images, item.bundle) if gt and item.bundle else None})
    set_threads(max(args.threads))
    _pareto(points)
    rows = [(p["knob"], p["label"], f"{p['wall_ms']:.1f}", f"{p['cpu_ms']:.1f}", _db(p["psnr_vs_full"]),
             f"{p['max_abs_vs_full']:.3g}", _db(p["psnr_vs_gt"]), "yes" if p["pareto"] else "") for p in points]
    body = [f"Inputs: {'; '.join(f'{i}: {x.label}' for i, x in enumerate(inputs))}. Pose: frame {frame} of "
            f"`{dataset}`; rig {len(rig.names)} cameras at {_size(rig)}; medians of {args.repeats} renders after "
            f"{args.warmup} warm-up, the points called in turn in each round (a change of load hits all alike); "
            f"full quality = input 0, scale 1, SH {inputs[0].scene.sh_degree}, UT, all "
            f"cameras, no BEV, auto backend, {max(args.threads)} threads.", "",
            *md_table(["knob", "value", "wall ms", "CPU ms", "PSNR vs full (dB)", "max abs vs full", "PSNR vs GT (dB)",
                       "Pareto"], rows)]
    return write_result(args.out, "render", meta, {"points": points},
                        body, lambda png: _plot(points, meta, png))


def _db(v: float | None) -> str:
    return "-" if v is None else "exact" if math.isinf(v) else f"{v:.2f}"


def _size(rig: Rig) -> str:
    m = rig.cameras[rig.names[0]].model
    return f"{m.width}x{m.height}"


def _plot(points: list[dict[str, Any]], meta: dict[str, Any], png: Path) -> None:
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
           title="render: latency vs error against the full-quality render")
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
    save_figure(fig, meta, png)
