"""3D Gaussians in a camera frame -> 2D image Gaussians, through the exact (fisheye) camera model.

The default is the unscented transform of 3DGUT: sigma points of each Gaussian go through
``camera.project`` itself (no linearisation), and the 2D mean and covariance are weighted sums
of the projected points. Everything is plain torch, so it is differentiable by autograd
(gsplat's and 3DGUT's UT kernels are not). EWA (first-order Jacobian of ``camera.project``)
is kept for comparison.

Choices at the edges, all deterministic and NaN-free:
- Culling happens before projecting, per camera: distance outside ``[near, far]``, or angle
  off the axis beyond ``theta_max`` plus the Gaussian's angular radius (``asin(3 sigma / d)``).
  Not ``z > 0``: a 190 deg lens sees points behind its image plane.
- Sigma points past the lens' valid angle are not dropped: ``camera.project`` puts them on the
  rim of the image circle in their own direction (never mirrored), which truncates the
  footprint at the lens edge. A Gaussian whose centre is past the edge but whose 3-sigma cone
  reaches inside is thus kept, squeezed against the rim.
- 2D covariances get the 3DGS 0.3 px^2 blur, then their eigenvalues are clamped to
  ``[0.3, (max_radius / 3)^2]``: UT with negative centre weights can be indefinite, and
  Gaussians around or right next to the camera would cover the whole image.
- Adaptive sigma points: the few Gaussians that are large for their distance and near the
  lens edge (where the 7-point UT is worst, see ``docs/benchmarks.md#ut-accuracy``) are blended
  continuously into a fifth-degree cubature set (2n^2+1 = 19 points).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache

import torch
from torch import Tensor

from ..camera import CameraModel
from ..geometry import rotation_from_quaternion
from .project_fast import FusedUTConfig, fused_supported, project_ut_fused

__all__ = ["UTParams", "Projected2D", "SigmaPoints", "project_gaussians", "cull_mask", "covariance_sqrt",
           "fused_config", "BLUR_PX2", "BACKENDS", "NEAR_M", "FAR_M"]

BLUR_PX2 = 0.3
"""Isotropic 2D blur added to every footprint (as 3DGS): a Gaussian never gets thinner than a pixel."""

NEAR_M, FAR_M = 0.05, 1000.0
"""Default culling distances from the camera centre, in metres."""

_EXTENT_SIGMAS = 3.0
_BLEND_THETA_DEG = 10.0

BACKENDS = ("auto", "torch", "fused")
"""``project_gaussians`` backends: the fused CPU kernel where it applies ("auto"), this module's torch, or fused."""


@dataclass(frozen=True)
class UTParams:
    """Unscented-transform parameters (``lambda = alpha^2 (n + kappa) - n``) and the adaptive rule.

    Defaults: 3DGUT's (alpha=1, beta=2, kappa=0), the most accurate 7-point set in
    ``docs/benchmarks.md#ut-accuracy``. Gaussians with ``sigma_max / distance > adaptive_min_rel_size``
    whose centre is more than ``adaptive_min_theta_deg`` off the axis are blended into the
    fifth-degree set (fully at twice the size and 10 deg further out); ``adaptive=False`` turns it off.

    Attributes:
        alpha: spread of the sigma points.
        beta: prior-knowledge term of the centre's covariance weight (2 is optimal for Gaussians).
        kappa: secondary scaling.
        adaptive: blend large Gaussians near the lens edge into the 19-point set.
        adaptive_min_theta_deg: angle off the axis (degrees) where the blend starts.
        adaptive_min_rel_size: ``sigma_max / distance`` where the blend starts.
    """

    alpha: float = 1.0
    beta: float = 2.0
    kappa: float = 0.0
    adaptive: bool = True
    adaptive_min_theta_deg: float = 60.0
    adaptive_min_rel_size: float = 0.1


