"""Fused CPU projection: the numba UT kernels behind a ``torch.autograd.Function``.

Same results as the torch reference in ``projection.py`` (cull, 7-point UT with the adaptive
fifth-degree blend, blur, eigenvalue clamp, conic) in one pass per Gaussian, forward and backward,
instead of ~50 eager torch ops each sweeping memory. Serves the three lens models through a model id.
"""

from __future__ import annotations

import contextlib
import math
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from typing import Any, NamedTuple

import numpy as np
import torch
from torch import Tensor

from ..camera import CameraModel, OCamFisheye, OpenCVFisheye, Pinhole, RadialPolyFisheye
from . import _project_kernels as pk
from ._views_kernels import project_views
from .scratch import Allocator, fresh

__all__ = ["FusedUTConfig", "fused_supported", "project_ut_fused", "project_views_fused", "ViewsProjected",
           "keep_torch_threads"]

_MODEL_IDS: dict[type[CameraModel], int] = {
    OpenCVFisheye: pk.OPENCV_FISHEYE, RadialPolyFisheye: pk.RADIAL_POLY, Pinhole: pk.PINHOLE}


@dataclass(frozen=True)
class FusedUTConfig:
    """Everything the kernels need besides the tensors: sigma-point sets ``(z, wm, wc)``, rules and limits.

    Angles in radians; ``adaptive_*`` as ``UTParams`` (blend ramp ``adaptive_blend_theta`` wide),
    ``blur`` the 2D blur in px^2, eigenvalues clamped to ``[blur, (max_radius / extent_sigmas)^2]``;
    ``cull`` False projects every Gaussian (to measure what culling saves); ``ewa`` asks the device kernels for
    the first-order footprint (the CPU fused kernels are UT only).
    """

    unscented: tuple[Tensor, Tensor, Tensor]
    fifth_degree: tuple[Tensor, Tensor, Tensor]
    adaptive: bool
    adaptive_min_theta: float
    adaptive_blend_theta: float
    adaptive_min_rel_size: float
    near: float
    far: float
    blur: float
    extent_sigmas: float
    max_radius: float
    cull: bool = True
    ewa: bool = False


def fused_supported(camera: CameraModel, means: Tensor, quats: Tensor, log_scales: Tensor,
                    R_cam_world: Tensor | None) -> bool:
    """True for CPU float32/float64 Gaussians of one dtype and a built-in lens with constant intrinsics."""
    dtype = means.dtype
    rot_ok = R_cam_world is None or (R_cam_world.device.type == "cpu" and R_cam_world.is_floating_point())
    return (type(camera) in _MODEL_IDS and dtype in (torch.float32, torch.float64) and rot_ok
            and all(t.device.type == "cpu" and t.dtype == dtype for t in (means, quats, log_scales))
            and not any(t.requires_grad for t in (camera.fx, camera.fy, camera.cx, camera.cy, camera.k)))


def _lens(camera: CameraModel) -> np.ndarray:
    """The kernels' ``lens`` array: fx, fy, cx, cy, theta_max, rho_max, q(0), k1..k4, cos and sin of theta_max
    (k1..k4 zeros for an OCam lens, whose polynomials follow in the device kernels' slots)."""
    k = np.zeros(4)
    if not isinstance(camera, OCamFisheye):
        k[:camera.k.numel()] = camera.k.detach().numpy()
    q0 = float(camera.q(torch.zeros((), dtype=torch.float64), camera.k.detach()))
    return np.array([float(camera.fx), float(camera.fy), float(camera.cx), float(camera.cy),
                     camera.theta_max, camera.rho_max, q0, *k, math.cos(camera.theta_max), math.sin(camera.theta_max)],
                    dtype=np.float64)


