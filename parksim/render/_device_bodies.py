"""One work item of the device projection kernels, compiled for the GPU (``_cuda_kernels``) and for the CPU (here).

A work item of the forward is one (view, Gaussian) pair: world -> camera, cull, 7-point UT through the exact lens
with the adaptive fifth-degree blend (or, with ``opts[EWA]``, the first-order footprint of the lens's Jacobian),
blur, eigenvalue clamp, conic, distance and the SH colour along the view ray
(the steps of ``_views_kernels``, one Gaussian at a time instead of a vectorised chunk). A work item of the backward
is one Gaussian over every view it was drawn in, so that its gradients are summed in registers and written once (no
atomics, deterministic). Both call the per-Gaussian helpers of ``_project_kernels`` and ``_sh_kernels`` that the CPU
renderer uses, so the lens models exist once.

The ``*_cpu`` launchers run the same bodies over all items with numba's CPU target: the GPU kernels' reference in
the tests (CI has no GPU), as Warp's CPU target is for Warp kernels. Scratch arrays are passed in (``cuda.local``
arrays on the GPU), arithmetic is float64 whatever the arrays' dtype.
"""

from __future__ import annotations

import math

import numba
import numpy as np

from . import _project_kernels as pk
from ._sh_kernels import TINY_DISTANCE, _basis_vjp, _view, sh_basis

__all__ = ["view_forward", "gaussian_backward", "views_forward_cpu", "views_backward_cpu", "N_FIFTH", "N_BASIS",
           "N_POSE_GRAD"]

N_FIFTH = 19
"""Points of the fifth-degree cubature set (2 n^2 + 1 for n = 3): the size of its scratch array."""
N_BASIS = 16
"""SH basis functions up to degree 3."""
N_POSE_GRAD = 15
"""Per (view, Gaussian) pose gradient columns: rotation (9, row major), translation (3), camera centre (3)."""


@numba.njit(inline="always", cache=True)
def _to_camera(rots: np.ndarray, trans: np.ndarray, v: int, means: np.ndarray, g: int
               ) -> tuple[float, float, float, float, float, float]:
    """Gaussian ``g``'s centre in view ``v``'s camera frame, and in the world: ``(x, y, z, mx, my, mz)``."""
    rot = rots[v]
    mx, my, mz = float(means[g, 0]), float(means[g, 1]), float(means[g, 2])
    return (rot[0, 0] * mx + rot[0, 1] * my + rot[0, 2] * mz + trans[v, 0],
            rot[1, 0] * mx + rot[1, 1] * my + rot[1, 2] * mz + trans[v, 1],
            rot[2, 0] * mx + rot[2, 1] * my + rot[2, 2] * mz + trans[v, 2], mx, my, mz)


@numba.njit(inline="always", cache=True)
def _shape(quats: np.ndarray, log_scales: np.ndarray, g: int, q: np.ndarray, s: np.ndarray, R: np.ndarray) -> float:
    """Gaussian ``g``'s unit quaternion and input norm into ``q``, scales into ``s``, ``R(q)`` into ``R``; its
    largest scale."""
    q[0], q[1], q[2], q[3], q[4] = pk._unit_quaternion(quats[g])
    for j in range(3):
        s[j] = math.exp(float(log_scales[g, j]))
    pk._rotation(q[0], q[1], q[2], q[3], R)
    return max(s[0], s[1], s[2])


@numba.njit(inline="always", cache=True)
def _ray(means: np.ndarray, g: int, centres: np.ndarray, v: int) -> tuple[float, float, float, float]:
    """Unit direction from view ``v``'s centre to Gaussian ``g`` and the (clamped) distance: ``(x, y, z, n)``."""
    dx, dy, dz, n = _view(means, g, centres[v])   # the CPU colour kernels' offset and clamped length
    return dx / n, dy / n, dz / n, n


