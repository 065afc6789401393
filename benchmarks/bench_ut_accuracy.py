"""UT vs EWA vs Monte-Carlo: accuracy of projected 2D Gaussians through a 200 deg fisheye, and projection cost.

Accuracy: for off-axis angles 0..95 deg and sigma/distance in {0.01, 0.05, 0.3}, the 2D mean error
(px) and the relative covariance error ||C - C_mc||_F / ||C_mc||_F against 1e6 samples pushed
through the exact ``camera.project`` (float64, averaged over a few orientations of an anisotropic
Gaussian). Cost: wall time of ``project_gaussians`` for a random garage-like scene and 4 cameras.

    .venv/bin/python benchmarks/bench_ut_accuracy.py [--samples 1000000] [--gaussians 200000]
"""

from __future__ import annotations

import argparse
import math
import platform
import statistics
import time
from datetime import date

import torch

from parksim.camera import OpenCVFisheye
from parksim.gaussians import GaussianScene
from parksim.geometry import rotation_from_quaternion
from parksim.render.projection import (
    BLUR_PX2,
    SigmaPoints,
    UTParams,
    _sigma_point_moments,
    covariance_sqrt,
    project_gaussians,
)

ANGLES = (0, 30, 60, 80, 85, 90, 95)
RATIOS = (0.01, 0.05, 0.3)
DISTANCE = 5.0
AXES = (1.0, 0.6, 0.3)   # relative standard deviations of the test Gaussian


def lens() -> OpenCVFisheye:
    """A 200 deg lens (theta_max = 100 deg), 1280x1280 so the whole image circle is inside."""
    return OpenCVFisheye(1280, 1280, 320.0, 320.0, 639.5, 639.5, [0.05, -0.01, 0.002, -0.0005], max_fov_deg=200.0)


