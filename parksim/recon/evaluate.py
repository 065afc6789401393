"""Evaluation: render test views, score PSNR/SSIM (whole valid image and slot regions), write side-by-sides."""

from __future__ import annotations

import dataclasses
import math
import statistics
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import torch
from torch import Tensor

from parksim.data import DatasetReader
from parksim.gaussians import GaussianScene
from parksim.imageio import write_image
from parksim.render import render
from parksim.rig import Rig

from .config import PoseRefineConfig
from .masks import scene_mask
from .metrics import psnr, slot_region_mask, slot_segments, ssim
from .plots import plot_offpath
from .pose_refine import POSES_KEY, PoseCorrections, align_poses
from .scaled import at_scale, scaled_rig

if TYPE_CHECKING:
    from parksim.bundle import Bundle

__all__ = ["render_view", "evaluate_views", "EvalReport", "summarize", "group_means"]

Response = Callable[[Tensor, str], Tensor]
ViewPose = Callable[[str, int], Tensor]
"""``(camera, frame) -> T_world_vehicle`` to render that view at (``DatasetReader.view_pose`` or a refined one)."""


def render_view(scene: GaussianScene, reader: DatasetReader, frame: int, camera: str, response: Response | None,
                backend: str, rig: Rig | None = None, view_pose: ViewPose | None = None, method: str = "ut") -> Tensor:
    """One camera of one frame, through the camera's learned response when given (HxWx3, unclamped).

    ``rig`` and ``view_pose`` default to the dataset's; pose refinement passes its refined rig and poses;
    ``method`` is the projection the scene was trained with (``bundle.projection``)."""
    pose = (view_pose or reader.view_pose)(camera, frame)
    image = render(scene, rig or reader.rig, pose, cameras=[camera], backend=backend, method=method).images[camera]
    return response(image, camera) if response is not None else image


@dataclass
class EvalReport:
    """Per-view scores and their means; slot scores only where the view has slot pixels."""

    views: list[dict[str, Any]] = field(default_factory=list)

    def mean(self, key: str, **where: Any) -> float | None:
        """Mean of ``key`` over views matching ``where`` that have it (None when none do)."""
        vals = [v[key] for v in self.views if v.get(key) is not None and all(v[k] == x for k, x in where.items())]
        return statistics.fmean(vals) if vals else None


_SCORES = ("psnr", "ssim", "slot_psnr", "slot_ssim")
"""The per-view scores every summary averages."""


def summarize(report: EvalReport, cameras: list[str], frames: list[int]) -> dict[str, Any]:
    """Overall, per-camera and per-frame means of every score."""
    return {"overall": {k: report.mean(k) for k in _SCORES},
            "per_camera": {c: {k: report.mean(k, camera=c) for k in _SCORES} for c in cameras},
            "per_frame": {str(f): {k: report.mean(k, frame=f) for k in _SCORES} for f in frames}}


def group_means(report: EvalReport, groups: Mapping[str, Sequence[int]]) -> dict[str, dict[str, Any]]:
    """Means of every score over the views of each group of frames, with the view counts behind them
    (``views``; ``slot_views``: those with slot pixels)."""
    out = {}
    for label, frames in groups.items():
        keep = set(frames)
        sub = EvalReport([v for v in report.views if v["frame"] in keep])
        out[label] = {"views": len(sub.views), "slot_views": sum(v.get("slot_psnr") is not None for v in sub.views),
                      **{k: sub.mean(k) for k in _SCORES}}
    return out