@dataclass(frozen=True)
class SigmaPoints:
    """Standard-normal sigma points ``z[P, 3]`` (row 0 the centre) with mean and covariance weights.

    Attributes:
        z: ``[P, 3]`` float64 points of N(0, I_3).
        wm: ``[P]`` float64 weights of the mean.
        wc: ``[P]`` float64 weights of the covariance.
    """

    z: Tensor
    wm: Tensor
    wc: Tensor

    @staticmethod
    @lru_cache(maxsize=16)
    def unscented(alpha: float, beta: float, kappa: float) -> SigmaPoints:
        """The 2n+1 scaled unscented set (Julier, Wan & van der Merwe), n = 3.

        Args:
            alpha: spread of the points around the centre.
            beta: added to the centre's covariance weight.
            kappa: secondary scaling.

        Returns:
            The 7 points (cached per parameter triple).

        Raises:
            ValueError: ``alpha^2 (3 + kappa) <= 0``.
        """
        n = 3
        lam = alpha * alpha * (n + kappa) - n
        if not n + lam > 0:
            raise ValueError(f"UT needs alpha^2 (n + kappa) > 0, got alpha={alpha}, kappa={kappa}")
        eye = torch.eye(n, dtype=torch.float64) * math.sqrt(n + lam)
        z = torch.cat([torch.zeros(1, n, dtype=torch.float64), eye, -eye])
        wi = torch.full((2 * n,), 1.0 / (2 * (n + lam)), dtype=torch.float64)
        w0 = lam / (n + lam)
        wm = torch.cat([torch.tensor([w0], dtype=torch.float64), wi])
        wc = torch.cat([torch.tensor([w0 + 1 - alpha * alpha + beta], dtype=torch.float64), wi])
        return SigmaPoints(z, wm, wc)

    @staticmethod
    @lru_cache(maxsize=1)
    def fifth_degree() -> SigmaPoints:
        """Stroud's degree-5 cubature for N(0, I_n), n = 3: 2n^2+1 = 19 points, all weights positive.

        Exact for polynomials up to degree 5, so the covariance of a locally quadratic projection
        is exact (the 7-point UT matches 3rd moments only); positive weights keep it PSD.

        Returns:
            The 19 points, mean and covariance weights equal (cached).
        """
        n = 3
        pts = [torch.zeros(n, dtype=torch.float64)]
        w = [2.0 / (n + 2)]
        for i in range(n):
            for s in (1.0, -1.0):
                p = torch.zeros(n, dtype=torch.float64)
                p[i] = s * math.sqrt(n + 2)
                pts.append(p)
                w.append((4.0 - n) / (2 * (n + 2) ** 2))
        for i in range(n):
            for j in range(i + 1, n):
                for si in (1.0, -1.0):
                    for sj in (1.0, -1.0):
                        p = torch.zeros(n, dtype=torch.float64)
                        p[i], p[j] = si * math.sqrt((n + 2) / 2), sj * math.sqrt((n + 2) / 2)
                        pts.append(p)
                        w.append(1.0 / (n + 2) ** 2)
        wt = torch.tensor(w, dtype=torch.float64)
        return SigmaPoints(torch.stack(pts), wt, wt)


@dataclass
class Projected2D:
    """Image-space Gaussians for the rows ``index`` of the input that survived culling.

    ``conics`` and ``cov2d`` are ``(a, b, c)`` of ``[[a, b], [b, c]]`` (inverse and forward 2D
    covariance), ``depths`` the distance ``|p|`` from the camera centre, ``radii`` the 3-sigma
    pixel radius, ``valid`` whether the footprint is finite and overlaps the image.

    Attributes:
        index: ``[M]`` int64 rows of the input that survived culling.
        means2d: ``[M, 2]`` pixel centres (u, v).
        conics: ``[M, 3]`` inverse 2D covariances ``(a, b, c)`` in 1/px^2.
        cov2d: ``[M, 3]`` 2D covariances ``(a, b, c)`` in px^2, blurred and clamped.
        depths: ``[M]`` distances from the camera centre (m).
        radii: ``[M]`` 3-sigma radii in whole pixels.
        valid: ``[M]`` bool: finite and overlapping the image.
    """

    index: Tensor
    means2d: Tensor
    conics: Tensor
    cov2d: Tensor
    depths: Tensor
    radii: Tensor
    valid: Tensor


def covariance_sqrt(quats: Tensor, log_scales: Tensor, R_cam_world: Tensor | None = None) -> Tensor:
    """``L[N,3,3]`` with ``Sigma_cam = L L^T = R_cw R(q) S^2 R(q)^T R_cw^T``; zero quaternions act as identity.

    Args:
        quats: ``[N, 4]`` rotations (w, x, y, z), any norm.
        log_scales: ``[N, 3]`` log standard deviations (m).
        R_cam_world: ``[3, 3]`` world -> camera rotation; None keeps the world frame.

    Returns:
        ``[N, 3, 3]`` square roots of the covariances (not triangular).
    """
    L = rotation_from_quaternion(quats) * torch.exp(log_scales)[..., None, :]
    return L if R_cam_world is None else R_cam_world.to(L) @ L