def monte_carlo(mu: torch.Tensor, L: torch.Tensor, cam: OpenCVFisheye, n: int,
                seed: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Mean and covariance of ``camera.project(mu + L z)``, z ~ N(0, I), in chunks (float64)."""
    g = torch.Generator().manual_seed(seed)
    s1 = torch.zeros(2, dtype=torch.float64)
    s2 = torch.zeros(2, 2, dtype=torch.float64)
    ref = cam.project(mu[None])[0][0]
    for start in range(0, n, 250_000):
        z = torch.randn(min(250_000, n - start), 3, generator=g, dtype=torch.float64)
        uv = cam.project(mu + z @ L.T)[0] - ref
        s1 += uv.sum(0)
        s2 += uv.T @ uv
    m = s1 / n
    return ref + m, (s2 - n * torch.outer(m, m)) / (n - 1)


def methods() -> dict[str, callable]:
    """name -> f(mu[1,3], quats[1,4], log_scales[1,3], cam) -> (mean[1,2], cov (a,b,c)[1,3]), without the blur."""
    def sp(points):
        return lambda mu, q, ls, cam: _sigma_point_moments(mu, covariance_sqrt(q, ls), cam, points)

    def full(method, params=None):
        def f(mu, q, ls, cam):
            p = project_gaussians(mu, (q, ls, None), cam, method=method, ut_params=params, max_radius=1e9)
            return p.means2d, p.cov2d - torch.tensor([BLUR_PX2, 0.0, BLUR_PX2], dtype=mu.dtype)
        return f

    return {"EWA": full("ewa"),
            "UT a=1 (3DGUT)": sp(SigmaPoints.unscented(1.0, 2.0, 0.0)),
            "UT a=0.1 (gsplat)": sp(SigmaPoints.unscented(0.1, 2.0, 0.0)),
            "19-pt deg-5": sp(SigmaPoints.fifth_degree()),
            "ParkSim default": full("ut", UTParams())}


def accuracy(samples: int, orientations: int) -> list[tuple]:
    cam = lens()
    g = torch.Generator().manual_seed(0)
    quats = torch.randn(orientations, 4, generator=g, dtype=torch.float64)
    rows = []
    for ratio in RATIOS:
        for angle in ANGLES:
            t = math.radians(angle)
            mu = DISTANCE * torch.tensor([[math.sin(t) * math.cos(0.35), math.sin(t) * math.sin(0.35), math.cos(t)]],
                                         dtype=torch.float64)
            errs: dict[str, list[tuple[float, float]]] = {}
            for o in range(orientations):
                ls = torch.log(torch.tensor([AXES], dtype=torch.float64) * ratio * DISTANCE)
                L = covariance_sqrt(quats[o:o + 1], ls)
                m_ref, c_ref = monte_carlo(mu[0], L[0], cam, samples, seed=o)
                c_ref = torch.stack([c_ref[0, 0], c_ref[0, 1], c_ref[1, 1]])
                fro = lambda c: torch.sqrt(c[0] ** 2 + 2 * c[1] ** 2 + c[2] ** 2)  # noqa: E731
                for name, f in methods().items():
                    m, c = f(mu, quats[o:o + 1], ls, cam)
                    errs.setdefault(name, []).append(((m[0] - m_ref).norm().item(),
                                                      (fro(c[0] - c_ref) / fro(c_ref)).item()))
            rows.append((angle, ratio, {k: (statistics.mean(e[0] for e in v), statistics.mean(e[1] for e in v))
                                        for k, v in errs.items()}))
    return rows


def garage_scene(n: int) -> GaussianScene:
    """Random Gaussians around the car: 40 m x 40 m x 3 m, 2 cm to 50 cm."""
    return GaussianScene.random(n, ((-20, -20, 0), (20, 20, 3)), seed=1, scale_range=(0.02, 0.5))


def timing(n: int, repeats: int) -> dict[str, float]:
    """Best-of-``repeats`` seconds to cull + project ``n`` Gaussians into 4 cameras (looking along +-x, +-y, 1 m up)."""
    cam = lens().scaled(0.5)
    scene = garage_scene(n)
    base = torch.tensor([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
    views = []
    for k in range(4):
        half = k * math.pi / 4
        Rz = rotation_from_quaternion(torch.tensor([math.cos(half), 0, 0, math.sin(half)])).float()
        R_cw = (Rz @ base).T
        views.append((R_cw, -R_cw @ torch.tensor([0.0, 0.0, 1.0])))
    variants = {"UT 7-pt": dict(ut_params=UTParams(adaptive=False)), "ParkSim default (adaptive)": {},
                "EWA": dict(method="ewa")}
    times: dict[str, list[float]] = {name: [] for name in variants}
    for _ in range(repeats):      # interleaved, best of: the machine is shared
        for name, kw in variants.items():
            t0 = time.perf_counter()
            with torch.no_grad():
                for R, t in views:
                    project_gaussians(scene.means @ R.T + t, (scene.quats, scene.log_scales, R), cam, **kw)
            times[name].append(time.perf_counter() - t0)
    out = {name: min(v) for name, v in times.items()}
    visible = rich = 0
    p = UTParams()
    for R, t in views:
        mc = scene.means @ R.T + t
        proj = project_gaussians(mc, (scene.quats, scene.log_scales, R), cam)
        mu = mc[proj.index]
        visible += len(mu)
        wide = cam.theta_of(mu) > math.radians(p.adaptive_min_theta_deg)
        large = torch.exp(scene.log_scales[proj.index].amax(-1)) > p.adaptive_min_rel_size * mu.norm(dim=-1)
        rich += int((wide & large).sum())
    out["rich fraction"] = rich / max(visible, 1)
    out["visible per camera"] = visible / 4
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--samples", type=int, default=1_000_000)
    ap.add_argument("--orientations", type=int, default=3)
    ap.add_argument("--gaussians", type=int, default=200_000)
    ap.add_argument("--repeats", type=int, default=5)
    args = ap.parse_args()
    rows = accuracy(args.samples, args.orientations)
    names = list(rows[0][2])
    print(f"Machine: {platform.processor() or platform.machine()}, {torch.get_num_threads()} threads, "
          f"torch {torch.__version__}; {date.today()}")
    print(f"Lens: OpenCV fisheye 1280x1280, f=320 px, 200 deg; Gaussian axes {AXES} x sigma, distance {DISTANCE} m; "
          f"Monte-Carlo {args.samples:g} samples, mean over {args.orientations} orientations.\n")
    print("| theta (deg) | sigma/d | " + " | ".join(f"{n}: mean px / cov rel" for n in names) + " |")
    print("|---|---|" + "---|" * len(names))
    for angle, ratio, e in rows:
        print(f"| {angle} | {ratio} | " + " | ".join(f"{e[n][0]:.3f} / {100 * e[n][1]:.2f}%" for n in names) + " |")
    t = timing(args.gaussians, args.repeats)
    print(f"\nProjection (cull + project, forward, no grad), {args.gaussians} Gaussians x 4 cameras 640x640, "
          f"{t['visible per camera']:.0f} visible per camera, "
          f"{100 * t['rich fraction']:.2f}% of them on the rich set:\n")
    print(f"| method | seconds (best of {args.repeats}) | ratio to UT 7-pt |")
    print("|---|---|---|")
    for name in ("UT 7-pt", "ParkSim default (adaptive)", "EWA"):
        print(f"| {name} | {t[name]:.3f} | {t[name] / t['UT 7-pt']:.2f} |")


if __name__ == "__main__":
    main()
