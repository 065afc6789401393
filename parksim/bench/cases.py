"""The speed issue's render cases, shared by ``parksim bench render`` (CPU, against a package copy) and
``parksim bench gpu`` (ParkSim on CUDA, against the CPU path and gsplat's 3DGUT): their sizes as options, their
targets, and one timed render of a case (forward, or forward and backward of a fixed weighting of the images).

The scene is a dataset's surface points densified to N Gaussians (``parksim.bench.scenes.garage_scene``); the
rig is the dataset's, scaled to the case's width, with a square BEV of ``bev_px`` over the rig's own extent; the
pose is one frame of the dataset's trajectory. Heavy imports (torch) happen inside the functions.
"""

from __future__ import annotations

import dataclasses
import json
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

__all__ = ["CaseSizes", "Case", "case", "count_text", "bev_rig", "load_pose", "render_case", "CAMERA"]

CAMERA = "front"
"""The camera of the one-camera cases (its width is the rig's base width)."""


@dataclass(frozen=True)
class CaseSizes:
    """The cases' scene sizes and image widths (the base of the render and gpu suites' options)."""

    gaussians_a: int = field(default=100_000, metadata={
        "help": "Gaussians of case (a), one camera", "low": 1, "quick": 2_000})
    width_a: int = field(default=320, metadata={
        "help": "camera width of case (a) (height by the rig's aspect)", "low": 8, "quick": 80})
    gaussians_b: int = field(default=200_000, metadata={
        "help": "Gaussians of case (b), every camera + BEV", "low": 1, "quick": 4_000})
    width_b: int = field(default=640, metadata={"help": "camera width of case (b)", "low": 8, "quick": 160})
    bev_px: int = field(default=512, metadata={"help": "side of the square BEV (same ground extent as the rig's)",
                                               "low": 8, "quick": 64})


@dataclass(frozen=True)
class Case:
    """One timed configuration of ``render()``.

    Attributes:
        group: the case family (``a``, ``b``, ``c``, ...), what ``--cases`` selects.
        target: the record's row key, naming every condition.
        n: Gaussians.
        scale: image size relative to the rig's cameras.
        cameras: the cameras rendered (None: all).
        bev: whether the BEV is rendered too.
        backward: also back-propagate a fixed weighting of the images.
        skip_off: the skip switched off (``cull``, ``early_stop``), or empty.
        goal: the stated target when the case is the issue's own size, else None.
    """

    group: str
    target: str
    n: int
    scale: float
    cameras: tuple[str, ...] | None
    bev: bool
    backward: bool = False
    skip_off: Literal["", "cull", "early_stop"] = ""
    goal: str | None = None


def count_text(n: int) -> str:
    """``100000`` -> ``1e5``, ``4000`` -> ``4e3``; other counts with thousands separators."""
    digits = len(str(n)) - 1
    if n >= 1000 and n % 10 ** digits == 0:
        return f"{n // 10 ** digits}e{digits}"
    return f"{n:,}"


def case(group: str, label: str, n: int, width: int, rig: Any, cameras: tuple[str, ...] | None, bev: bool,
         backward: bool = False, skip_off: Literal["", "cull", "early_stop"] = "", goal: str | None = None) -> Case:
    """A case whose target names its pass, cameras, size, BEV, Gaussians and skip switched off.

    Args:
        group: the case family (``--cases``).
        label: the target's first words (``"case (a)"``).
        n: Gaussians.
        width: camera width; the height follows the rig's aspect.
        rig: the rig with its BEV already sized (``bev_rig``).
        cameras: cameras to render (None: all).
        bev: render the BEV too.
        backward: forward and backward.
        skip_off: the skip switched off.
        goal: the stated target, if any.

    Returns:
        The case.
    """
    model = rig.cameras[CAMERA].model
    scale = width / model.width
    count = len(cameras) if cameras is not None else len(rig.names)
    views = f"{count} camera{'s' if count > 1 else ''} {width}x{round(model.height * scale)}"
    views += f" + BEV {rig.bev.width}" if bev else ""
    off = {"": "", "cull": ", culling off", "early_stop": ", early stop off"}[skip_off]
    target = f"{label} {'fwd+bwd' if backward else 'fwd'}, {views}, {count_text(n)} Gaussians{off}"
    return Case(group, target, n, scale, cameras, bev, backward, skip_off, goal)


def bev_rig(rig: Any, px: int) -> Any:
    """``rig`` (any package copy's ``Rig``) with a ``px`` x ``px`` BEV over the same ground extent (in place)."""
    b = rig.bev
    rig.bev = dataclasses.replace(b, width=px, height=px, m_per_px=b.m_per_px * b.width / px)
    return rig


def load_pose(dataset: Path, frame: int) -> Any:
    """``T_world_vehicle`` ``(4, 4)`` float64 of frame ``frame`` (modulo the trajectory's length) of the dataset."""
    import torch

    frames = json.loads((dataset / "poses.json").read_text())["frames"]
    return torch.tensor(frames[frame % len(frames)]["T_world_vehicle"], dtype=torch.float64)


def render_case(render_fn: Callable[..., Any], scene: Any, rig: Any, pose: Any, case: Case,
                weights: dict[str, Any], **kwargs: Any) -> None:
    """Render ``case`` once; with ``case.backward`` also back-propagate a fixed random weighting of the images.

    Args:
        render_fn: a package's ``render``.
        scene: that package's ``GaussianScene`` (leaves with gradients for a backward case).
        rig: that package's rig.
        pose: ``(4, 4)`` ``T_world_vehicle``.
        case: what to render.
        weights: per camera the loss weights ``(H, W, 3)``, drawn on first use (seeded, on the images' device) so
            every call does the same work.
        **kwargs: passed to ``render_fn`` (``backend``).
    """
    import torch

    with torch.set_grad_enabled(case.backward):
        out = render_fn(scene, rig, pose, cameras=case.cameras, bev=case.bev, scale=case.scale, **kwargs)
    if case.backward:
        for name, img in out.images.items():
            if name not in weights:
                weights[name] = torch.rand(img.shape, generator=torch.Generator().manual_seed(1)).to(img)
        sum((img * weights[name]).sum() for name, img in out.images.items()).backward()
