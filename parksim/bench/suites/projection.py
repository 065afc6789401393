"""``parksim bench projection``: the fused numba projection against the torch reference path of
``project_gaussians``, or against a package copy's fused path (``--reference MODULE``), as ``render()`` runs it per
camera.

A four-camera surround rig (640x480 OpenCV fisheyes, 190 deg, 1 m up, looking forward, left, back and right) in a
40 x 40 x 3 m box of random Gaussians (3-sigma 5 cm - 1 m, random orientation), float32. One call projects the
scene into the first 1 or all 4 cameras (world -> camera transform, cull, UT), forward, or forward and backward
of a sum of the means, conics and depths. Without a reference the torch path is timed at most 3 times (it is slow),
after the fused path; with one, the two packages' calls alternate (``time_medians``).
"""

from __future__ import annotations

import importlib
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from ..cases import count_text
from ..common import Timing, progress, set_threads, time_medians
from ..record import Figure
from ..suite import Context, Outcome, Suite

__all__ = ["ProjectionSuite", "ProjectionOptions", "TORCH_REPEATS"]

TORCH_REPEATS = 3
"""At most this many timed calls of the torch path."""
Scene = tuple[Any, Any, Any]


@dataclass(frozen=True)
class ProjectionOptions:
    """Options of ``parksim bench projection``."""

    gaussians: list[int] = field(default_factory=lambda: [100_000, 200_000], metadata={
        "help": "scene sizes", "low": 1, "quick": [2_000]})
    repeats: int = field(default=5, metadata={"help": f"timed calls per case (torch path: {TORCH_REPEATS} at most)",
                                              "low": 1, "quick": 1})
    threads: int | None = field(default=None, metadata={"help": "torch and numba threads (default: theirs)",
                                                        "low": 1})
    reference: str | None = field(default=None, metadata={
        "help": "module name of a package copy whose fused path is timed alongside (instead of the torch path)",
        "metavar": "MODULE"})


def make_scene(n: int, seed: int) -> Scene:
    """``(means, quats, log_scales)`` float32 of ``n`` Gaussians in a 40 x 40 x 3 m box around the origin."""
    import torch

    g = torch.Generator().manual_seed(seed)
    means = (torch.rand(n, 3, generator=g) - torch.tensor([0.5, 0.5, 0.0])) * torch.tensor([40.0, 40.0, 3.0])
    quats = torch.randn(n, 4, generator=g)
    log_scales = torch.log(torch.rand(n, 3, generator=g) * 0.3 + 0.017)
    return means, quats, log_scales


def make_rig(package: str) -> list[tuple[Any, Any, Any]]:
    """``(camera, R_cam_world, t_cam_world)`` of four 190 deg fisheyes at the origin, 1 m up (``package``'s camera
    class: the fused path dispatches on it)."""
    import torch

    from ...geometry import rotation_from_quaternion

    fisheye = importlib.import_module(f"{package}.camera").OpenCVFisheye
    cam = fisheye(640, 480, 160.0, 160.0, 319.5, 239.5, [0.05, -0.01, 0.002, -0.0005], max_fov_deg=190.0)
    front = torch.tensor([[0.0, -1.0, 0.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0]])  # camera z along world +x
    rig = []
    for yaw in (0.0, 0.5 * torch.pi, torch.pi, 1.5 * torch.pi):
        half = torch.tensor(0.5 * yaw)
        R_world_cam = rotation_from_quaternion(torch.stack([half.cos(), torch.tensor(0.0), torch.tensor(0.0),
                                                            half.sin()])) @ front.T
        R = R_world_cam.T.contiguous()
        rig.append((cam, R, -R @ torch.tensor([0.0, 0.0, 1.0])))
    return rig


def project_rig(scene: Scene, rig: list[tuple[Any, Any, Any]], backend: str, backward: bool, package: str) -> None:
    """Project the scene into every camera of ``rig`` (as ``render()`` does) with ``package``'s
    ``project_gaussians``; with ``backward`` back-propagate the sum of means, conics and depths."""
    import torch

    project_gaussians = importlib.import_module(f"{package}.render.projection").project_gaussians
    means, quats, log_scales = (t.detach().requires_grad_(backward) for t in scene)
    loss = torch.zeros(())
    for cam, R, t in rig:
        p = project_gaussians(means @ R.T + t, (quats, log_scales, R), cam, backend=backend)
        if backward:
            loss = loss + p.means2d.sum() + p.conics.sum() + p.depths.sum()
    if backward:
        loss.backward()


def _pair(scene: Scene, rigs: dict[str, list[tuple[Any, Any, Any]]], n_cams: int, backward: bool,
          options: ProjectionOptions) -> tuple[Timing, Timing]:
    """(this tree's fused path, the reference: the copy's fused path, else this tree's torch path)."""
    def call(package: str, backend: str) -> Callable[[], None]:
        return lambda: project_rig(scene, rigs[package][:n_cams], backend, backward, package)

    if options.reference:
        new, old = time_medians([call("parksim", "fused"), call(options.reference, "fused")], options.repeats)
        return new, old
    return (time_medians([call("parksim", "fused")], options.repeats)[0],
            time_medians([call("parksim", "torch")], min(options.repeats, TORCH_REPEATS))[0])


class ProjectionSuite(Suite):
    """The fused projection against the torch path or a package copy's fused path."""

    name = "projection"
    help = "fused numba projection vs the torch path (or a package copy), 1 and 4 fisheyes, fwd and fwd+bwd"
    description = ("Projection as render() runs it per camera (world -> camera, cull, UT) of random Gaussians in a "
                   "40 x 40 x 3 m box into 1 or 4 640x480 190 deg fisheyes, forward and forward+backward, float32. "
                   "Figures: the fused path's median wall ms (process CPU beside) against the torch path's, or "
                   "with --reference MODULE against that package copy's fused path, called alternately.")
    Options = ProjectionOptions

    def run(self, options: ProjectionOptions, context: Context) -> Outcome:
        """Time every (size, cameras, pass) case."""
        if options.threads:
            set_threads(options.threads)
        packages = ["parksim"] + ([options.reference] if options.reference else [])
        rigs = {p: make_rig(p) for p in packages}
        label = f"package copy {options.reference}, same process" if options.reference else "torch path, same run"
        figures: list[Figure] = []
        rows: list[dict[str, Any]] = []
        cases = [(n, c, b) for n in options.gaussians for c in (1, 4) for b in (False, True)]
        with progress(len(cases), "bench projection", context.quiet) as bar:
            for n in options.gaussians:
                scene = make_scene(n, context.seed)
                for n_cams in (1, 4):
                    for backward in (False, True):
                        fused, ref = _pair(scene, rigs, n_cams, backward, options)
                        cams = f"{n_cams} fisheye{'s' if n_cams > 1 else ''} 640x480 190 deg"
                        target = f"projection {'fwd+bwd' if backward else 'fwd'}, {cams}, {count_text(n)} Gaussians"
                        figures.append(Figure(target, fused.wall_ms, "ms", cpu=fused.cpu_ms, reference=ref.wall_ms,
                                              reference_cpu=ref.cpu_ms, reference_label=label))
                        rows.append({"gaussians": n, "cameras": n_cams, "backward": backward, "fused": fused,
                                     "reference": ref})
                        bar.update(1)
        return Outcome(figures, {"reference": options.reference or "torch", "rows": rows})
