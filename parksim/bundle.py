"""Scene bundles: a trained Gaussian scene with everything needed to render and evaluate it.

```
gaussians.ply      the Gaussians (INRIA 3DGS layout)
rig.json           the rig the scene was trained with, BEV spec included (Rig.save)
map.json           the dataset's world slot map and obstacles (optional)
bundle.json        metadata: format version, source dataset, iterations, per-camera response,
                   recorded_path (the dataset's ego path, ``recorded_path()``)
config.yaml        the training config used (optional)
poses.json         the per-frame poses the scene was trained at, refined by pose refinement (optional; the
                   dataset's poses.json schema plus "refined": the frame ids whose poses were fitted)
visibility.npz     per-region visibility written by ``parksim compact`` (optional, named in bundle.json)
metrics.jsonl/png  training metrics (optional)
```
``load(dir)`` reads it back for rendering; ``save`` writes each file atomically.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from .fileio import atomic_write, write_json
from .gaussians import GaussianScene, PLYFormatError
from .rig import BEVSpec, CalibrationError, Rig
from .visibility import VisibilityGrid

__all__ = ["Bundle", "BundleError", "load", "save", "recorded_path", "BUNDLE_VERSION", "RECORDED_PATH_POINTS"]

BUNDLE_VERSION = 1
"""Bumped when the bundle layout changes incompatibly."""

GAUSSIANS, RIG, MAP, META, VISIBILITY = "gaussians.ply", "rig.json", "map.json", "bundle.json", "visibility.npz"
POSES = "poses.json"
RECORDED_PATH_POINTS = 256
"""Most poses ``recorded_path`` keeps: enough to draw and measure the path, small enough for a scene's JSON."""


def recorded_path(poses: np.ndarray, points: int = RECORDED_PATH_POINTS) -> list[list[float]]:
    """The dataset's ego path ``[[x, y, yaw], ...]`` from ``T_world_vehicle`` [N, 4, 4], at most ``points`` of them.

    Evenly spaced frames, first and last kept: where the cameras drove, so viewers can start and stay there.

    Args:
        poses: ``[N, 4, 4]`` ``T_world_vehicle`` per frame (array-like).
        points: most poses to keep.

    Returns:
        ``min(N, points)`` rows ``[x, y, yaw]`` (metres, radians) as plain lists, in frame order.
    """
    poses = np.asarray(poses, dtype=np.float64)
    keep = np.unique(np.linspace(0, len(poses) - 1, min(len(poses), points)).round().astype(np.int64))
    p = poses[keep]
    yaw = np.arctan2(p[:, 1, 0], p[:, 0, 0])
    return np.stack([p[:, 0, 3], p[:, 1, 3], yaw], axis=1).tolist()


class BundleError(ValueError):
    """A bundle folder is missing a file or holds an unreadable one; the message names it."""


@dataclass
class Bundle:
    """A trained scene: Gaussians, the rig (with its BEV spec), the world map, metadata, optional visibility grid.

    ``meta["visibility"]`` names the grid's file and is kept in step with ``visibility`` by ``save``;
    ``poses`` (poses.json) are the refined training poses when pose refinement ran (``rig`` is then refined too).

    Attributes:
        scene: the Gaussians (world frame).
        rig: the cameras and the BEV spec.
        map: world-frame slots, marking points and obstacles (map.json), or None.
        meta: bundle.json without its ``version``.
        visibility: per-region visibility grid, or None.
        poses: poses.json's content, or None.

    Raises:
        BundleError: the scene's shapes or values are invalid (``GaussianScene.validate``).
    """

    scene: GaussianScene
    rig: Rig
    map: dict[str, Any] | None = None
    meta: dict[str, Any] = field(default_factory=dict)
    visibility: VisibilityGrid | None = None
    poses: dict[str, Any] | None = None

    def __post_init__(self) -> None:
        """Validate the scene once, as it is loaded or built."""
        try:
            self.scene.validate()
        except ValueError as e:
            raise BundleError(f"bundle scene: {e}") from None

    @property
    def projection(self) -> str:
        """The projection the Gaussians were trained with, and so must be rendered with: "ut" or "ewa".

        Read from ``run.projection``; bundles from before it: "ut". An EWA-trained scene rendered with UT
        scored 12 dB lower.
        """
        return str(self.meta.get("projection", "ut"))

    @property
    def bev(self) -> BEVSpec:
        """The rig's BEV spec."""
        return self.rig.bev


