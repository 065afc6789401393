"""Tile-based 3D Gaussian Splatting rasterizer: 2D Gaussians -> RGB, alpha and expected depth.

One entry point, three backends: "torch" (dense reference, small inputs), "numba" (binned CPU kernel,
forward and backward) and "gsplat" (CUDA). Conventions: pixel (row i, col j) has its centre at uv = (j, i);
conics are (a, b, c) of the inverse 2D covariance [[a, b], [b, c]]; opacities are already in [0, 1];
compositing is front to back by ascending depth with the 3DGS thresholds in `constants`.
"""

from __future__ import annotations

import importlib.util

import torch
from torch import Tensor

from .constants import ALPHA_MAX, ALPHA_MIN, T_MIN, TILE
from .reference import rasterize_reference

BACKENDS = ("auto", "torch", "numba", "gsplat")

__all__ = ["rasterize", "rasterize_reference", "resolve_backend", "BACKENDS", "ALPHA_MAX", "ALPHA_MIN", "T_MIN", "TILE"]


def resolve_backend(backend: str, device: torch.device) -> str:
    """Map "auto" to "gsplat" for CUDA tensors when gsplat is importable, else to "numba".

    Args:
        backend: one of ``BACKENDS``.
        device: the device of the tensors to rasterize.

    Returns:
        The backend that will run: "torch", "numba" or "gsplat" (others pass through unchanged).

    Raises:
        ValueError: ``backend`` is not one of ``BACKENDS``.
    """
    if backend not in BACKENDS:
        raise ValueError(f"unknown rasterizer backend {backend!r}; choose one of {BACKENDS}")
    if backend != "auto":
        return backend
    if device.type == "cuda" and importlib.util.find_spec("gsplat") is not None:
        return "gsplat"
    return "numba"


def _check_inputs(means2d: Tensor, conics: Tensor, colors: Tensor, opacities: Tensor, depths: Tensor) -> None:
    """Raise ValueError on inconsistent shapes (one row per Gaussian everywhere)."""
    m = means2d.shape[0]
    expected = {"means2d": (m, 2), "conics": (m, 3), "colors": (m, 3), "opacities": (m,), "depths": (m,)}
    for name, tensor in zip(expected, (means2d, conics, colors, opacities, depths)):
        if tuple(tensor.shape) != expected[name]:
            raise ValueError(f"{name} has shape {tuple(tensor.shape)}, expected {expected[name]}")


def rasterize(
    means2d: Tensor,
    conics: Tensor,
    colors: Tensor,
    opacities: Tensor,
    depths: Tensor,
    width: int,
    height: int,
    backend: str = "auto",
    bg: Tensor | None = None,
) -> tuple[Tensor, Tensor, Tensor]:
    """Composite M projected Gaussians front to back into an image, differentiably in all five inputs.

    Gaussians with a non positive definite conic or opacity below 1/255 are culled.

    Args:
        means2d: ``(M, 2)`` centres in pixels (u, v), pixel centres at integers.
        conics: ``(M, 3)`` inverse 2D covariances ``(a, b, c)`` of ``[[a, b], [b, c]]``, in 1/px^2.
        colors: ``(M, 3)`` RGB.
        opacities: ``(M,)`` in [0, 1].
        depths: ``(M,)`` sort keys (distance from the camera), also what ``depth`` averages.
        width: image width in pixels.
        height: image height in pixels.
        backend: one of ``BACKENDS`` ("auto": gsplat for CUDA tensors if installed, else numba).
        bg: ``(3,)`` background filling the remaining transmittance of rgb, a constant; None for black.

    Returns:
        ``(rgb, alpha, depth)``: ``(H, W, 3)``, ``(H, W)`` with alpha = 1 - final transmittance, and ``(H, W)``
        the unnormalised expected depth ``sum_i d_i alpha_i T_i`` (divide by alpha for the mean depth of
        covered pixels); the inputs' dtype.

    Raises:
        ValueError: an input whose shape is not one row per Gaussian as above, or an unknown ``backend``.

    Example:
        >>> import torch
        >>> rgb, alpha, depth = rasterize(torch.tensor([[1.0, 1.0]]), torch.tensor([[1.0, 0.0, 1.0]]),
        ...                               torch.tensor([[1.0, 0.0, 0.0]]), torch.tensor([0.5]), torch.tensor([2.0]),
        ...                               3, 3, backend="torch")
        >>> rgb.shape, rgb[1, 1].tolist(), alpha[1, 1].item(), depth[1, 1].item()
        (torch.Size([3, 3, 3]), [0.5, 0.0, 0.0], 0.5, 1.0)
    """
    _check_inputs(means2d, conics, colors, opacities, depths)
    chosen = resolve_backend(backend, means2d.device)
    if chosen == "torch":
        return rasterize_reference(means2d, conics, colors, opacities, depths, width, height, bg=bg)
    if chosen == "numba":
        from .cpu import rasterize_cpu

        return rasterize_cpu(means2d, conics, colors, opacities, depths, width, height, bg=bg)
    from .gsplat_backend import rasterize_gsplat

    return rasterize_gsplat(means2d, conics, colors, opacities, depths, width, height, bg=bg)
