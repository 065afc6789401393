"""``parksim bench ut-accuracy``: how accurately UT, EWA and richer sigma-point sets project a 3D Gaussian through a
200 deg fisheye, against Monte-Carlo, and what the richer set costs in projection time.

Accuracy: off-axis angles 0-95 deg and sigma / distance in {0.01, 0.05, 0.3}; an anisotropic Gaussian (standard
deviations 1, 0.6, 0.3 x sigma) at 5 m, a few random orientations (mean reported); the 2D mean error (px) and the
relative covariance error ||C - C_mc||_F / ||C_mc||_F (no 3DGS blur) against ``--samples`` samples pushed through the
exact ``camera.project`` in float64. Methods: EWA (linearised), the 7-point UT with 3DGUT's alpha = 1 and gsplat's
alpha = 0.1, the fifth-degree 19-point set, and ParkSim's default (7 points, blended into the 19-point set for large
Gaussians far off-axis). Cost: cull + project (forward, no grad) of a random garage-like scene into 4 cameras
looking along +-x, +-y, 1 m up, the three variants called alternately (``time_medians``).
"""

from __future__ import annotations

import math
import statistics
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from ..cases import count_text
from ..common import progress, time_medians
from ..record import Figure
from ..suite import Context, Outcome, Suite

__all__ = ["UTAccuracySuite", "UTAccuracyOptions", "ANGLES", "RATIOS", "monte_carlo"]

ANGLES = (0, 30, 60, 80, 85, 90, 95)
"""Off-axis angles of the Gaussian's centre (deg)."""
RATIOS = (0.01, 0.05, 0.3)
"""Sigma / distance."""
DISTANCE = 5.0
AXES = (1.0, 0.6, 0.3)
"""Relative standard deviations of the test Gaussian."""
TARGET_ANGLE, TARGET_RATIO = 80, 0.3
"""The target: at theta >= 80 deg and sigma = 0.3 d, ParkSim's covariance error at most half of 3DGUT's."""


@dataclass(frozen=True)
class UTAccuracyOptions:
    """Options of ``parksim bench ut-accuracy``."""

    samples: int = field(default=1_000_000, metadata={"help": "Monte-Carlo samples per reference", "low": 100,
                                                      "quick": 2_000})
    orientations: int = field(default=3, metadata={"help": "random orientations of the test Gaussian (mean)",
                                                   "low": 1, "quick": 1})
    gaussians: int = field(default=200_000, metadata={"help": "Gaussians of the timed scene", "low": 1,
                                                      "quick": 2_000})
    repeats: int = field(default=5, metadata={"help": "timed rounds of the projection (median)", "low": 1,
                                              "quick": 1})


def lens() -> Any:
    """A 200 deg lens (theta_max = 100 deg), 1280x1280 so the whole image circle is inside."""
    from ...camera import OpenCVFisheye

    return OpenCVFisheye(1280, 1280, 320.0, 320.0, 639.5, 639.5, [0.05, -0.01, 0.002, -0.0005], max_fov_deg=200.0)


def monte_carlo(mu: Any, L: Any, cam: Any, n: int, seed: int) -> tuple[Any, Any]:
    """Mean and covariance of ``camera.project(mu + L z)``, z ~ N(0, I), in chunks (float64).

    Args:
        mu: ``(3,)`` camera-frame centre.
        L: ``(3, 3)`` covariance square root.
        cam: the camera model.
        n: samples.
        seed: their seed.

    Returns:
        The mean ``(2,)`` and covariance ``(2, 2)`` in pixels.
    """
    import torch

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


def methods() -> dict[str, Callable[..., tuple[Any, Any]]]:
    """name -> f(mu[1,3], quats[1,4], log_scales[1,3], cam) -> (mean[1,2], cov (a,b,c)[1,3]), without the blur."""
    import torch

    from ...render.projection import (
        BLUR_PX2,
        SigmaPoints,
        UTParams,
        _sigma_point_moments,
        covariance_sqrt,
        project_gaussians,
    )

    def sp(points: Any) -> Callable[..., tuple[Any, Any]]:
        return lambda mu, q, ls, cam: _sigma_point_moments(mu, covariance_sqrt(q, ls), cam, points)

    def full(method: str, params: Any = None) -> Callable[..., tuple[Any, Any]]:
        def f(mu: Any, q: Any, ls: Any, cam: Any) -> tuple[Any, Any]:
            p = project_gaussians(mu, (q, ls, None), cam, method=method, ut_params=params, max_radius=1e9)
            return p.means2d, p.cov2d - torch.tensor([BLUR_PX2, 0.0, BLUR_PX2], dtype=mu.dtype)
        return f

    return {"EWA": full("ewa"),
            "UT a=1 (3DGUT)": sp(SigmaPoints.unscented(1.0, 2.0, 0.0)),
            "UT a=0.1 (gsplat)": sp(SigmaPoints.unscented(0.1, 2.0, 0.0)),
            "19-pt deg-5": sp(SigmaPoints.fifth_degree()),
            "ParkSim default": full("ut", UTParams())}