def _opts(cfg: FusedUTConfig, camera: CameraModel, dtype: torch.dtype) -> np.ndarray:
    """The kernels' ``opts`` array (dtype limits as the torch path uses them for ``dtype``)."""
    o = np.empty(pk.N_OPTS, dtype=np.float64)
    o[pk.AXIS_EPS] = math.sqrt(torch.finfo(dtype).eps)
    o[pk.TINY] = torch.finfo(dtype).tiny
    o[pk.ADAPTIVE] = float(cfg.adaptive)
    o[pk.THETA_MIN] = cfg.adaptive_min_theta
    o[pk.BLEND] = cfg.adaptive_blend_theta
    o[pk.REL_SIZE] = cfg.adaptive_min_rel_size
    o[pk.BLUR] = cfg.blur
    o[pk.LO] = cfg.blur
    o[pk.HI] = (cfg.max_radius / cfg.extent_sigmas) ** 2
    o[pk.EXTENT] = cfg.extent_sigmas
    o[pk.WIDTH] = camera.width
    o[pk.HEIGHT] = camera.height
    o[pk.NEAR] = cfg.near
    o[pk.FAR] = cfg.far
    o[pk.CULL] = float(cfg.cull)
    o[pk.EWA] = float(cfg.ewa)
    return o


@contextlib.contextmanager
def keep_torch_threads() -> Iterator[None]:
    """Give torch back its intra-op thread count after numba kernels run inside the block.

    Numba's OpenMP layer sets the OpenMP thread count of the launching thread to its own on every parallel
    launch, and torch reads that same count: with torch at 1 thread and numba at 2, every torch op after a
    kernel ran on 2 threads, which on the loaded 2-core machine made 40 small ops take 970 ms instead of 2 ms.
    """
    n = torch.get_num_threads()
    try:
        yield
    finally:
        if torch.get_num_threads() != n:
            torch.set_num_threads(n)


def _np(t: Tensor) -> np.ndarray:
    """Contiguous numpy view (or copy) of a detached CPU tensor."""
    return np.ascontiguousarray(t.detach().numpy())


_SigmaSets = tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]
"""z7, wm7, wc7, z19, wm19, wc19: the kernels' sigma-point arguments, in their order."""


def _sets(cfg: FusedUTConfig) -> _SigmaSets:
    """Both sigma-point sets as float64 arrays: z7, wm7, wc7, z19, wm19, wc19."""
    z7, wm7, wc7, z19, wm19, wc19 = (np.ascontiguousarray(t.detach().to(torch.float64).numpy())
                                     for t in (*cfg.unscented, *cfg.fifth_degree))
    return z7, wm7, wc7, z19, wm19, wc19