@numba.njit(inline="always", cache=True)
def _sh_rgb(sh: np.ndarray, g: int, n_basis: int, basis: np.ndarray) -> tuple[float, float, float]:
    """``basis . sh[g] + 0.5`` per channel, before the clamp at 0."""
    r = gr = b = 0.0
    for j in range(n_basis):
        r += basis[j] * sh[g, j, 0]
        gr += basis[j] * sh[g, j, 1]
        b += basis[j] * sh[g, j, 2]
    return r + 0.5, gr + 0.5, b + 0.5


@numba.njit(inline="always", cache=True)
def _jl(out: tuple[float, ...], row: int, L: np.ndarray, j: int) -> float:
    """``(J L)[row, j]`` for the Jacobian rows ``out[2:8]`` of ``_project_kernels._project``."""
    return (out[2 + 3 * row] * L[0, j] + out[3 + 3 * row] * L[1, j] + out[4 + 3 * row] * L[2, j])


@numba.njit(inline="always", cache=True)
def _ewa_moments(out: tuple[float, ...], L: np.ndarray) -> tuple[float, float, float, float, float]:
    """First-order footprint from the projected centre ``out`` (``_project``): ``(u, v)`` and ``J L L^T J^T`` as
    ``(a, b, c)``, as ``projection._ewa``."""
    a = b = c = 0.0
    for j in range(3):
        r0, r1 = _jl(out, 0, L, j), _jl(out, 1, L, j)
        a += r0 * r0
        b += r0 * r1
        c += r1 * r1
    return out[0], out[1], a, b, c


@numba.njit(cache=True, error_model="numpy")
def view_forward(v: int, g: int, means: np.ndarray, quats: np.ndarray, log_scales: np.ndarray, sh: np.ndarray,
                 sh_degree: int, rots: np.ndarray, trans: np.ndarray, centres: np.ndarray, models: np.ndarray,
                 lenses: np.ndarray, opts: np.ndarray, z7: np.ndarray, wm7: np.ndarray, wc7: np.ndarray,
                 z19: np.ndarray, wm19: np.ndarray, wc19: np.ndarray, q: np.ndarray, s: np.ndarray, R: np.ndarray,
                 L: np.ndarray, uv7: np.ndarray, uv19: np.ndarray, mom: np.ndarray, basis: np.ndarray,
                 out_means: np.ndarray, out_conics: np.ndarray, out_colors: np.ndarray, out_depths: np.ndarray,
                 out_drawn: np.ndarray) -> None:
    """Gaussian ``g`` in view ``v``: 2D mean, conic, colour, distance, and ``out_drawn[v, g]`` 1 if drawn (else the
    row is zeros)."""
    out_drawn[v, g] = 0
    for k in range(3):
        out_conics[v, g, k] = 0.0
        out_colors[v, g, k] = 0.0
    out_means[v, g, 0] = out_means[v, g, 1] = out_depths[v, g] = 0.0
    lens, opt = lenses[v], opts[v]
    x, y, z, _, _, _ = _to_camera(rots, trans, v, means, g)
    if not pk._visible(lens, opt, x, y, z, log_scales[g]):
        return
    sigma = _shape(quats, log_scales, g, q, s, R)
    pk._rotate_scaled(rots[v], R, s, L)
    if opt[pk.EWA] > 0:
        mean_u, mean_v, a, b, c = _ewa_moments(pk._project(models[v], lens, opt[pk.AXIS_EPS], opt[pk.TINY], x, y, z),
                                               L)
    else:
        pk._sigma_points(models[v], lens, opt, x, y, z, L, z7, uv7, False)
        m7 = pk._moments(uv7[:, 0], uv7[:, 1], 0, 1, wm7, wc7)
        pk._ut_blend(models[v], lens, opt, x, y, z, sigma, L, m7, z19, wm19, wc19, uv19, mom, False)
        mean_u, mean_v, a, b, c = mom[2, 0], mom[2, 1], mom[2, 2], mom[2, 3], mom[2, 4]
    u, w, a, b, c, depth, _, ok = pk._clamped(mean_u, mean_v, a, b, c, x, y, z, opt)
    if not ok:
        return
    det = a * c - b * b
    out_means[v, g, 0], out_means[v, g, 1] = u, w
    out_conics[v, g, 0], out_conics[v, g, 1], out_conics[v, g, 2] = c / det, -b / det, a / det
    out_depths[v, g] = depth
    dx, dy, dz, _ = _ray(means, g, centres, v)
    r, gr, bl = _sh_rgb(sh, g, sh_basis(sh_degree, dx, dy, dz, basis), basis)
    out_colors[v, g, 0], out_colors[v, g, 1], out_colors[v, g, 2] = max(r, 0.0), max(gr, 0.0), max(bl, 0.0)
    out_drawn[v, g] = 1