@torch.no_grad()
def evaluate_views(scene: GaussianScene, reader: DatasetReader, views: list[tuple[int, str]],
                   response: Response | None, backend: str = "auto", slots: bool = True,
                   side_by_side: Path | None = None, rig: Rig | None = None,
                   view_pose: ViewPose | None = None, method: str = "ut") -> EvalReport:
    """Score each ``(frame, camera)`` view against the dataset over the camera's scene mask (rendered with ``rig``
    at ``view_pose``, the dataset's by default, by projection ``method``).

    Renders and scores run on the scene's device (``response`` must be there too); the slot-region masks are
    found on the CPU (a ray-floor test per pixel, once per view) and moved there."""
    rig, view_pose = rig or reader.rig, view_pose or reader.view_pose
    device = scene.means.device
    masks = {c: scene_mask(rig.cameras[c], rig.bev).to(device) for c in {c for _, c in views}}
    segments = slot_segments(reader.map) if slots and reader.layout.map.is_file() else torch.zeros(0, 2, 2)
    report = EvalReport()
    for frame, camera in views:
        gt = reader.image(camera, frame).to(device)
        pred = render_view(scene, reader, frame, camera, response, backend, rig, view_pose, method).clamp(0.0, 1.0)
        mask = masks[camera]
        row: dict[str, Any] = {"frame": frame, "camera": camera,
                               "psnr": psnr(pred, gt, mask), "ssim": ssim(pred, gt, mask)}
        if len(segments):
            depth_path = reader.layout.depth(camera, frame)
            depth = reader.depth(camera, frame) if depth_path.is_file() else None
            slot = slot_region_mask(rig.cameras[camera], view_pose(camera, frame).cpu(), segments,
                                    depth).to(device) & mask
            if slot.any():
                row["slot_psnr"], row["slot_ssim"] = psnr(pred, gt, slot), ssim(pred, gt, slot)
            row["slot_pixels"] = int(slot.sum())
        if side_by_side is not None:
            shown = torch.where(mask[..., None], pred, pred * 0.3)
            write_image(side_by_side / f"{frame:06d}_{camera}.png", torch.cat([shown, gt], dim=1))
        report.views.append({k: (None if isinstance(v, float) and math.isinf(v) else v) for k, v in row.items()})
    return report


def _aligned_poses(bundle: Bundle, reader: DatasetReader, views: list[tuple[int, str]], response: Response,
                   backend: str, steps: int | None) -> tuple[Rig, PoseCorrections | None, str]:
    """The rig and test poses to score a bundle at, and a note saying how: a pose-refined bundle renders with its
    refined rig at test poses aligned for ``steps`` (None: its run's ``pose_opt.test_steps``) with Gaussians frozen."""
    refinement = bundle.meta.get(POSES_KEY)
    if refinement is None:
        return reader.rig, None, "off (the bundle was trained without pose refinement)"
    cfg = PoseRefineConfig.model_validate(refinement["config"])
    steps = cfg.test_steps if steps is None else steps
    if steps == 0:
        return bundle.rig, None, "off: test frames scored at their recorded poses with the refined rig"
    aligned = align_poses(bundle.scene, reader, bundle.rig, views, response, cfg, steps, backend)
    return bundle.rig, aligned, (f"test-time pose alignment: each test {refinement['mode']} pose fitted "
                                           f"for {steps} Adam steps with the Gaussians frozen, then scored")


def _score_split(bundle: Bundle, reader: DatasetReader, response: Response, backend: str, align_steps: int | None,
                 side_by_side: Path | None = None) -> tuple[EvalReport, Rig, PoseCorrections | None, str]:
    """Every test view of ``reader`` scored as ``evaluate_bundle`` scores them (pose-refined bundles aligned first)."""
    views = [(f, c) for f in reader.split["test"] for c in reader.rig.names]
    rig, aligned, alignment = _aligned_poses(bundle, reader, views, response, backend, align_steps)
    view_pose = aligned.view_pose if aligned is not None else None
    report = evaluate_views(bundle.scene, reader, views, response, backend, side_by_side=side_by_side, rig=rig,
                            view_pose=view_pose, method=bundle.projection)
    return report, rig, aligned, alignment


def offpath_split(data_dir: Path) -> Path | None:
    """The dataset's off-path split folder (``parksim offpath``), or None when it has none."""
    from parksim.synth.offpath import OFFPATH_DIR, OFFPATH_FILE

    split = Path(data_dir) / OFFPATH_DIR
    return split if (split / OFFPATH_FILE).is_file() else None


