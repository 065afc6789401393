"""Gaussian actor assets: an object's Gaussians in its own frame, its footprint box and a name, as a folder.

An actor (a parked or moving car, a pedestrian) is rendered with the scene by placing its asset at a pose
(``parksim.render.actors``). The asset frame is ParkSim's vehicle convention: x forward, y left, z up, the origin on
the ground under the actor's reference point (a car's centre), so an ``(x, y, yaw)`` pose stands it on the floor.

```
asset.json      {"version", "name", "box": [[x0, y0, z0], [x1, y1, z1]], "meta": {...}}
gaussians.ply   the Gaussians in the asset frame (INRIA 3DGS layout)
```
``parksim.actor_sources`` makes assets (synth cars and a pedestrian baked to Gaussians, a box cropped out of a
bundle, a third-party 3DGS PLY); ``parksim asset`` writes them.
"""

from __future__ import annotations

import json
import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor

from .fileio import atomic_directory, atomic_write, write_json
from .gaussians import GaussianScene, PLYFormatError
from .geometry import as_pose

__all__ = ["ActorAsset", "AssetError", "load_asset", "save_asset", "ASSET_VERSION"]

ASSET_VERSION = 1
"""Bumped when the asset folder layout changes incompatibly."""
GAUSSIANS, META = "gaussians.ply", "asset.json"


class AssetError(ValueError):
    """An asset folder is missing a file, holds an unreadable one or an invalid box; the message names it."""


Box = tuple[tuple[float, float, float], tuple[float, float, float]]
"""``((x0, y0, z0), (x1, y1, z1))``: an axis-aligned box in the asset frame, lower corner first (m)."""


@dataclass(eq=False)
class ActorAsset:
    """An actor's Gaussians in its own frame, its footprint box and its name.

    Attributes:
        name: what the asset shows (``sedan``, ``pedestrian``, a file's name), for messages and scenario files.
        scene: the Gaussians in the asset frame (x forward, y left, z up, origin on the ground).
        box: ``((x0, y0, z0), (x1, y1, z1))`` the actor's extent in the asset frame (m); its floor rectangle is the
            footprint that collision checks use.
        meta: provenance (what it was baked or cropped from), kept in ``asset.json``.

    Raises:
        AssetError: an empty name, no Gaussians, invalid Gaussians, or a box that is not finite with lo < hi.
    """

    name: str
    scene: GaussianScene
    box: Box
    meta: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        """Check the name, the Gaussians (``GaussianScene.validate``) and the box; store the box as floats."""
        if not isinstance(self.name, str) or not self.name.strip():
            raise AssetError(f"actor asset: name must be a non-empty string, got {self.name!r}")
        if len(self.scene) == 0:
            raise AssetError(f"actor asset {self.name!r}: holds no Gaussians")
        try:
            self.scene.validate()
            lo, hi = (tuple(float(v) for v in corner) for corner in self.box)
        except (TypeError, ValueError) as e:
            raise AssetError(f"actor asset {self.name!r}: {' '.join(str(e).split())}") from None
        if len(lo) != 3 or len(hi) != 3 or not all(math.isfinite(v) for v in lo + hi) or \
                not all(a < b for a, b in zip(lo, hi)):
            raise AssetError(f"actor asset {self.name!r}: box must be two finite corners (x, y, z) with lo < hi "
                             f"on every axis, got {self.box}")
        self.box = (lo, hi)

    def footprint(self, pose: Tensor | Sequence[float] = (0.0, 0.0, 0.0)) -> np.ndarray:
        """The box's floor rectangle in the world with the actor at ``pose``.

        Args:
            pose: ``T_world_actor`` as ``parksim.geometry.as_pose`` takes it (4x4, ``(x, y, yaw)`` or 6 numbers).

        Returns:
            ``(4, 2)`` float64 world ``(x, y)`` corners, counter-clockwise from ``(x1, y1)`` (front left).
        """
        (x0, y0, _), (x1, y1, _) = self.box
        corners = np.array([[x1, y1, 0.0, 1.0], [x0, y1, 0.0, 1.0], [x0, y0, 0.0, 1.0], [x1, y0, 0.0, 1.0]])
        T = as_pose(pose).detach().cpu().numpy()
        return (corners @ T.T)[:, :2]

    def obstacle(self, pose: Tensor | Sequence[float] = (0.0, 0.0, 0.0), kind: str = "actor") -> dict[str, Any]:
        """The actor at ``pose`` as a ``map.json`` obstacle (what ``parksim.vehicle.Obstacles`` collides with).

        Args:
            pose: ``T_world_actor`` as ``footprint`` takes it; its yaw turns the box (roll and pitch are ignored).
            kind: the obstacle's ``kind``.

        Returns:
            ``{"kind", "center": [x, y], "size": [length, width], "z": [z0, z1], "yaw"}`` in the world (m, rad).
        """
        (x0, y0, z0), (x1, y1, z1) = self.box
        T = as_pose(pose).detach().cpu().numpy()
        centre = T @ np.array([(x0 + x1) / 2, (y0 + y1) / 2, 0.0, 1.0])
        return {"kind": kind, "center": [float(centre[0]), float(centre[1])], "size": [x1 - x0, y1 - y0],
                "z": [z0 + float(T[2, 3]), z1 + float(T[2, 3])], "yaw": math.atan2(T[1, 0], T[0, 0])}