class _ProjectUT(torch.autograd.Function):
    """Cull + project in the forward kernel; the backward kernel recomputes each Gaussian and reverses it."""

    @staticmethod
    def forward(ctx: Any, means: Tensor, quats: Tensor, log_scales: Tensor, rot: Tensor,
                camera: CameraModel, cfg: FusedUTConfig) -> tuple[Tensor, ...]:
        lens, opts, sets = _lens(camera), _opts(cfg, camera, means.dtype), _sets(cfg)
        m_np, q_np, ls_np = _np(means), _np(quats), _np(log_scales)
        rot_np = np.ascontiguousarray(rot.detach().to(torch.float64).numpy())
        keep = np.empty(len(m_np), dtype=np.bool_)
        with keep_torch_threads():
            pk.cull(m_np, ls_np, lens, opts, keep)
            index = np.flatnonzero(keep)
            m, dt = len(index), m_np.dtype
            out = (np.empty((m, 2), dt), np.empty((m, 3), dt), np.empty((m, 3), dt), np.empty(m, dt),
                   np.empty(m, dt), np.empty(m, np.bool_))
            pk.forward(index, m_np, q_np, ls_np, rot_np, _MODEL_IDS[type(camera)], lens, opts, *sets, *out)
        ctx.save_for_backward(means, quats, log_scales, rot)
        ctx.state = (index, lens, opts, sets, _MODEL_IDS[type(camera)])
        index_t, means2d, conics, cov2d, depths, radii, valid = (torch.from_numpy(a) for a in (index, *out))
        ctx.mark_non_differentiable(index_t, radii, valid)
        return index_t, means2d, conics, cov2d, depths, radii, valid

    @staticmethod
    def backward(ctx: Any, _g_index: Tensor | None, g_means2d: Tensor | None, g_conics: Tensor | None,
                 g_cov2d: Tensor | None, g_depths: Tensor | None, _g_radii: Tensor | None,
                 _g_valid: Tensor | None) -> tuple[Tensor | None, ...]:
        means, quats, log_scales, rot = ctx.saved_tensors
        sets: _SigmaSets
        index, lens, opts, sets, model = ctx.state
        m, m_np = len(index), _np(means)

        def grad(g: Tensor | None, shape: tuple[int, ...]) -> np.ndarray:
            return _np(g.to(means.dtype)) if g is not None else np.zeros(shape, m_np.dtype)

        g_means = np.zeros_like(m_np)
        g_quats = np.zeros(tuple(quats.shape), m_np.dtype)
        g_ls = np.zeros(tuple(log_scales.shape), m_np.dtype)
        g_rot = np.zeros(((m + pk.CHUNK - 1) // pk.CHUNK, pk.N_ROT_GRAD))
        with keep_torch_threads():
            pk.backward(index, m_np, _np(quats), _np(log_scales),
                        np.ascontiguousarray(rot.detach().to(torch.float64).numpy()), model, lens, opts, *sets,
                        grad(g_means2d, (m, 2)), grad(g_conics, (m, 3)), grad(g_cov2d, (m, 3)),
                        grad(g_depths, (m,)), g_means, g_quats, g_ls, g_rot)
        rot_grad = torch.from_numpy(g_rot.sum(0).reshape(3, 3)).to(rot.dtype) if ctx.needs_input_grad[3] else None
        return (torch.from_numpy(g_means), torch.from_numpy(g_quats), torch.from_numpy(g_ls), rot_grad, None, None)


def project_ut_fused(means_cam: Tensor, quats: Tensor, log_scales: Tensor, R_cam_world: Tensor | None,
                     camera: CameraModel, cfg: FusedUTConfig) -> tuple[Tensor, ...]:
    """Cull and UT-project with the fused kernels: ``(index, means2d, conics, cov2d, depths, radii, valid)``.

    Differentiable w.r.t. ``means_cam``, ``quats``, ``log_scales`` and ``R_cam_world`` (identity if None).
    """
    rot = torch.eye(3, dtype=torch.float64) if R_cam_world is None else R_cam_world
    return _ProjectUT.apply(means_cam, quats, log_scales, rot, camera, cfg)


class ViewsProjected(NamedTuple):
    """Dense per-camera rows ``[C, N, ...]`` (float32) of ``project_views_fused``; opacity 0 = not drawn."""

    means2d: np.ndarray
    conics: np.ndarray
    colors: np.ndarray
    opacities: np.ndarray
    depths: np.ndarray


def project_views_fused(means: Tensor, quats: Tensor, log_scales: Tensor, opacities: Tensor, sh: Tensor,
                        sh_degree: int, T_camera_world: Sequence[Tensor], cameras: Sequence[CameraModel],
                        cfgs: Sequence[FusedUTConfig], alloc: Allocator = fresh) -> ViewsProjected:
    """Cull, UT-project and SH-colour world Gaussians into every camera in one kernel pass (no autograd).

    ``T_camera_world[c]`` (4x4) places camera ``c``; ``cfgs[c]`` holds its UT rules and limits. Each
    Gaussian's rotation and scales are read once for all cameras, and only drawn Gaussians are coloured.
    ``alloc`` gives the output rows (new arrays by default; see ``parksim.render.scratch``).
    """
    n, c = means.shape[0], len(cameras)
    if cfgs[0].unscented[0].shape[0] != pk.N_UT:
        raise ValueError(f"project_views_fused: the UT set has {cfgs[0].unscented[0].shape[0]} points, not {pk.N_UT}")
    T = np.stack([np.asarray(t.detach().to(torch.float64).numpy()) for t in T_camera_world])
    rots, trans = np.ascontiguousarray(T[:, :3, :3]), np.ascontiguousarray(T[:, :3, 3])
    centres = np.ascontiguousarray(-np.einsum("cji,cj->ci", rots, trans))   # -R^T t
    models = np.array([_MODEL_IDS[type(cam)] for cam in cameras], dtype=np.int64)
    lenses = np.stack([_lens(cam) for cam in cameras])
    opts = np.stack([_opts(cfg, cam, means.dtype) for cfg, cam in zip(cfgs, cameras)])
    out = ViewsProjected(*(alloc(f"views.{name}", (c, n, *tail), np.float32)
                           for name, tail in zip(ViewsProjected._fields, ((2,), (3,), (3,), (), ()))))
    with keep_torch_threads():
        project_views(_np(means), _np(quats), _np(log_scales), _np(opacities), _np(sh), sh_degree, rots, trans,
                      centres, models, lenses, opts, *_sets(cfgs[0]), *out)
    return out