def _cholesky_sqrt(covs: Tensor) -> Tensor:
    """Lower Cholesky factor of PSD covariances, with a relative jitter so singular ones factor too."""
    eye = torch.eye(3, dtype=covs.dtype, device=covs.device)
    tr = covs.diagonal(dim1=-2, dim2=-1).sum(-1)
    jitter = (tr * 1e-6 + torch.finfo(covs.dtype).tiny)[..., None, None] * eye
    L, _ = torch.linalg.cholesky_ex(covs + jitter)
    return L


@torch.no_grad()
def cull_mask(means_cam: Tensor, sigma_max: Tensor, camera: CameraModel, near: float, far: float) -> Tensor:
    """Gaussians possibly visible: distance in ``[near, far]`` and 3-sigma cone reaching ``theta_max``.

    Args:
        means_cam: ``[N, 3]`` camera-frame centres (m).
        sigma_max: ``[N]`` largest standard deviation of each Gaussian (m).
        camera: the lens (its ``theta_max``).
        near: closest distance kept (m).
        far: farthest distance kept (m).

    Returns:
        ``[N]`` bool mask, no gradient.
    """
    dist = means_cam.norm(dim=-1)
    in_range = (dist >= near) & (dist <= far)
    ratio = torch.clamp(_EXTENT_SIGMAS * sigma_max / torch.clamp_min(dist, near), max=1.0)
    return in_range & (camera.theta_of(means_cam) - torch.asin(ratio) <= camera.theta_max)


def _sigma_point_moments(mu: Tensor, L: Tensor, camera: CameraModel, sp: SigmaPoints) -> tuple[Tensor, Tensor]:
    """2D mean ``[M,2]`` and covariance ``(a, b, c)`` ``[M,3]`` from sigma points through ``camera.project``."""
    z, wm, wc = (t.to(mu) for t in (sp.z, sp.wm, sp.wc))
    pts = mu[:, None, :] + torch.einsum("mij,pj->mpi", L, z)
    uv, _ = camera.project(pts)
    rel = uv - uv[:, :1]          # relative to the centre point: no cancellation with large weights
    m = torch.einsum("p,mpk->mk", wm, rel)
    d = rel - m[:, None]
    cov = torch.stack([torch.einsum("p,mp->m", wc, d[..., 0] * d[..., 0]),
                       torch.einsum("p,mp->m", wc, d[..., 0] * d[..., 1]),
                       torch.einsum("p,mp->m", wc, d[..., 1] * d[..., 1])], dim=-1)
    return uv[:, 0] + m, cov


def _ut(mu: Tensor, L: Tensor, sigma_max: Tensor, camera: CameraModel, p: UTParams) -> tuple[Tensor, Tensor]:
    """7-point UT for all; blended into the fifth-degree set for large Gaussians near the lens edge.

    The blend weight ramps from 0 to 1 over ``_BLEND_THETA_DEG`` past the angle threshold and from
    1x to 2x the size threshold, so the footprint stays continuous (and gradcheck-able) in the
    Gaussian's parameters.

    Returns:
        ``(mean [M, 2], cov [M, 3])``: pixel means and 2D covariances ``(a, b, c)``, before blur and clamping.
    """
    mean, cov = _sigma_point_moments(mu, L, camera, SigmaPoints.unscented(p.alpha, p.beta, p.kappa))
    if not p.adaptive or len(mu) == 0:
        return mean, cov
    theta_min = math.radians(p.adaptive_min_theta_deg)
    with torch.no_grad():
        rich = ((camera.theta_of(mu) > theta_min)
                & (sigma_max > p.adaptive_min_rel_size * mu.norm(dim=-1))).nonzero().squeeze(1)
    if len(rich) == 0:
        return mean, cov
    mu_r = mu[rich]
    w = (torch.clamp((camera.theta_of(mu_r) - theta_min) / math.radians(_BLEND_THETA_DEG), max=1.0)
         * torch.clamp(sigma_max[rich] / (p.adaptive_min_rel_size * mu_r.norm(dim=-1)) - 1.0, max=1.0))[:, None]
    mean_r, cov_r = _sigma_point_moments(mu_r, L[rich], camera, SigmaPoints.fifth_degree())
    return (mean.index_put((rich,), mean[rich] + w * (mean_r - mean[rich])),
            cov.index_put((rich,), cov[rich] + w * (cov_r - cov[rich])))