def _offpath(bundle: Bundle, split: Path, response: Response, backend: str, align_steps: int | None,
             on_path: EvalReport, image_scale: float) -> dict[str, Any]:
    """Scores on the off-path split grouped by kind and offset, beside the on-path reference (the recorded test
    views ``on_path``); per-view rows carry their pose's kind and signed offset."""
    from parksim.synth.offpath import group_frames, read_offpath

    reader = at_scale(DatasetReader(split), image_scale)
    info = read_offpath(split)
    descriptors = {d["frame"]: d for d in info["frames"]}
    report, _, _, alignment = _score_split(bundle, reader, response, backend, align_steps)
    groups = group_frames(list(descriptors.values()))
    means = group_means(report, {label: g["frames"] for label, g in groups.items()})
    on_frames = sorted({v["frame"] for v in on_path.views})
    reference = {"frames": len(on_frames), **group_means(on_path, {"on path": on_frames})["on path"]}
    return {"dataset": str(split), "pose_alignment": alignment,
            "skipped": info["skipped"],
            "on_path": reference,
            "groups": [{"group": label, "kind": g["kind"], "offset": g["offset"], "frames": len(g["frames"]),
                        **means[label]} for label, g in groups.items()],
            "views": [{**v, "kind": descriptors[v["frame"]]["kind"], "offset": descriptors[v["frame"]]["offset"]}
                      for v in report.views]}


def evaluate_bundle(scene_dir: Path, data_dir: Path, out_dir: Path, backend: str = "auto",
                    lpips: Callable[[Tensor, Tensor, Tensor], float] | None = None,
                    align_steps: int | None = None, offpath: bool = True,
                    projection: str | None = None, device: torch.device | None = None,
                    image_scale: float | None = None) -> dict[str, Any]:
    """Score a bundle on the dataset's test frames; writes ``eval.json``, ``eval.md`` and side-by-side PNGs.

    Views are rendered with the projection the bundle was trained with (``Bundle.projection``, as the server
    renders it), or with ``projection`` to see what the other one gives; eval.json's ``projection`` says which.

    A pose-refined bundle's test poses are aligned first (``align_steps``; None: as its run configured, 0: off);
    eval.json then holds them as ``aligned_test_poses`` (poses.json schema). With ``offpath`` and an off-path split
    in the dataset (``parksim offpath``), its views are scored the same way and grouped by offset: eval.json's
    ``offpath``, a table in eval.md and ``offpath.png``.

    Views are scored at the image scale the bundle was trained at (its meta's ``image_scale``, the run's
    ``data.image_scale``: the dataset's images resized and the bundle's cameras scaled as in training), or at
    ``image_scale`` in (0, 1]; eval.json's ``image_scale`` says which.

    Everything renders and scores on ``device`` (a ``parksim.device.resolve_device`` result; None: the CPU), where
    ``lpips`` must run too."""
    from parksim.bundle import load
    from parksim.fileio import write_json

    from .response import CameraResponse

    bundle = load(scene_dir)
    scale = float(bundle.meta.get("image_scale", 1.0)) if image_scale is None else image_scale
    if not 0 < scale <= 1:
        raise ValueError(f"image scale must be in (0, 1], got {scale}")
    reader = at_scale(DatasetReader(data_dir), scale)
    bundle = dataclasses.replace(bundle, scene=bundle.scene.to(device=device), rig=scaled_rig(bundle.rig, scale))
    if projection is not None:
        bundle = dataclasses.replace(bundle, meta={**bundle.meta, "projection": projection})
    response = CameraResponse(reader.rig, 0.0, device)
    response.load_dict(bundle.meta.get("camera_response", {}))
    frames = reader.split["test"]
    if not frames:
        raise ValueError(f"{data_dir}: no test frames in split.json")
    (out_dir / "renders").mkdir(parents=True, exist_ok=True)
    report, rig, aligned, alignment = _score_split(bundle, reader, response, backend, align_steps,
                                                   out_dir / "renders")
    view_pose = aligned.view_pose if aligned is not None else None
    if lpips is not None:
        masks = {c: scene_mask(rig.cameras[c], rig.bev).to(device) for c in rig.names}
        for row in report.views:
            pred = render_view(bundle.scene, reader, row["frame"], row["camera"], response, backend, rig,
                               view_pose, bundle.projection).clamp(0, 1)
            row["lpips"] = lpips(pred, reader.image(row["camera"], row["frame"]).to(device), masks[row["camera"]])
    summary = summarize(report, reader.rig.names, frames)
    summary["overall"]["lpips"] = report.mean("lpips")
    result = {"scene": str(scene_dir), "dataset": str(data_dir), "test_frames": frames,
              "projection": bundle.projection, "image_scale": scale,
              "lpips": "computed" if lpips is not None else "not computed (no LPIPS weights given)",
              "pose_alignment": alignment, **summary, "views": report.views}
    if aligned is not None:
        result["aligned_test_poses"] = aligned.refined_poses(frames)
    split = offpath_split(data_dir) if offpath else None
    if split is not None:
        result["offpath"] = _offpath(bundle, split, response, backend, align_steps, report, scale)
        plot_offpath(result["offpath"], out_dir / "offpath.png")
    write_json(out_dir / "eval.json", result)
    (out_dir / "eval.md").write_text(_table(result, reader.rig.names))
    return result


