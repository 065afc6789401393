"""Named synthetic scenes: four benchmark garages (scene1..scene4) and a tiny one for tests."""

from __future__ import annotations

from dataclasses import dataclass, field

from .layout import LayoutParams
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
    "tiny": ScenePreset("tiny", LayoutParams(seed=7, length=34.0, kinds=("perpendicular", "slanted")),
                        TrajectoryParams("aisle", speed=2.0, start_x=6.0), frames=12, width=160, height=120,
                        bev_px=300, points=3000),
}


def get_preset(name: str) -> ScenePreset:
    """The preset called ``name``; the error lists the known ones."""
    if name not in PRESETS:
        raise ValueError(f"unknown preset {name!r}; known presets: {', '.join(PRESETS)}")
    return PRESETS[name]