def save_asset(directory: str | Path, asset: ActorAsset, overwrite: bool = False) -> Path:
    """Write ``asset`` as a folder, whole or not at all.

    Args:
        directory: the asset folder to write.
        asset: what to write (its Gaussians as float32).
        overwrite: replace an existing folder.

    Returns:
        ``directory`` as a Path.

    Raises:
        FileExistsError: ``directory`` exists and ``overwrite`` is False.
    """
    directory = Path(directory)
    with atomic_directory(directory, overwrite=overwrite) as tmp:
        atomic_write(tmp / GAUSSIANS, asset.scene.save_ply)
        write_json(tmp / META, {"version": ASSET_VERSION, "name": asset.name, "box": [list(c) for c in asset.box],
                                "meta": asset.meta})
    return directory


def load_asset(directory: str | Path, dtype: torch.dtype = torch.float32) -> ActorAsset:
    """Read an asset folder written by ``save_asset`` (``parksim asset``).

    Args:
        directory: the asset folder.
        dtype: dtype of the Gaussians.

    Returns:
        The asset.

    Raises:
        AssetError: the folder, ``asset.json`` or ``gaussians.ply`` is missing or unreadable, the version is not
            ``ASSET_VERSION``, or the name, box or Gaussians are invalid; one line naming the file.
    """
    directory = Path(directory)
    if not directory.is_dir():
        raise AssetError(f"{directory}: actor asset folder not found")
    for name in (META, GAUSSIANS):
        if not (directory / name).is_file():
            raise AssetError(f"{directory}: not an actor asset ({name} is missing)")
    path = directory / META
    try:
        data = json.loads(path.read_text())
    except (OSError, ValueError) as e:
        raise AssetError(f"{path}: unreadable JSON ({' '.join(str(e).split())})") from None
    if not isinstance(data, dict) or data.get("version") != ASSET_VERSION:
        version = data.get("version") if isinstance(data, dict) else None
        raise AssetError(f"{path}: asset version {version!r} is not the supported version {ASSET_VERSION}")
    if not isinstance(data.get("box"), list) or len(data["box"]) != 2 or \
            not all(isinstance(c, list) and len(c) == 3 for c in data["box"]):
        raise AssetError(f"{path}: 'box' must be [[x0, y0, z0], [x1, y1, z1]], got {data.get('box')!r}")
    try:
        scene = GaussianScene.load_ply(directory / GAUSSIANS, dtype=dtype)
    except PLYFormatError as e:
        raise AssetError(str(e)) from None
    meta = data.get("meta", {})
    if not isinstance(meta, dict):
        raise AssetError(f"{path}: 'meta' must be an object, got {type(meta).__name__}")
    try:
        return ActorAsset(data.get("name", ""), scene, (tuple(data["box"][0]), tuple(data["box"][1])), meta)
    except AssetError as e:
        raise AssetError(f"{path}: {e}") from None