def _ewa(mu: Tensor, L: Tensor, camera: CameraModel) -> tuple[Tensor, Tensor]:
    """First-order (EWA) footprint: ``J L L^T J^T`` with the Jacobian of ``camera.project`` by forward AD."""
    f = lambda p: camera.project(p)[0]  # noqa: E731
    cols = []
    for k in range(3):
        e = torch.zeros_like(mu)
        e[:, k] = 1.0
        uv, col = torch.func.jvp(f, (mu,), (e,))[:2]   # (outputs, tangents); torch types it as maybe 3 long
        cols.append(col)
    JL = torch.stack(cols, dim=-1) @ L
    S = JL @ JL.transpose(-1, -2)
    return uv, torch.stack([S[:, 0, 0], S[:, 0, 1], S[:, 1, 1]], dim=-1)


def _clamp_eigenvalues(cov: Tensor, lo: float, hi: float) -> Tensor:
    """Clamp both eigenvalues of symmetric 2x2 ``(a, b, c)`` to ``[lo, hi]``; untouched (same graph) where inside.

    Uses ``f(A) = f(l2) I + (f(l1) - f(l2)) / (l1 - l2) (A - l2 I)``, which needs no eigenvectors
    and stays finite (value and gradient) for isotropic matrices.

    Returns:
        ``[..., 3]`` the clamped ``(a, b, c)``.
    """
    a, b, c = cov.unbind(-1)
    mid, half = 0.5 * (a + c), 0.5 * (a - c)
    disc = half * half + b * b
    with torch.no_grad():
        r0 = torch.sqrt(disc)
        need = (mid - r0 < lo) | (mid + r0 > hi)
    pos = need & (disc > torch.finfo(cov.dtype).tiny)
    r = torch.where(pos, torch.sqrt(torch.where(pos, disc, torch.ones_like(disc))), torch.zeros_like(disc))
    l1, l2 = mid + r, mid - r
    f1, f2 = torch.clamp(l1, lo, hi), torch.clamp(l2, lo, hi)
    s = torch.where(pos, (f1 - f2) / torch.where(pos, 2 * r, torch.ones_like(r)), torch.zeros_like(r))
    clamped = torch.stack([f2 + s * (a - l2), s * b, f2 + s * (c - l2)], dim=-1)
    return torch.where(need[..., None], clamped, cov)


def fused_config(params: UTParams, near: float, far: float, cap: float, cull: bool = True, ewa: bool = False
                 ) -> FusedUTConfig:
    """This module's UT rules and limits, as the fused kernels take them.

    Args:
        params: sigma-point set and adaptive rule.
        near: closest distance kept (m).
        far: farthest distance kept (m).
        cap: largest 3-sigma footprint radius in pixels.
        cull: False keeps every Gaussian.
        ewa: the first-order (EWA) footprint instead of the UT (device kernels only).

    Returns:
        The kernels' configuration.
    """
    ut, fifth = SigmaPoints.unscented(params.alpha, params.beta, params.kappa), SigmaPoints.fifth_degree()
    return FusedUTConfig((ut.z, ut.wm, ut.wc), (fifth.z, fifth.wm, fifth.wc), params.adaptive,
                         math.radians(params.adaptive_min_theta_deg), math.radians(_BLEND_THETA_DEG),
                         params.adaptive_min_rel_size, near, far, BLUR_PX2, _EXTENT_SIGMAS, cap, cull, ewa)