def accuracy(samples: int, orientations: int, seed: int, tick: Callable[[], Any]) -> list[dict[str, Any]]:
    """Per (sigma / distance, angle): each method's mean error (px) and relative covariance error, mean over the
    orientations; ``tick`` after each row."""
    import torch

    from ...render.projection import covariance_sqrt

    cam = lens()
    quats = torch.randn(orientations, 4, generator=torch.Generator().manual_seed(seed), dtype=torch.float64)
    fns = methods()
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
                m_ref, c_ref = monte_carlo(mu[0], L[0], cam, samples, seed=seed + o)
                c_ref = torch.stack([c_ref[0, 0], c_ref[0, 1], c_ref[1, 1]])
                for name, f in fns.items():
                    m, c = f(mu, quats[o:o + 1], ls, cam)
                    errs.setdefault(name, []).append(((m[0] - m_ref).norm().item(),
                                                      (_fro(c[0] - c_ref) / _fro(c_ref)).item()))
            rows.append({"angle_deg": angle, "sigma_over_d": ratio,
                         "methods": {k: {"mean_px": statistics.mean(e[0] for e in v),
                                         "cov_rel": statistics.mean(e[1] for e in v)} for k, v in errs.items()}})
            tick()
    return rows


def _fro(c: Any) -> Any:
    """Frobenius norm of the symmetric 2x2 ``(a, b, c)``."""
    return (c[0] ** 2 + 2 * c[1] ** 2 + c[2] ** 2).sqrt()


def timing(n: int, repeats: int, seed: int) -> dict[str, Any]:
    """Cull + project ``n`` random Gaussians into 4 cameras (1 m up, along +-x, +-y): per variant the median, the
    visible Gaussians per camera and the share of them on the rich (19-point) set."""
    import torch

    from ...gaussians import GaussianScene
    from ...geometry import rotation_from_quaternion
    from ...render.projection import UTParams, project_gaussians

    cam = lens().scaled(0.5)
    scene = GaussianScene.random(n, ((-20, -20, 0), (20, 20, 3)), seed=seed + 1, scale_range=(0.02, 0.5))
    base = torch.tensor([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
    views = []
    for k in range(4):
        half = k * math.pi / 4
        Rz = rotation_from_quaternion(torch.tensor([math.cos(half), 0, 0, math.sin(half)])).float()
        R_cw = (Rz @ base).T
        views.append((R_cw, -R_cw @ torch.tensor([0.0, 0.0, 1.0])))
    variants: dict[str, dict[str, Any]] = {"UT 7-pt": {"ut_params": UTParams(adaptive=False)},
                                           "ParkSim default (adaptive)": {}, "EWA": {"method": "ewa"}}

    def closure(kw: dict[str, Any]) -> Callable[[], None]:
        def once() -> None:
            with torch.no_grad():
                for R, t in views:
                    project_gaussians(scene.means @ R.T + t, (scene.quats, scene.log_scales, R), cam, **kw)
        return once

    timings = dict(zip(variants, time_medians([closure(kw) for kw in variants.values()], repeats)))
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
    return {"timings": timings, "rich_fraction": rich / max(visible, 1), "visible_per_camera": visible / 4,
            "size": f"{cam.width}x{cam.height}"}


class UTAccuracySuite(Suite):
    """Projection accuracy of UT, EWA and richer sigma points against Monte-Carlo; the richer set's cost."""

    name = "ut-accuracy"
    help = "UT vs EWA vs 19-point sigma points against Monte-Carlo through a 200 deg fisheye; projection cost"
    description = ("2D mean and covariance errors of a Gaussian projected through a 200 deg fisheye, 0-95 deg "
                   "off-axis, sigma/d 0.01-0.3, against a float64 Monte-Carlo reference: EWA, the 7-point UT "
                   "(3DGUT's alpha=1, gsplat's 0.1), the 19-point fifth-degree set and ParkSim's adaptive default; "
                   "and the cull + project time of a random 2e5-Gaussian scene in 4 cameras per variant. Targets: "
                   "covariance error at >= 80 deg, sigma = 0.3 d, at most half of 3DGUT's; the adaptive set at most "
                   "1.5x the 7-point UT's projection time.")
    Options = UTAccuracyOptions

    def run(self, options: UTAccuracyOptions, context: Context) -> Outcome:
        """Accuracy table, then timing."""
        with progress(len(RATIOS) * len(ANGLES) + 1, "bench ut-accuracy", context.quiet) as bar:
            rows = accuracy(options.samples, options.orientations, context.seed, lambda: bar.update(1))
            cost = timing(options.gaussians, options.repeats, context.seed)
            bar.update(1)
        figures = []
        for row in rows:
            if row["sigma_over_d"] == TARGET_RATIO and row["angle_deg"] >= TARGET_ANGLE:
                ours, ref = row["methods"]["ParkSim default"], row["methods"]["UT a=1 (3DGUT)"]
                figures.append(Figure(
                    f"UT covariance error, {row['angle_deg']} deg off-axis, sigma = 0.3 d: ParkSim default",
                    100 * ours["cov_rel"], "%", reference=100 * ref["cov_rel"], goal="<= half of 3DGUT's",
                    reference_label="3DGUT's 7-point UT (alpha = 1), same run"))
        scene = f"{count_text(options.gaussians)} Gaussians x 4 fisheyes {cost['size']}"
        seven = cost["timings"]["UT 7-pt"]
        for name, goal in (("ParkSim default (adaptive)", "<= 1.5x the 7-point UT"), ("EWA", None)):
            t = cost["timings"][name]
            figures.append(Figure(f"projection (cull + project, fwd), {scene}: {name}", t.wall_ms, "ms",
                                  cpu=t.cpu_ms, reference=seven.wall_ms, reference_cpu=seven.cpu_ms, goal=goal,
                                  reference_label="7-point UT, same run"))
        figures.append(Figure(f"visible Gaussians on the 19-point set, {scene}", 100 * cost["rich_fraction"], "%"))
        data = {"lens": "OpenCV fisheye 1280x1280, f = 320 px, 200 deg", "axes": AXES, "distance_m": DISTANCE,
                "accuracy": rows, "timing": cost}
        return Outcome(figures, data)