def _cell(v: float | None, digits: int) -> str:
    return "n/a" if v is None else f"{v:.{digits}f}"


def _table(result: dict[str, Any], cameras: list[str]) -> str:
    """Markdown: overall and per-camera scores; LPIPS marked when it was not computed."""
    o = result["overall"]
    lpips = _cell(o["lpips"], 3) if o["lpips"] is not None else "not computed"
    lines = ["| view | PSNR | SSIM | slot PSNR | slot SSIM |", "| --- | --- | --- | --- | --- |"]
    for name, s in [("all test views", o)] + [(c, result["per_camera"][c]) for c in cameras]:
        lines.append(f"| {name} | {_cell(s['psnr'], 2)} | {_cell(s['ssim'], 3)} | {_cell(s['slot_psnr'], 2)} | "
                     f"{_cell(s['slot_ssim'], 3)} |")
    text = "\n".join(lines) + f"\n\nLPIPS: {lpips}\n\nTest poses: {result['pose_alignment']}\n"
    return text + (_offpath_table(result["offpath"]) if "offpath" in result else "")


def _offpath_table(off: dict[str, Any]) -> str:
    """Markdown: scores on the recorded path and at each off-path offset (docs/offpath.md), plot below."""
    ref = off["on_path"]
    lines = ["", "### Off the recorded path", "",
             "| poses | frames | views | PSNR | SSIM | slot PSNR | slot SSIM | PSNR - on path |",
             "| --- | --- | --- | --- | --- | --- | --- | --- |"]
    for name, s in [("on path (recorded test frames)", ref)] + [(g["group"], g) for g in off["groups"]]:
        drop = None if s["psnr"] is None or ref["psnr"] is None else s["psnr"] - ref["psnr"]
        lines.append(f"| {name} | {s['frames']} | {s['views']} | {_cell(s['psnr'], 2)} | "
                     f"{_cell(s['ssim'], 3)} | {_cell(s['slot_psnr'], 2)} | {_cell(s['slot_ssim'], 3)} | "
                     f"{_cell(drop, 2)} |")
    skipped = ", ".join(f"{k} {v}" for k, v in sorted(off["skipped"].items())) or "none"
    return "\n".join(lines) + (f"\n\nSkipped poses: {skipped}. Off-path poses: {off['pose_alignment']}. "
                               "Plot: offpath.png.\n")
