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
    """Map "auto" to "gsplat" for CUDA tensors when gsplat is importable, else to "numba"."""
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
    """Composite M projected Gaussians into an image; returns (rgb [H,W,3], alpha [H,W], depth [H,W]).

    Differentiable w.r.t. means2d [M,2], conics [M,3], colors [M,3], opacities [M] and depths [M].
    alpha = 1 - final transmittance; depth = sum_i d_i alpha_i T_i is the unnormalised expected depth
    (divide by alpha for the mean depth of covered pixels). bg [3], if given, fills the remaining
    transmittance of rgb and is treated as a constant. Gaussians with a non positive definite conic or
    opacity below 1/255 are culled.
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