@numba.njit(inline="always", cache=True)
def _moments_backward_start(mean_u: float, mean_v: float, a: float, b: float, c: float, x: float, y: float,
                            z: float, gd: float, g_mu: np.ndarray, g_L: np.ndarray) -> bool:
    """The distance's gradient into ``g_mu``, zeros into ``g_L``; whether the moments are finite (else the
    footprint was zeroed and passes no more gradient)."""
    n = math.sqrt(x * x + y * y + z * z)
    g_mu[0], g_mu[1], g_mu[2] = gd * x / n, gd * y / n, gd * z / n
    for r in range(3):
        for j in range(3):
            g_L[r, j] = 0.0
    return (math.isfinite(mean_u) and math.isfinite(mean_v) and math.isfinite(a) and math.isfinite(b)
            and math.isfinite(c))


@numba.njit(inline="always", cache=True)
def _covariance_backward(a: float, b: float, c: float, opt: np.ndarray, gc0: float, gc1: float, gc2: float
                         ) -> tuple[float, float, float]:
    """Back from the conic's gradient ``(gc0, gc1, gc2)`` through the inverse, the eigenvalue clamp and the blur to
    the footprint's covariance ``(a, b, c)``."""
    blur, lo, hi, tiny = opt[pk.BLUR], opt[pk.LO], opt[pk.HI], opt[pk.TINY]
    _, _, _, _, _, _, ca, cb, cc = pk._eig_clamp(a + blur, b, c + blur, lo, hi, tiny)
    det = ca * cc - cb * cb
    gdet = -(gc0 * cc - gc1 * cb + gc2 * ca) / (det * det)
    return pk._eig_clamp_backward(a + blur, b, c + blur, lo, hi, tiny, gc2 / det + gdet * cc,
                                  -gc1 / det - 2 * gdet * cb, gc0 / det + gdet * ca)


HESSIAN_STEP = 6e-6
"""Central-difference step of the EWA backward: ``HESSIAN_STEP (r^2 |p|)^(1/3)`` for a centre at distance ``|p|``
and ``r`` off the optical axis (``r`` at least ``1e-6 |p|``). The Jacobian varies on the scale ``r`` (lenses with
even powers of theta are not twice differentiable on the axis), so truncation is ``(h / r)^2`` and rounding
``eps |p| / h``: this step balances them, ~1e-10 relative in the open field and ~1e-7 at ``r = 1e-6 |p|``, below
float32's spacing everywhere."""