def project_gaussians(means_cam: Tensor, cov: Tensor | tuple[Tensor, Tensor, Tensor | None], camera: CameraModel,
                      method: str = "ut", ut_params: UTParams | None = None, near: float = NEAR_M,
                      far: float = FAR_M, max_radius: float | None = None, backend: str = "auto",
                      cull: bool = True) -> Projected2D:
    """Cull, then project Gaussians given in the camera frame (OpenCV axes) into ``camera``.

    ``cov`` is either camera-frame covariances ``[N,3,3]`` or ``(quats, log_scales, R_cam_world)``
    (world-frame rotation and log scales; ``R_cam_world`` may be None when they are camera-frame).
    ``max_radius`` caps the 3-sigma footprint radius in pixels (default: the image's larger side).
    ``backend`` "auto" runs UT with ``(quats, log_scales, R)`` on CPU float tensors through the fused
    kernel (``project_fast``, same results), everything else here; "torch" forces this module's path.
    ``cull`` False projects every Gaussian (only to measure what culling saves).

    Args:
        means_cam: ``[N, 3]`` centres in the camera frame (m).
        cov: ``[N, 3, 3]`` camera-frame covariances, or ``(quats [N, 4], log_scales [N, 3], R_cam_world [3, 3] |
            None)``.
        camera: the lens model.
        method: "ut" (unscented transform through ``camera.project``) or "ewa" (its Jacobian).
        ut_params: sigma-point set and adaptive rule (default ``UTParams()``).
        near: closest distance kept (m).
        far: farthest distance kept (m).
        max_radius: cap of the 3-sigma radius in pixels (default: the image's larger side).
        backend: one of ``BACKENDS``.
        cull: False projects every Gaussian.

    Returns:
        The M surviving Gaussians in 2D; rows with ``valid`` False are finite but should not be drawn.

    Raises:
        ValueError: an unknown ``method`` or ``backend``, or ``backend="fused"`` where the fused kernel does not
            apply.
    """
    if method not in ("ut", "ewa"):
        raise ValueError(f"project_gaussians: method must be 'ut' or 'ewa', got {method!r}")
    if backend not in BACKENDS:
        raise ValueError(f"project_gaussians: backend must be one of {BACKENDS}, got {backend!r}")
    params = ut_params or UTParams()
    cap = float(max_radius if max_radius is not None else max(camera.width, camera.height))
    fusable = method == "ut" and not isinstance(cov, Tensor) and fused_supported(camera, means_cam, *cov)
    if backend == "fused" and not fusable:
        raise ValueError("project_gaussians: backend='fused' needs method='ut', (quats, log_scales, R) on CPU "
                         "float32/float64 of one dtype and an OpenCVFisheye, RadialPolyFisheye or Pinhole camera")
    if fusable and backend != "torch":
        return Projected2D(*project_ut_fused(means_cam, cov[0], cov[1], cov[2], camera,
                                             fused_config(params, near, far, cap, cull)))
    if isinstance(cov, Tensor):   # sqrt(trace): an upper bound of the largest standard deviation
        sigma_max = torch.sqrt(torch.clamp_min(cov.diagonal(dim1=-2, dim2=-1).sum(-1), 0.0))
    else:
        sigma_max = torch.exp(cov[1].amax(dim=-1))
    keep = cull_mask(means_cam, sigma_max.detach(), camera, near, far) if cull else torch.ones_like(sigma_max) > 0
    index = keep.nonzero().squeeze(1)
    mu = means_cam[index]
    L = _cholesky_sqrt(cov[index]) if isinstance(cov, Tensor) else covariance_sqrt(cov[0][index], cov[1][index], cov[2])
    L = L.to(mu.dtype)
    if method == "ut":
        mean2d, cov2d = _ut(mu, L, sigma_max[index].to(mu.dtype), camera, params)
    else:
        mean2d, cov2d = _ewa(mu, L, camera)

    blur = torch.tensor([BLUR_PX2, 0.0, BLUR_PX2], dtype=cov2d.dtype, device=cov2d.device)
    finite = torch.isfinite(mean2d).all(-1) & torch.isfinite(cov2d).all(-1)
    cov2d = torch.where(finite[:, None], cov2d, torch.zeros_like(cov2d))   # never hand NaN downstream
    mean2d = torch.where(finite[:, None], mean2d, torch.zeros_like(mean2d))
    cov2d = _clamp_eigenvalues(cov2d + blur, BLUR_PX2, (cap / _EXTENT_SIGMAS) ** 2)
    a, b, c = cov2d.unbind(-1)
    det = a * c - b * b
    conics = torch.stack([c, -b, a], dim=-1) / det[:, None]
    with torch.no_grad():
        lmax = 0.5 * (a + c) + torch.sqrt(torch.clamp_min((0.5 * (a - c)) ** 2 + b * b, 0.0))
        radii = torch.ceil(_EXTENT_SIGMAS * torch.sqrt(lmax))
        u, v = mean2d.detach().unbind(-1)
        overlaps = ((u + radii > -0.5) & (u - radii < camera.width - 0.5)
                    & (v + radii > -0.5) & (v - radii < camera.height - 0.5))
    return Projected2D(index, mean2d, conics, cov2d, mu.norm(dim=-1), radii, finite & overlaps)
