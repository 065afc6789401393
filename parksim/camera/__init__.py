"""Camera models that project on the whole sphere (fisheye lenses see past 90 deg).

Each model has ``project(points[...,3]) -> (uv[...,2], valid[...])`` and
``unproject(uv[...,2]) -> rays[...,3]``, differentiable in points and intrinsics.
"""

from .base import CameraModel, pixel_grid
from .models import OpenCVFisheye, Pinhole, RadialPolyFisheye, camera_from_dict
from .ocam import OCamFisheye

__all__ = ["CameraModel", "pixel_grid", "OpenCVFisheye", "RadialPolyFisheye", "Pinhole", "OCamFisheye",
           "camera_from_dict"]
