"""Projection speed on this machine: fused numba kernel vs the torch reference path of ``project_gaussians``.

A four-camera surround rig (640x480 OpenCV fisheyes, 190 deg, 1 m up, looking forward/back/left/right)
inside a 40 x 40 x 3 m box of random Gaussians (3-sigma 5 cm - 1 m, random orientation). Times the
projection as ``render()`` runs it per camera (world -> camera transform, cull, UT), forward and
forward+backward (a weighted sum of means, conics and depths as the loss), 1 and 4 cameras, 1e5 and 2e5
Gaussians, float32. Reports medians after a warm-up and the torch/fused ratio; --out writes markdown.
``--reference MODULE`` times that importable copy of the package's fused path instead of the torch path,
alternately with this tree's (wall and process-CPU medians), for A/B runs of the kernels.

    .venv/bin/python benchmarks/bench_projection.py --out benchmarks/RESULTS_projection.md
    PYTHONPATH=/tmp/ab .venv/bin/python benchmarks/bench_projection.py --reference parksim_prev --threads 1
"""

from __future__ import annotations

import argparse
import datetime
import importlib
import os
import platform
import sys
from typing import Any

import numba
import torch

from parksim.bench.common import cpu_model, time_medians
from parksim.geometry import rotation_from_quaternion

Scene = tuple[torch.Tensor, torch.Tensor, torch.Tensor]


def make_scene(n: int, seed: int = 0) -> Scene:
    """(means, quats, log_scales) float32 in a 40 x 40 x 3 m box around the origin."""
    g = torch.Generator().manual_seed(seed)
    means = (torch.rand(n, 3, generator=g) - torch.tensor([0.5, 0.5, 0.0])) * torch.tensor([40.0, 40.0, 3.0])
    quats = torch.randn(n, 4, generator=g)
    log_scales = torch.log(torch.rand(n, 3, generator=g) * 0.3 + 0.017)
    return means, quats, log_scales


def make_rig(package: str = "parksim") -> list[tuple[Any, torch.Tensor, torch.Tensor]]:
    """(camera, R_cam_world, t_cam_world) of four 190 deg fisheyes at the origin, 1 m up (``package``'s camera
    class: the fused path dispatches on it)."""
    fisheye = importlib.import_module(f"{package}.camera").OpenCVFisheye
    cam = fisheye(640, 480, 160.0, 160.0, 319.5, 239.5, [0.05, -0.01, 0.002, -0.0005], max_fov_deg=190.0)
    # camera x right, y down, z forward; yaw 0 looks along world +x
    front = torch.tensor([[0.0, -1.0, 0.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0]])
    rig = []
    for yaw in (0.0, 0.5 * torch.pi, torch.pi, 1.5 * torch.pi):
        half = torch.tensor(0.5 * yaw)
        R_world_cam = rotation_from_quaternion(torch.stack([half.cos(), torch.tensor(0.0), torch.tensor(0.0),
                                                            half.sin()])) @ front.T
        R = R_world_cam.T.contiguous()
        rig.append((cam, R, -R @ torch.tensor([0.0, 0.0, 1.0])))
    return rig


def project_rig(scene: Scene, rig: list, backend: str, backward: bool, package: str = "parksim") -> None:
    """Project the scene into every camera of ``rig`` (as ``render()`` does) with ``package``'s
    ``project_gaussians``, optionally backpropagate."""
    project_gaussians = importlib.import_module(f"{package}.render.projection").project_gaussians
    means, quats, log_scales = (t.detach().requires_grad_(backward) for t in scene)
    loss = torch.zeros(())
    for cam, R, t in rig:
        p = project_gaussians(means @ R.T + t, (quats, log_scales, R), cam, backend=backend)
        if backward:
            loss = loss + p.means2d.sum() + p.conics.sum() + p.depths.sum()
    if backward:
        loss.backward()


def _row(scene: Scene, rig: list, n_cams: int, backward: bool, args: argparse.Namespace) -> str:
    """One table row: the fused path against the torch path, or against ``args.reference``'s fused path."""
    label = f"| {len(scene[0]):,} | {n_cams} | {'fwd+bwd' if backward else 'fwd'} |"
    if args.reference:
        ref_rig = make_rig(args.reference)
        new, old = time_medians([lambda: project_rig(scene, rig[:n_cams], "fused", backward),
                                 lambda: project_rig(scene, ref_rig[:n_cams], "fused", backward, args.reference)],
                                args.repeats)
        return (f"{label} {new.wall_ms:.1f} / {new.cpu_ms:.1f} | {old.wall_ms:.1f} / {old.cpu_ms:.1f} | "
                f"{old.wall_ms / new.wall_ms:.2f}x / {old.cpu_ms / new.cpu_ms:.2f}x |")
    ms = {b: time_medians([lambda b=b: project_rig(scene, rig[:n_cams], b, backward)],
                          args.repeats if b == "fused" else min(args.repeats, 3))[0].wall_ms
          for b in ("torch", "fused")}
    return f"{label} {ms['torch']:.1f} | {ms['fused']:.1f} | {ms['torch'] / ms['fused']:.1f}x |"


def main() -> None:
    """Run every case and print (and optionally write) the table."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=5, help="timed runs per case (torch path: 3 at most)")
    ap.add_argument("--threads", type=int, help="torch and numba threads (default: their defaults)")
    ap.add_argument("--out", help="write the results as markdown here")
    ap.add_argument("--reference", help="module name of a package copy whose fused path is timed alongside "
                                        "(instead of the torch path)")
    args = ap.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)
        numba.set_num_threads(args.threads)
    rig = make_rig()
    rows = []
    for n in (100_000, 200_000):
        scene = make_scene(n)
        for n_cams in (1, 4):
            for backward in (False, True):
                rows.append(_row(scene, rig, n_cams, backward, args))
                print(rows[-1], flush=True)
    lines = [
        "# Projection benchmark: fused numba kernel vs " + (f"{args.reference}'s fused path" if args.reference
                                                             else "torch path"),
        "",
        f"- command: `{' '.join([os.path.relpath(sys.executable), *sys.argv])}`",
        f"- date: {datetime.datetime.now().isoformat(timespec='seconds')}",
        f"- machine: {cpu_model()}, {platform.machine()}, {os.cpu_count()} cores, numba threads "
        f"{numba.get_num_threads()}, torch threads {torch.get_num_threads()}, load average "
        f"{', '.join(f'{v:.1f}' for v in os.getloadavg())} (shared: compare within a row only)",
        f"- python {platform.python_version()}, torch {torch.__version__}, numba {numba.__version__}",
        "- scene: random Gaussians in a 40 x 40 x 3 m box, 4 x 640x480 OpenCVFisheye 190 deg at the centre, "
        "float32; times include world->camera transform and culling; medians in ms",
        "",
        *((f"| Gaussians | cameras | pass | fused wall / CPU (ms) | {args.reference} wall / CPU (ms) | "
           "speed-up wall / CPU |",) if args.reference else
          ("| Gaussians | cameras | pass | torch (ms) | fused (ms) | speed-up |",)),
        "| ---: | ---: | --- | ---: | ---: | ---: |",
        *rows,
        "",
    ]
    if args.out:
        with open(args.out, "w") as f:
            f.write("\n".join(lines))


if __name__ == "__main__":
    main()
