"""Renderer: cull + project Gaussians through the exact camera (UT), rasterize, optional BEV by IPM."""

from ..kernel_cache import configure as _configure_kernel_cache

_configure_kernel_cache()  # before the kernel modules: their cache must match this source

from .api import RenderResult, bev_ipm, render, render_batch  # noqa: E402
from .projection import Projected2D, UTParams, project_gaussians  # noqa: E402

__all__ = ["render", "render_batch", "RenderResult", "bev_ipm", "project_gaussians", "Projected2D", "UTParams"]
