"""Scene registry: every bundle under the scenes folder loaded once at start-up and shared by all requests.

Each scene is a ``parksim.sim.LocalSim``, which caches its per-scale precomputation (scaled rig,
IPM grids and blend weights); renders reuse it. ``check_pose`` keeps poses inside the scene. A bundle that does not
load is refused (its reason kept for ``/scenes`` and ``/healthz`` and logged as a warning) while the others are
served, unless the folder is loaded strictly.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import TYPE_CHECKING

from parksim.bundle import META, BundleError
from parksim.device import resolve_device
from parksim.frames import RequestError
from parksim.sim import LocalSim

from .schemas import Pose
from .settings import Settings

if TYPE_CHECKING:
    import torch

__all__ = ["SceneRegistry", "UnknownScene", "check_pose", "WARM_UP_SCALE"]

log = logging.getLogger(__name__)

WARM_UP_SCALE = 0.25
"""Image scale of ``SceneRegistry.warm_up``'s renders (the kernels compiled do not depend on it)."""


class UnknownScene(LookupError):
    """A request names a scene that is not loaded; the message lists the loaded ones."""


class SceneRegistry:
    """Loaded scenes by id (bundle folder name), in sorted order; the first is the default. ``refused`` maps the id
    of each bundle that did not load to the one-line reason, naming the bad file."""

    def __init__(self, sims: Iterable[LocalSim], refused: Mapping[str, str] | None = None) -> None:
        self.sims = {s.id: s for s in sorted(sims, key=lambda s: s.id)}
        self.refused = dict(sorted((refused or {}).items()))
        if not self.sims:
            why = "; ".join(f"{scene_id}: {reason}" for scene_id, reason in self.refused.items())
            raise BundleError(f"no scene to serve: every bundle was refused ({why})" if why else "no scene to serve")

    @classmethod
    def from_dir(cls, scenes_dir: str | Path, strict: bool = False, device: str | torch.device = "auto"
                 ) -> SceneRegistry:
        """Every bundle folder directly under ``scenes_dir`` (or ``scenes_dir`` itself when it is a bundle), each
        rendering on ``device`` (``auto``, ``cpu`` or ``cuda[:N]``, resolved once, before any bundle loads).

        A bundle that fails to load is refused with its one-line error, logged as a warning, and the others are
        served; with ``strict`` the first such error is raised instead. ``BundleError`` when none loads;
        ``DeviceError`` for a bad device name or a missing GPU.
        """
        device = resolve_device(device)   # a bad device is the caller's error, not a refusal of every bundle
        root = Path(scenes_dir)
        if not root.is_dir():
            raise BundleError(f"scenes folder not found: {root}")
        dirs = [root] if (root / META).is_file() else sorted(d for d in root.iterdir() if (d / META).is_file())
        if not dirs:
            raise BundleError(f"{root}: no scene bundle (a folder with {META}) in it")
        sims: list[LocalSim] = []
        refused: dict[str, str] = {}
        for d in dirs:
            try:
                sims.append(LocalSim.from_dir(d, device))
            except (ValueError, OSError) as e:   # BundleError, a bad field, an unreadable file: not a bug
                if strict:
                    raise
                reason = " ".join(str(e).split()) or type(e).__name__
                refused[d.name] = reason if str(d) in reason else f"{d}: {reason}"
                log.warning("refused scene %r: %s", d.name, refused[d.name])
        return cls(sims, refused)

    @property
    def ids(self) -> list[str]:
        return list(self.sims)

    def warm_up(self, scale: float = WARM_UP_SCALE) -> None:
        """Render every scene once, small (all cameras, depth and the BEV at the middle of its bounds), before the
        app serves: the first render after an install or a kernel change compiles the kernels (a minute or more on
        two cores), which must not run into a request's ``render_timeout_s``. Loaded from the kernel cache it
        takes milliseconds.

        Args:
            scale: image size relative to the rig's cameras.
        """
        for sim in self.sims.values():
            (x0, x1), (y0, y1) = sim.bounds["x"], sim.bounds["y"]
            sim.render(((x0 + x1) / 2, (y0 + y1) / 2, 0.0), None, bev=True, scale=scale, depth=True)

    def get(self, scene_id: str | None) -> LocalSim:
        """The scene ``scene_id`` (the default scene when None)."""
        if scene_id is None:
            return next(iter(self.sims.values()))
        if scene_id not in self.sims:
            raise UnknownScene(f"unknown scene {scene_id!r}; loaded scenes: {self.ids}")
        return self.sims[scene_id]


def check_pose(sim: LocalSim, pose: Pose, settings: Settings) -> None:
    """``RequestError`` unless ``pose`` lies within the scene bounds plus the margin and is not tilted too far."""
    m = settings.pose_margin_m
    z_lo, z_hi = sim.bounds["z"]
    limits = {"x": (sim.bounds["x"][0] - m, sim.bounds["x"][1] + m),
              "y": (sim.bounds["y"][0] - m, sim.bounds["y"][1] + m),
              "z": (z_lo - 1.0, z_hi)}
    for axis, (lo, hi) in limits.items():
        v = getattr(pose, axis)
        if not lo <= v <= hi:
            why = f"scene bounds plus a {m:g} m margin" if axis != "z" else "1 m below the floor up to the ceiling"
            raise RequestError(f"pose {axis}={v:g} is outside scene {sim.id!r}: {axis} must be in [{lo:g}, {hi:g}] "
                               f"({why})")
    for angle in ("roll", "pitch"):
        v = getattr(pose, angle)
        if abs(v) > settings.max_tilt_rad:
            raise RequestError(f"pose {angle}={v:g} rad is too tilted: |{angle}| must be <= "
                               f"{settings.max_tilt_rad:g} rad")
    if abs(pose.yaw) > 1e6 * math.pi:
        raise RequestError(f"pose yaw={pose.yaw:g} rad is too large: |yaw| must be <= {1e6 * math.pi:g} rad")
