"""Every view of a render projected and coloured in one differentiable kernel launch, on the Gaussians' device.

``project_views_device`` takes world-frame Gaussians and V camera poses (all cameras of all poses of a render or a
batch) and returns dense ``[V, N, ...]`` rows: 2D means, conics, colours, distances and whether each (view, Gaussian)
is drawn; rows not drawn are zeros, so the rasterizer needs no gather (no host synchronisation). Its backward runs
one kernel over the Gaussians and gives the gradients of the means, quaternions, log-scales, SH coefficients and,
when asked for, of the views' poses (rotation, translation, centre), for pose refinement.

On CUDA tensors the kernels are ``_cuda_kernels`` (numba-cuda); on CPU tensors the same bodies run on numba's CPU
target (``_device_bodies``), which is how CI, with no GPU, tests the GPU kernels' values and gradients. The maths is
``projection.py``'s UT (and the fused CPU kernels'): the full sphere, rim for points past the valid angle, never
mirrored.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any, NamedTuple

import numpy as np
import torch
from torch import Tensor

from ..camera import CameraModel, OCamFisheye
from . import _device_bodies as body
from . import _project_kernels as pk
from .project_fast import _MODEL_IDS, FusedUTConfig, _lens, _opts

__all__ = ["DeviceViews", "device_supported", "project_views_device", "view_transforms"]


class DeviceViews(NamedTuple):
    """Dense per-view rows ``[V, N, ...]`` in the Gaussians' dtype; ``drawn`` is bool, False rows are zeros.

    Attributes:
        means2d: ``[V, N, 2]`` pixel centres (pixel ``(i, j)`` at ``(j, i)``).
        conics: ``[V, N, 3]`` inverse 2D covariances ``(a, b, c)``.
        colors: ``[V, N, 3]`` SH colour along the view ray, clamped at 0.
        depths: ``[V, N]`` distance from the camera centre (m).
        drawn: ``[V, N]`` the Gaussian is drawn in the view (not culled, finite, on the image).
    """

    means2d: Tensor
    conics: Tensor
    colors: Tensor
    depths: Tensor
    drawn: Tensor


_DEVICE_MODEL_IDS: dict[type[CameraModel], int] = {**_MODEL_IDS, OCamFisheye: pk.OCAM}
"""The fused CPU kernels' lens models and OCam."""


def _device_lens(camera: CameraModel) -> np.ndarray:
    """The kernels' ``lens`` array (``_project_kernels``' slots); an OCam lens adds its affine and polynomials."""
    if not isinstance(camera, OCamFisheye):
        return _lens(camera)
    ss, series, rho_hi = camera.radial_polynomials()
    ss_np = np.zeros(0) if ss is None else ss.numpy()
    ocam = np.array([float(camera.d), float(camera.e), rho_hi, len(ss_np), len(series)], dtype=np.float64)
    return np.concatenate([_lens(camera), ocam, ss_np, series.numpy()])


def _stacked_lenses(cameras: Sequence[CameraModel]) -> np.ndarray:
    """``[V, width]`` lens arrays, zero-padded to the longest (OCam polynomials differ in length)."""
    rows = [_device_lens(cam) for cam in cameras]
    out = np.zeros((len(rows), max(len(r) for r in rows)), dtype=np.float64)
    for i, r in enumerate(rows):
        out[i, :len(r)] = r
    return out


def device_supported(camera: CameraModel) -> bool:
    """Whether the kernels serve ``camera``: a built-in lens model (OpenCV/KB fisheye, radial polynomial, pinhole,
    OCam) whose intrinsics need no gradient.

    Args:
        camera: a lens model.

    Returns:
        True when ``project_views_device`` can project into it.
    """
    return type(camera) in _DEVICE_MODEL_IDS and not any(t.requires_grad for t in (camera.fx, camera.fy, camera.cx,
                                                                          camera.cy, camera.k))


