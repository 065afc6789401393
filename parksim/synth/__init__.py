"""Synthetic underground garages seen by a four-fisheye AVM rig, written as ParkRecon3D-style datasets.

Ground truth comes from analytic ray casting (floor, ceiling, boxes) through the exact
full-sphere fisheye model, with 2x2 supersampling; no Gaussians are involved.
"""

from ..kernel_cache import configure as _configure_kernel_cache

_configure_kernel_cache()  # before the kernel modules: their cache must match this source

from .generate import GENERATOR_VERSION, SceneRenderer, generate, scene_map  # noqa: E402
from .presets import PRESETS, ScenePreset, get_preset  # noqa: E402

__all__ = ["generate", "SceneRenderer", "scene_map", "PRESETS", "ScenePreset", "get_preset", "GENERATOR_VERSION"]
