"""Renderer: cull + project Gaussians through the exact camera (UT), rasterize, optional BEV by IPM."""

from .api import RenderResult, bev_ipm, render
from .projection import Projected2D, UTParams, project_gaussians

__all__ = ["render", "RenderResult", "bev_ipm", "project_gaussians", "Projected2D", "UTParams"]
