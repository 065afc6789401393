"""Camera models that project on the whole sphere (fisheye lenses see past 90 deg).

Each model has ``project(points[...,3]) -> (uv[...,2], valid[...])`` and
``unproject(uv[...,2]) -> rays[...,3]``, differentiable in points and intrinsics.
"""

from .base import CameraModel
from .models import OpenCVFisheye, Pinhole, RadialPolyFisheye, camera_from_dict

__all__ = ["CameraModel", "OpenCVFisheye", "RadialPolyFisheye", "Pinhole", "camera_from_dict"]