@numba.njit(inline="always", cache=True)
def _ewa_backward(model: int, lens: np.ndarray, opt: np.ndarray, x: float, y: float, z: float, L: np.ndarray,
                  gmu: float, gmv: float, gc0: float, gc1: float, gc2: float, gd: float, g_mu: np.ndarray,
                  g_L: np.ndarray) -> float:
    """Back through one view's first-order footprint: the camera-frame centre's gradient into ``g_mu``, ``L``'s into
    ``g_L``; returns 0 (nothing depends on the largest scale).

    The centre reaches the covariance through the Jacobian ``J(p)``: its gradient there is ``H_u w_u + H_v w_v``
    (``w`` the rows of ``J``'s gradient), each Hessian-vector product a central difference of the analytic
    Jacobian along ``w`` in float64 (``HESSIAN_STEP``).
    """
    eps, tiny = opt[pk.AXIS_EPS], opt[pk.TINY]
    out = pk._project(model, lens, eps, tiny, x, y, z)
    mean_u, mean_v, a, b, c = _ewa_moments(out, L)
    if not _moments_backward_start(mean_u, mean_v, a, b, c, x, y, z, gd, g_mu, g_L):
        return 0.0
    ga, gb, gcc = _covariance_backward(a, b, c, opt, gc0, gc1, gc2)
    w0x = w0y = w0z = w1x = w1y = w1z = 0.0   # d loss / d J, rows u and v
    for j in range(3):
        r0, r1 = _jl(out, 0, L, j), _jl(out, 1, L, j)
        g0, g1 = 2.0 * ga * r0 + gb * r1, gb * r0 + 2.0 * gcc * r1     # d loss / d (J L)[:, j]
        for r in range(3):
            g_L[r, j] += out[2 + r] * g0 + out[5 + r] * g1
        w0x += g0 * L[0, j]
        w0y += g0 * L[1, j]
        w0z += g0 * L[2, j]
        w1x += g1 * L[0, j]
        w1y += g1 * L[1, j]
        w1z += g1 * L[2, j]
    for k in range(3):
        g_mu[k] += gmu * out[2 + k] + gmv * out[5 + k]
    n = math.sqrt(x * x + y * y + z * z)
    off = max(math.sqrt(x * x + y * y), 1e-6 * n)
    h = HESSIAN_STEP * (off * off * n) ** (1.0 / 3.0)
    for row in range(2):
        wx, wy, wz = (w0x, w0y, w0z) if row == 0 else (w1x, w1y, w1z)
        norm = math.sqrt(wx * wx + wy * wy + wz * wz)
        if not norm > 0.0:
            continue
        dx, dy, dz = h * wx / norm, h * wy / norm, h * wz / norm
        plus = pk._project(model, lens, eps, tiny, x + dx, y + dy, z + dz)
        minus = pk._project(model, lens, eps, tiny, x - dx, y - dy, z - dz)
        for k in range(3):
            g_mu[k] += norm * (plus[2 + 3 * row + k] - minus[2 + 3 * row + k]) / (2.0 * h)
    return 0.0


@numba.njit(inline="always", cache=True)
def _footprint_backward(model: int, lens: np.ndarray, opt: np.ndarray, x: float, y: float, z: float, sigma: float,
                        L: np.ndarray, z7: np.ndarray, wm7: np.ndarray, wc7: np.ndarray, z19: np.ndarray,
                        wm19: np.ndarray, wc19: np.ndarray, uv7: np.ndarray, uv19: np.ndarray, mom: np.ndarray,
                        gmu: float, gmv: float, gc0: float, gc1: float, gc2: float, gd: float,
                        g_mu: np.ndarray, g_L: np.ndarray) -> float:
    """Back through one view's footprint (as ``_project_kernels._backward_range`` for one row): the camera-frame
    centre's gradient into ``g_mu``, ``L``'s into ``g_L``; returns the gradient of the largest scale (blend)."""
    pk._sigma_points(model, lens, opt, x, y, z, L, z7, uv7, True)
    m7 = pk._moments(uv7[:, 0], uv7[:, 1], 0, 1, wm7, wc7)
    rich, w, dwx, dwy, dwz, dws = pk._ut_blend(model, lens, opt, x, y, z, sigma, L, m7, z19, wm19, wc19, uv19,
                                               mom, True)
    if not _moments_backward_start(mom[2, 0], mom[2, 1], mom[2, 2], mom[2, 3], mom[2, 4], x, y, z, gd, g_mu, g_L):
        return 0.0
    ga, gb, gcc = _covariance_backward(mom[2, 2], mom[2, 3], mom[2, 4], opt, gc0, gc1, gc2)
    pk._moments_backward(uv7, wm7, wc7, gmu, gmv, ga, gb, gcc, 1.0 - w, z7, g_mu, g_L)
    if not rich:
        return 0.0
    pk._moments_backward(uv19, wm19, wc19, gmu, gmv, ga, gb, gcc, w, z19, g_mu, g_L)
    gw = (gmu * (mom[1, 0] - mom[0, 0]) + gmv * (mom[1, 1] - mom[0, 1]) + ga * (mom[1, 2] - mom[0, 2])
          + gb * (mom[1, 3] - mom[0, 3]) + gcc * (mom[1, 4] - mom[0, 4]))
    g_mu[0] += gw * dwx
    g_mu[1] += gw * dwy
    g_mu[2] += gw * dwz
    return gw * dws


