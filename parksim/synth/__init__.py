"""Synthetic underground garages seen by a four-fisheye AVM rig, written as ParkRecon3D-style datasets.

Ground truth comes from analytic ray casting (floor, ceiling, boxes) through the exact
full-sphere fisheye model, with 2x2 supersampling; no Gaussians are involved.
"""

from .generate import GENERATOR_VERSION, SceneRenderer, generate, scene_map
from .presets import PRESETS, ScenePreset, get_preset

__all__ = ["generate", "SceneRenderer", "scene_map", "PRESETS", "ScenePreset", "get_preset", "GENERATOR_VERSION"]
