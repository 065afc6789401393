"""Named synthetic scenes: four clean benchmark garages (scene1..scene4), two hard ones that look like real
garages (worn: dim, faded and dirty; busy: full, cluttered, glossy, unevenly exposed; see docs/synth.md) and a
tiny one for tests."""

from __future__ import annotations

from dataclasses import dataclass, field

from .garage import LayoutParams
from .shading import SensorOptions
from .trajectory import TrajectoryParams

__all__ = ["ScenePreset", "PRESETS", "get_preset"]


@dataclass(frozen=True)
class ScenePreset:
    """Everything that defines one generated scene."""

    name: str
    layout: LayoutParams
    trajectory: TrajectoryParams
    frames: int = 100
    width: int = 640
    height: int = 480
    bev_px: int = 600
    points: int = 30000
    sensor: SensorOptions = field(default_factory=SensorOptions)

    def __post_init__(self) -> None:
        sizes = {"frames": self.frames, "width": self.width, "height": self.height, "bev_px": self.bev_px,
                 "points": self.points}
        bad = {k: v for k, v in sizes.items() if v < 1}
        if bad:
            raise ValueError(f"scene preset {self.name!r}: {', '.join(f'{k} {v}' for k, v in bad.items())} "
                             "must be at least 1")


PRESETS: dict[str, ScenePreset] = {
    "scene1": ScenePreset("scene1", LayoutParams(seed=101, length=48.0,
                                                 kinds=("perpendicular",) * 3 + ("slanted", "parallel")),
                          TrajectoryParams("aisle", speed=2.0, start_x=5.0, weave=0.5)),
    "scene2": ScenePreset("scene2", LayoutParams(seed=202, length=56.0, kinds=("perpendicular", "slanted"),
                                                 slant_deg=45.0, yellow_fraction=0.7, occupancy=0.7,
                                                 light_spacing=7.5, light_intensity=0.8, ambient=0.08),
                          TrajectoryParams("aisle", speed=2.4, start_x=6.0, weave=0.3)),
    "scene3": ScenePreset("scene3", LayoutParams(seed=303, length=44.0, aisles=2, kinds=("perpendicular", "parallel"),
                                                 occupancy=0.45, broken_lights=0.2, light_intensity=1.2),
                          TrajectoryParams("turn", speed=1.8)),
    "scene4": ScenePreset("scene4", LayoutParams(seed=404, length=52.0, aisles=2, height=3.2,
                                                 kinds=("perpendicular", "slanted", "parallel"), slant_deg=55.0,
                                                 yellow_fraction=0.5, occupancy=0.6, light_spacing=5.0,
                                                 light_intensity=0.7, ambient=0.15),
                          TrajectoryParams("turn", speed=2.2)),
    "worn": ScenePreset("worn", LayoutParams(seed=505, length=50.0, kinds=("perpendicular", "perpendicular",
                                                                          "slanted", "parallel"),
                                             yellow_fraction=0.4, occupancy=0.6, light_spacing=7.0,
                                             light_intensity=0.7, broken_lights=0.3, ambient=0.045, light_falloff=6.0,
                                             car_variety=1.0, clutter=0.4, signage=True, paint_fade=0.5,
                                             paint_scuff=0.25, tyre_marks=0.8, stains=1.5, wet_patches=0.6,
                                             floor_gloss=0.1, grime=0.7),
                        TrajectoryParams("aisle", speed=2.0, start_x=5.0, weave=0.5),
                        sensor=SensorOptions(exposure_low=0.75, exposure_high=1.25, drift=0.06, white_balance=0.08,
                                             vignette_strength=0.5, noise_scale=1.8)),
    "busy": ScenePreset("busy", LayoutParams(seed=606, length=52.0, aisles=2, kinds=("perpendicular", "slanted",
                                                                                       "parallel"),
                                             slant_deg=60.0, yellow_fraction=0.5, occupancy=0.92, light_spacing=6.0,
                                             light_intensity=0.9, broken_lights=0.15, ambient=0.08, light_falloff=5.0,
                                             car_variety=1.0, clutter=0.9, signage=True, paint_fade=0.35,
                                             paint_scuff=0.15, tyre_marks=0.5, stains=0.8, wet_patches=0.3,
                                             floor_gloss=0.8, grime=0.4),
                        TrajectoryParams("turn", speed=2.2),
                        sensor=SensorOptions(exposure_low=0.6, exposure_high=1.4, drift=0.1, white_balance=0.15,
                                             vignette_strength=0.45, noise_scale=1.3, motion_blur=1 / 60)),
    "tiny": ScenePreset("tiny", LayoutParams(seed=7, length=34.0, kinds=("perpendicular", "slanted")),
                        TrajectoryParams("aisle", speed=2.0, start_x=6.0), frames=12, width=160, height=120,
                        bev_px=300, points=3000),
}


def get_preset(name: str) -> ScenePreset:
    """The preset called ``name``; the error lists the known ones."""
    if name not in PRESETS:
        raise ValueError(f"unknown preset {name!r}; known presets: {', '.join(PRESETS)}")
    return PRESETS[name]