@numba.njit(inline="always", cache=True)
def _color_backward(sh: np.ndarray, g: int, sh_degree: int, x: float, y: float, z: float, n: float,
                    g_rgb: tuple[float, float, float], basis: np.ndarray, g_basis: np.ndarray, grad_sh: np.ndarray
                    ) -> tuple[float, float, float]:
    """Back through the SH colour of unit ray ``(x, y, z)`` at distance ``n``: adds into ``grad_sh[g]``; returns the
    gradient of the Gaussian's world centre through the ray."""
    k_used = sh_basis(sh_degree, x, y, z, basis)
    rgb = _sh_rgb(sh, g, k_used, basis)
    g0 = g_rgb[0] if rgb[0] > 0.0 else 0.0    # clamped at 0 (an unclamped exact 0 too) passes no gradient
    g1 = g_rgb[1] if rgb[1] > 0.0 else 0.0
    g2 = g_rgb[2] if rgb[2] > 0.0 else 0.0
    for k in range(k_used):
        grad_sh[g, k, 0] += basis[k] * g0
        grad_sh[g, k, 1] += basis[k] * g1
        grad_sh[g, k, 2] += basis[k] * g2
        g_basis[k] = sh[g, k, 0] * g0 + sh[g, k, 1] * g1 + sh[g, k, 2] * g2
    if sh_degree == 0:
        return 0.0, 0.0, 0.0
    gx, gy, gz = _basis_vjp(sh_degree, x, y, z, g_basis)
    radial = x * gx + y * gy + z * gz if n > TINY_DISTANCE else 0.0   # the clamped length passes none
    return (gx - x * radial) / n, (gy - y * radial) / n, (gz - z * radial) / n