def view_transforms(T_world_cameras: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """``(rots [V, 3, 3], trans [V, 3], centres [V, 3])`` of ``T_camera_world = [rots | trans]``, float64, from
    ``T_world_cameras [V, 4, 4]`` (differentiably: a pose tensor's gradient flows through them).

    Args:
        T_world_cameras: ``[V, 4, 4]`` camera-to-world rigid transforms.

    Returns:
        The world-to-camera rotations and translations and the camera centres in the world.
    """
    T = T_world_cameras.to(torch.float64)
    rots = T[:, :3, :3].transpose(1, 2)
    centres = T[:, :3, 3]
    return rots, -(rots @ centres.unsqueeze(-1)).squeeze(-1), centres


_Static = tuple[Tensor, ...]
"""models, lenses, opts, z7, wm7, wc7, z19, wm19, wc19: the kernels' non-differentiable arguments, on the device."""

_STATIC_CACHE: dict[tuple[Any, ...], _Static] = {}
_STATIC_CACHE_SIZE = 64


def _static(cameras: Sequence[CameraModel], cfgs: Sequence[FusedUTConfig], dtype: torch.dtype,
            device: torch.device) -> _Static:
    """The lens, option and sigma-point arrays of the views, on ``device`` (built on the host once per content)."""
    models = np.array([_DEVICE_MODEL_IDS[type(cam)] for cam in cameras], dtype=np.int64)
    lenses = _stacked_lenses(cameras)
    opts = np.stack([_opts(cfg, cam, dtype) for cfg, cam in zip(cfgs, cameras)])
    sets = [t.detach().to(torch.float64).numpy() for t in (*cfgs[0].unscented, *cfgs[0].fifth_degree)]
    key = (str(device), models.tobytes(), lenses.tobytes(), opts.tobytes(), *(a.tobytes() for a in sets))
    hit = _STATIC_CACHE.get(key)
    if hit is None:
        if len(_STATIC_CACHE) >= _STATIC_CACHE_SIZE:
            _STATIC_CACHE.clear()
        hit = tuple(torch.from_numpy(np.ascontiguousarray(a)).to(device) for a in (models, lenses, opts, *sets))
        _STATIC_CACHE[key] = hit
    return hit


def _launch(name: str, items: int, device: torch.device, *args: Any) -> None:
    """Run kernel ``name`` over ``items`` work items: numba-cuda on a CUDA device, else its CPU twin."""
    if items == 0:   # an empty scene: nothing to launch (a CUDA grid of 0 blocks is an error)
        return
    if device.type == "cuda":
        from . import _cuda_kernels as kernels
        from ._numba_cuda import cuda

        with cuda.gpus[device.index if device.index is not None else torch.cuda.current_device()]:
            stream = cuda.external_stream(torch.cuda.current_stream(device).cuda_stream)
            converted = [cuda.as_cuda_array(a.detach()) if isinstance(a, Tensor) else a for a in args]
            getattr(kernels, name)[(items + kernels.THREADS - 1) // kernels.THREADS, kernels.THREADS, stream](
                *converted)
        return
    getattr(body, f"{name}_cpu")(*[a.detach().numpy() if isinstance(a, Tensor) else a for a in args])


class _ProjectViews(torch.autograd.Function):
    """Forward: one launch over (view, Gaussian); backward: one launch over Gaussians."""

    @staticmethod
    def forward(ctx: Any, means: Tensor, quats: Tensor, log_scales: Tensor, sh: Tensor, rots: Tensor, trans: Tensor,
                centres: Tensor, sh_degree: int, static: _Static) -> tuple[Tensor, ...]:
        v, n, dtype, device = rots.shape[0], means.shape[0], means.dtype, means.device
        out = (torch.empty((v, n, 2), dtype=dtype, device=device), torch.empty((v, n, 3), dtype=dtype, device=device),
               torch.empty((v, n, 3), dtype=dtype, device=device), torch.empty((v, n), dtype=dtype, device=device),
               torch.empty((v, n), dtype=torch.uint8, device=device))
        inputs = (means.contiguous(), quats.contiguous(), log_scales.contiguous(), sh.contiguous(), sh_degree,
                  rots.contiguous(), trans.contiguous(), centres.contiguous(), *static)
        _launch("views_forward", v * n, device, *inputs, *out)
        drawn = out[4].bool()
        ctx.save_for_backward(*(t for t in inputs if isinstance(t, Tensor)), out[4])
        ctx.sh_degree = sh_degree
        ctx.mark_non_differentiable(drawn)
        return (*out[:4], drawn)

    @staticmethod
    def backward(ctx: Any, g_means2d: Tensor | None, g_conics: Tensor | None, g_colors: Tensor | None,
                 g_depths: Tensor | None, _g_drawn: Tensor | None) -> tuple[Tensor | None, ...]:
        means, quats, log_scales, sh, rots, trans, centres, *static, drawn = ctx.saved_tensors
        v, n, dtype, device = rots.shape[0], means.shape[0], means.dtype, means.device

        def grad(g: Tensor | None, *tail: int) -> Tensor:
            return (g.to(dtype).contiguous() if g is not None
                    else torch.zeros((v, n, *tail), dtype=dtype, device=device))

        pose = any(ctx.needs_input_grad[4:7])
        grads = (torch.empty_like(means), torch.empty_like(quats), torch.empty_like(log_scales), torch.empty_like(sh),
                 torch.empty((v, n, body.N_POSE_GRAD) if pose else (1, 1, body.N_POSE_GRAD), dtype=torch.float64,
                             device=device))
        _launch("views_backward", n, device, means, quats, log_scales, sh, ctx.sh_degree, rots, trans, centres,
                *static, drawn, grad(g_means2d, 2), grad(g_conics, 3), grad(g_colors, 3), grad(g_depths), pose,
                *grads)
        g_rots = g_trans = g_centres = None
        if pose:
            total = grads[4].sum(1)
            g_rots, g_trans, g_centres = total[:, :9].reshape(v, 3, 3), total[:, 9:12], total[:, 12:15]
        return (*grads[:4], g_rots, g_trans, g_centres, None, None)


def project_views_device(means: Tensor, quats: Tensor, log_scales: Tensor, sh: Tensor, sh_degree: int,
                         T_world_cameras: Tensor, cameras: Sequence[CameraModel], cfgs: Sequence[FusedUTConfig]
                         ) -> DeviceViews:
    """Cull, UT-project and SH-colour N world Gaussians into V views with one kernel launch (differentiable).

    Args:
        means: ``[N, 3]`` world centres (float32 or float64; every Gaussian tensor of one dtype and device).
        quats: ``[N, 4]`` rotations (w, x, y, z), any norm.
        log_scales: ``[N, 3]``.
        sh: ``[N, K, 3]`` SH coefficients, ``K >= (sh_degree + 1)^2``.
        sh_degree: SH degree used, 0..3.
        T_world_cameras: ``[V, 4, 4]`` camera-to-world transforms (a gradient reaches them when they need one).
        cameras: V lens models (``device_supported``), at the size to render.
        cfgs: V UT configurations (``projection.fused_config``); one sigma-point set for all.

    Returns:
        ``DeviceViews`` of ``[V, N, ...]`` rows on the Gaussians' device.

    Raises:
        ValueError: mismatched counts, a lens the kernels do not serve, or a UT set of another size.
    """
    if not (len(cameras) == len(cfgs) == T_world_cameras.shape[0]):
        raise ValueError(f"project_views_device: {T_world_cameras.shape[0]} poses, {len(cameras)} cameras and "
                         f"{len(cfgs)} configs")
    unsupported = [type(c).__name__ for c in cameras if not device_supported(c)]
    if unsupported:
        raise ValueError(f"project_views_device: no device kernel for {unsupported}")
    z7, z19 = cfgs[0].unscented[0], cfgs[0].fifth_degree[0]
    if z7.shape[0] != 7 or z19.shape[0] != body.N_FIFTH:
        raise ValueError(f"project_views_device: sigma-point sets of {z7.shape[0]} and {z19.shape[0]} points, not 7 "
                         f"and {body.N_FIFTH}")
    rots, trans, centres = view_transforms(T_world_cameras.to(means.device))
    static = _static(cameras, cfgs, means.dtype, means.device)
    return DeviceViews(*_ProjectViews.apply(means, quats, log_scales, sh, rots, trans, centres, sh_degree, static))