def save(directory: str | Path, bundle: Bundle) -> Path:
    """Write ``bundle`` into ``directory`` (created if needed); other files there are left alone.

    Args:
        directory: the bundle folder.
        bundle: what to write; ``meta["visibility"]`` is set from ``bundle.visibility``.

    Returns:
        ``directory`` as a Path.
    """
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    atomic_write(directory / GAUSSIANS, bundle.scene.save_ply)
    atomic_write(directory / RIG, bundle.rig.save)
    if bundle.map is not None:
        write_json(directory / MAP, bundle.map)
    if bundle.poses is not None:
        write_json(directory / POSES, bundle.poses)
    meta = {k: v for k, v in bundle.meta.items() if k != "visibility"}
    if bundle.visibility is not None:
        atomic_write(directory / VISIBILITY, bundle.visibility.save)
        meta["visibility"] = VISIBILITY
    write_json(directory / META, {"version": BUNDLE_VERSION, **meta})
    return directory


def _read_json(path: Path) -> Any:
    """The parsed JSON file; BundleError if it cannot be read or parsed."""
    try:
        return json.loads(path.read_text())
    except (OSError, json.JSONDecodeError, UnicodeDecodeError) as e:
        raise BundleError(f"{path}: unreadable JSON ({e})") from None


def _inside(directory: Path, name: str, key: str) -> Path:
    """``directory / name``, refused (naming ``key``) when it resolves outside ``directory``, links included."""
    path = directory / name
    if not path.resolve().is_relative_to(directory.resolve()):
        raise BundleError(f"{directory}: {key} {name!r} points outside the bundle folder")
    return path


def load(directory: str | Path) -> Bundle:
    """Read a bundle folder written by ``save`` (or by ``parksim reconstruct``); every file must lie inside it.

    Args:
        directory: the bundle folder.

    Returns:
        The bundle, its scene validated.

    Raises:
        BundleError: the folder or a required file (gaussians.ply, rig.json, bundle.json) is missing, the version
            is not ``BUNDLE_VERSION``, a file is unreadable or points outside the folder, or the visibility grid
            does not fit the scene.
    """
    directory = Path(directory)
    if not directory.is_dir():
        raise BundleError(f"{directory}: bundle folder not found")
    for name in (GAUSSIANS, RIG, META):
        if not _inside(directory, name, "file").is_file():
            raise BundleError(f"{directory}: not a scene bundle ({name} is missing)")
    meta = _read_json(directory / META)
    if not isinstance(meta, dict) or meta.get("version") != BUNDLE_VERSION:
        raise BundleError(f"{directory / META}: bundle version {meta.get('version') if isinstance(meta, dict) else '?'}"
                          f" is not the supported version {BUNDLE_VERSION}")
    try:
        scene = GaussianScene.load_ply(directory / GAUSSIANS)
        rig = Rig.load(directory / RIG)
    except (PLYFormatError, CalibrationError) as e:
        raise BundleError(str(e)) from None
    world_map = _read_json(directory / MAP) if _inside(directory, MAP, "file").is_file() else None
    poses = _read_json(directory / POSES) if _inside(directory, POSES, "file").is_file() else None
    meta.pop("version")
    return Bundle(scene, rig, world_map, meta, _load_visibility(directory, meta.get("visibility"), len(scene)), poses)


def _load_visibility(directory: Path, name: Any, n_gaussians: int) -> VisibilityGrid | None:
    """The grid named in bundle.json (None when it names none), checked against the scene's Gaussian count."""
    if name is None:
        return None
    path = _inside(directory, str(name), f"{META} key 'visibility'")
    if not path.is_file():
        raise BundleError(f"{directory}: bundle.json names a visibility grid {name!r} that is missing")
    try:
        grid = VisibilityGrid.load(path)
        grid.check(n_gaussians)
    except ValueError as e:
        raise BundleError(str(e)) from None
    return grid