@numba.njit(cache=True, error_model="numpy")
def gaussian_backward(g: int, means: np.ndarray, quats: np.ndarray, log_scales: np.ndarray, sh: np.ndarray,
                      sh_degree: int, rots: np.ndarray, trans: np.ndarray, centres: np.ndarray, models: np.ndarray,
                      lenses: np.ndarray, opts: np.ndarray, z7: np.ndarray, wm7: np.ndarray, wc7: np.ndarray,
                      z19: np.ndarray, wm19: np.ndarray, wc19: np.ndarray, drawn: np.ndarray, g_means2d: np.ndarray,
                      g_conics: np.ndarray, g_colors: np.ndarray, g_depths: np.ndarray, pose: bool, q: np.ndarray,
                      s: np.ndarray, R: np.ndarray, L: np.ndarray, uv7: np.ndarray, uv19: np.ndarray,
                      mom: np.ndarray, basis: np.ndarray, g_basis: np.ndarray, g_mu: np.ndarray, g_L: np.ndarray,
                      G: np.ndarray, gq: np.ndarray, gls: np.ndarray, grot: np.ndarray, acc: np.ndarray,
                      grad_means: np.ndarray, grad_quats: np.ndarray, grad_log_scales: np.ndarray,
                      grad_sh: np.ndarray, grad_pose: np.ndarray) -> None:
    """Gradients of Gaussian ``g`` summed over the views that drew it (``drawn[v, g]``), written to its rows.

    ``acc`` (10) sums the centre (3), quaternion (4) and log-scale (3) gradients; with ``pose`` each view's pose
    gradient goes to ``grad_pose[v, g]`` (``N_POSE_GRAD`` columns, zeros where not drawn).
    """
    for k in range(10):
        acc[k] = 0.0
    for k in range(sh.shape[1]):
        for ch in range(3):
            grad_sh[g, k, ch] = 0.0
    sigma = _shape(quats, log_scales, g, q, s, R)
    for v in range(rots.shape[0]):
        if pose:
            for k in range(N_POSE_GRAD):
                grad_pose[v, g, k] = 0.0
        if drawn[v, g] == 0:
            continue
        rot = rots[v]
        x, y, z, mx, my, mz = _to_camera(rots, trans, v, means, g)
        pk._rotate_scaled(rot, R, s, L)
        gmu, gmv = float(g_means2d[v, g, 0]), float(g_means2d[v, g, 1])
        gc0, gc1, gc2 = float(g_conics[v, g, 0]), float(g_conics[v, g, 1]), float(g_conics[v, g, 2])
        if opts[v, pk.EWA] > 0:
            g_sigma = _ewa_backward(models[v], lenses[v], opts[v], x, y, z, L, gmu, gmv, gc0, gc1, gc2,
                                    float(g_depths[v, g]), g_mu, g_L)
        else:
            g_sigma = _footprint_backward(models[v], lenses[v], opts[v], x, y, z, sigma, L, z7, wm7, wc7, z19, wm19,
                                          wc19, uv7, uv19, mom, gmu, gmv, gc0, gc1, gc2, float(g_depths[v, g]), g_mu,
                                          g_L)
        # sigma = exp(max log-scale): torch's amax splits the gradient evenly between ties
        ties = (s[0] == sigma) + (s[1] == sigma) + (s[2] == sigma)
        for k in range(9):
            grot[k] = 0.0
        pk._scale_rotation_backward(0, q[0], q[1], q[2], q[3], q[4], s, sigma, g_sigma / ties, rot, R, g_L, G,
                                    gq, gls, grot)
        for k in range(4):
            acc[3 + k] += gq[0, k]
        for k in range(3):
            acc[7 + k] += gls[0, k]
            acc[k] += rot[0, k] * g_mu[0] + rot[1, k] * g_mu[1] + rot[2, k] * g_mu[2]   # x_cam = rot m + t
        dx, dy, dz, n = _ray(means, g, centres, v)
        cx, cy, cz = _color_backward(sh, g, sh_degree, dx, dy, dz, n, (float(g_colors[v, g, 0]),
                                     float(g_colors[v, g, 1]), float(g_colors[v, g, 2])), basis, g_basis, grad_sh)
        acc[0] += cx
        acc[1] += cy
        acc[2] += cz
        if pose:
            for i in range(3):
                grad_pose[v, g, 3 * i] = grot[3 * i] + g_mu[i] * mx
                grad_pose[v, g, 3 * i + 1] = grot[3 * i + 1] + g_mu[i] * my
                grad_pose[v, g, 3 * i + 2] = grot[3 * i + 2] + g_mu[i] * mz
                grad_pose[v, g, 9 + i] = g_mu[i]
            grad_pose[v, g, 12], grad_pose[v, g, 13], grad_pose[v, g, 14] = -cx, -cy, -cz   # ray = m - centre
    for k in range(3):
        grad_means[g, k] = acc[k]
        grad_log_scales[g, k] = acc[7 + k]
    for k in range(4):
        grad_quats[g, k] = acc[3 + k]


_CPU_CHUNK = 256
"""Gaussians per parallel work item of the CPU launchers (one scratch allocation each)."""


@numba.njit(parallel=True, cache=True, error_model="numpy")
def views_forward_cpu(means: np.ndarray, quats: np.ndarray, log_scales: np.ndarray, sh: np.ndarray, sh_degree: int,
                      rots: np.ndarray, trans: np.ndarray, centres: np.ndarray, models: np.ndarray,
                      lenses: np.ndarray, opts: np.ndarray, z7: np.ndarray, wm7: np.ndarray, wc7: np.ndarray,
                      z19: np.ndarray, wm19: np.ndarray, wc19: np.ndarray, out_means: np.ndarray,
                      out_conics: np.ndarray, out_colors: np.ndarray, out_depths: np.ndarray,
                      out_drawn: np.ndarray) -> None:
    """``view_forward`` for every (view, Gaussian) on the CPU: what ``_cuda_kernels.views_forward`` computes."""
    n = means.shape[0]
    for ch in numba.prange((n + _CPU_CHUNK - 1) // _CPU_CHUNK):
        q, s, R, L = np.empty(5), np.empty(3), np.empty((3, 3)), np.empty((3, 3))
        uv7, uv19, mom, basis = np.empty((pk.N_UT, 8)), np.empty((N_FIFTH, 8)), np.empty((3, 5)), np.empty(N_BASIS)
        for g in range(ch * _CPU_CHUNK, min(n, (ch + 1) * _CPU_CHUNK)):
            for v in range(rots.shape[0]):
                view_forward(v, g, means, quats, log_scales, sh, sh_degree, rots, trans, centres, models, lenses,
                             opts, z7, wm7, wc7, z19, wm19, wc19, q, s, R, L, uv7, uv19, mom, basis, out_means,
                             out_conics, out_colors, out_depths, out_drawn)


@numba.njit(parallel=True, cache=True, error_model="numpy")
def views_backward_cpu(means: np.ndarray, quats: np.ndarray, log_scales: np.ndarray, sh: np.ndarray,
                       sh_degree: int, rots: np.ndarray, trans: np.ndarray, centres: np.ndarray, models: np.ndarray,
                       lenses: np.ndarray, opts: np.ndarray, z7: np.ndarray, wm7: np.ndarray, wc7: np.ndarray,
                       z19: np.ndarray, wm19: np.ndarray, wc19: np.ndarray, drawn: np.ndarray,
                       g_means2d: np.ndarray, g_conics: np.ndarray, g_colors: np.ndarray, g_depths: np.ndarray,
                       pose: bool, grad_means: np.ndarray, grad_quats: np.ndarray, grad_log_scales: np.ndarray,
                       grad_sh: np.ndarray, grad_pose: np.ndarray) -> None:
    """``gaussian_backward`` for every Gaussian on the CPU: what ``_cuda_kernels.views_backward`` computes."""
    n = means.shape[0]
    for ch in numba.prange((n + _CPU_CHUNK - 1) // _CPU_CHUNK):
        q, s, R, L = np.empty(5), np.empty(3), np.empty((3, 3)), np.empty((3, 3))
        uv7, uv19, mom, basis = np.empty((pk.N_UT, 8)), np.empty((N_FIFTH, 8)), np.empty((3, 5)), np.empty(N_BASIS)
        g_basis, g_mu, g_L, G = np.zeros(N_BASIS), np.empty(3), np.empty((3, 3)), np.empty((3, 3))
        gq, gls, grot, acc = np.empty((1, 4)), np.empty((1, 3)), np.empty(9), np.empty(10)
        for g in range(ch * _CPU_CHUNK, min(n, (ch + 1) * _CPU_CHUNK)):
            gaussian_backward(g, means, quats, log_scales, sh, sh_degree, rots, trans, centres, models, lenses, opts,
                              z7, wm7, wc7, z19, wm19, wc19, drawn, g_means2d, g_conics, g_colors, g_depths, pose,
                              q, s, R, L, uv7, uv19, mom, basis, g_basis, g_mu, g_L, G, gq, gls, grot, acc,
                              grad_means, grad_quats, grad_log_scales, grad_sh, grad_pose)
