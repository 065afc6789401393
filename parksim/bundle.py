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
``load(dir)`` reads it back for rendering, dropping finite but absurd Gaussians (``drop_absurd``); ``save`` writes
each file atomically.
"""

from __future__ import annotations

import json
import logging
import math
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
import torch

from .fileio import atomic_write, write_json
from .gaussians import GaussianScene, PLYFormatError
from .rig import BEVSpec, CalibrationError, Rig
from .visibility import VisibilityGrid

__all__ = ["Bundle", "BundleError", "load", "save", "read_map", "is_bundle", "recorded_path", "garage_box",
           "scene_extent", "absurd_gaussians", "drop_absurd", "BUNDLE_VERSION", "RECORDED_PATH_POINTS",
           "EXTENT_MULTIPLE", "MIN_EXTENT_M", "MAX_OPACITY_LOGIT", "MAX_DROPPED_FRACTION"]

log = logging.getLogger(__name__)

BUNDLE_VERSION = 1
"""Bumped when the bundle layout changes incompatibly."""

GAUSSIANS, RIG, MAP, META, VISIBILITY = "gaussians.ply", "rig.json", "map.json", "bundle.json", "visibility.npz"
POSES = "poses.json"
RECORDED_PATH_POINTS = 256
"""Most poses ``recorded_path`` keeps: enough to draw and measure the path, small enough for a scene's JSON."""
EXTENT_MULTIPLE = 20.0
"""A Gaussian whose mean lies more than this many robust extents ``R`` from the scene's centre, or whose largest
standard deviation exceeds this many ``R``, is absurd (``scene_extent``): no trained garage has either."""
MIN_EXTENT_M = 1.0
"""Smallest robust extent ``R`` (m), so a scene of one point or one plane still has room around it."""
MAX_OPACITY_LOGIT = 100.0
"""Largest |opacity logit|: float32's sigmoid is exactly 1 past 17 and 0 past -104, where its gradient vanishes, so no
optimiser moves a logit beyond it (hand-made scenes use 20-60 for "opaque")."""
MAX_DROPPED_FRACTION = 0.1
"""Most absurd Gaussians (fraction of the scene) ``load`` drops; beyond it the bundle is refused as corrupt."""


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


_REASONS = {"mean": f"mean more than {EXTENT_MULTIPLE:g}x the scene's extent from its centre",
            "scale": f"largest scale above {EXTENT_MULTIPLE:g}x the scene's extent",
            "opacity": f"|opacity logit| above {MAX_OPACITY_LOGIT:g}"}
"""Why ``absurd_gaussians`` flags a Gaussian, in the order it checks (a Gaussian counts under the first only)."""


def garage_box(world_map: dict[str, Any] | None) -> np.ndarray | None:
    """The map's garage as a box: floor ``x`` and ``y`` ranges, ``z`` from 0 to its ``height`` (3 m when unset).

    Args:
        world_map: map.json's content, or None.

    Returns:
        ``[2, 3]`` float64 corners ``(lo, hi)`` (m), or None when there is no map or it has no garage.

    Raises:
        BundleError: the garage lacks an ``x`` or ``y`` range of two numbers, or its height is not a number.
    """
    garage = (world_map or {}).get("garage") if isinstance(world_map, dict) else None
    if not garage:
        return None
    try:
        return np.array([[float(garage["x"][0]), float(garage["y"][0]), 0.0],
                         [float(garage["x"][1]), float(garage["y"][1]), float(garage.get("height", 3.0))]])
    except (KeyError, IndexError, TypeError, ValueError, AttributeError) as e:
        raise BundleError(f"{MAP}: 'garage' needs 'x' and 'y' as [lo, hi] and a numeric 'height' "
                          f"({type(e).__name__}: {e})") from None


def scene_extent(means: np.ndarray, world_map: dict[str, Any] | None = None) -> tuple[np.ndarray, float]:
    """The scene's robust centre and extent, which no minority of outliers can move.

    The centre is the per-axis median of the means; the extent ``R`` is the median of the means' distances
    (largest coordinate difference) from it, at least ``MIN_EXTENT_M`` and, with a garage in the map, at least the
    distance of its farthest corner, so ``EXTENT_MULTIPLE * R`` around the centre always holds the garage. Both
    statistics stay put while fewer than half of the Gaussians are outliers.

    Args:
        means: ``[N, 3]`` Gaussian means (m), N >= 1.
        world_map: map.json's content, or None.

    Returns:
        ``(centre [3], R)`` in metres, float64.
    """
    means = np.asarray(means, dtype=np.float64)
    centre = np.median(means, axis=0)
    extent = max(float(np.median(np.abs(means - centre).max(axis=1))), MIN_EXTENT_M)
    box = garage_box(world_map)
    if box is not None:
        extent = max(extent, float(np.abs(box - centre).max()))
    return centre, extent


def absurd_gaussians(scene: GaussianScene, world_map: dict[str, Any] | None = None) -> dict[str, np.ndarray]:
    """Finite but absurd Gaussians, per reason: far outside the scene, larger than it, or of a meaningless opacity.

    With ``(c, R) = scene_extent(means, world_map)`` a Gaussian is absurd when its mean lies more than
    ``EXTENT_MULTIPLE * R`` from ``c`` in some coordinate ("mean"), else when its largest standard deviation
    exceeds ``EXTENT_MULTIPLE * R`` ("scale"), else when ``|opacity logit| > MAX_OPACITY_LOGIT`` ("opacity").

    Args:
        scene: the Gaussians (any device).
        world_map: map.json's content, or None; its garage widens the extent.

    Returns:
        ``{"mean", "scale", "opacity"}`` to ``[N]`` bool arrays, disjoint (all False for an empty scene).
    """
    n = len(scene)
    if n == 0:
        return {reason: np.zeros(0, dtype=bool) for reason in _REASONS}
    means = scene.means.detach().to("cpu", torch.float64).numpy()
    centre, extent = scene_extent(means, world_map)
    limit = EXTENT_MULTIPLE * extent
    far = np.abs(means - centre).max(axis=1) > limit
    huge = scene.log_scales.detach().to("cpu", torch.float64).numpy().max(axis=1) > math.log(limit)
    opaque = np.abs(scene.opacity_logits.detach().to("cpu", torch.float64).numpy()) > MAX_OPACITY_LOGIT
    return {"mean": far, "scale": huge & ~far, "opacity": opaque & ~far & ~huge}


def drop_absurd(scene: GaussianScene, world_map: dict[str, Any] | None = None, source: str = "scene"
                ) -> tuple[GaussianScene, np.ndarray, dict[str, int]]:
    """``scene`` without its absurd Gaussians (``absurd_gaussians``); a warning line counts them per reason.

    Args:
        scene: the Gaussians.
        world_map: map.json's content, or None.
        source: what the Gaussians came from, for the messages (a file name).

    Returns:
        ``(kept scene, keep [N] bool, {reason: count})``: the scene itself, all True and ``{}`` when none is absurd;
        the kept Gaussians keep their order and values.

    Raises:
        BundleError: every Gaussian is absurd, or more than ``MAX_DROPPED_FRACTION`` of them are.
    """
    absurd = absurd_gaussians(scene, world_map)
    keep = ~np.logical_or.reduce(list(absurd.values()), axis=0)
    counts = {reason: int(mask.sum()) for reason, mask in absurd.items() if mask.any()}
    if not counts:
        return scene, keep, {}
    n, dropped = len(scene), len(scene) - int(keep.sum())
    why = ", ".join(f"{count} with {_REASONS[reason]}" for reason, count in counts.items())
    if dropped == n or dropped > MAX_DROPPED_FRACTION * n:
        verdict = "none is usable" if dropped == n else f"more than {MAX_DROPPED_FRACTION:.0%}"
        raise BundleError(f"{source}: {dropped} of {n} Gaussians are absurd ({why}); {verdict}, so the scene is "
                          f"refused as corrupt")
    log.warning("%s: dropped %d of %d absurd Gaussian(s): %s", source, dropped, n, why)
    return scene.subset(torch.from_numpy(keep).to(scene.means.device)), keep, counts


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
        dropped: absurd Gaussians ``load`` dropped, per reason (``drop_absurd``); empty when none was. Not saved.

    Raises:
        BundleError: the scene's shapes or values are invalid (``GaussianScene.validate``).
    """

    scene: GaussianScene
    rig: Rig
    map: dict[str, Any] | None = None
    meta: dict[str, Any] = field(default_factory=dict)
    visibility: VisibilityGrid | None = None
    poses: dict[str, Any] | None = None
    dropped: dict[str, int] = field(default_factory=dict)

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


def is_bundle(directory: str | Path) -> bool:
    """Whether ``directory`` looks like a scene bundle (it holds ``bundle.json``), without reading it.

    Args:
        directory: a folder.

    Returns:
        True when its ``bundle.json`` exists.
    """
    return (Path(directory) / META).is_file()


def read_map(directory: str | Path) -> dict[str, Any] | None:
    """A bundle's ``map.json`` alone, without loading its Gaussians (what scenario tools need of a scene).

    Args:
        directory: the bundle folder.

    Returns:
        The map, or None when the bundle has none.

    Raises:
        BundleError: the map is unreadable or points outside the folder.
    """
    directory = Path(directory)
    return _read_json(directory / MAP) if _inside(directory, MAP, "file").is_file() else None


def load(directory: str | Path) -> Bundle:
    """Read a bundle folder written by ``save`` (or by ``parksim reconstruct``); every file must lie inside it.

    Args:
        directory: the bundle folder.

    Returns:
        The bundle, its scene validated and without its absurd Gaussians (``drop_absurd``, counted in
        ``dropped``; a visibility grid is renumbered to match).

    Raises:
        BundleError: the folder or a required file (gaussians.ply, rig.json, bundle.json) is missing, the version
            is not ``BUNDLE_VERSION``, a file is unreadable or points outside the folder, the visibility grid
            does not fit the scene, the map's garage is malformed, or every Gaussian or more than
            ``MAX_DROPPED_FRACTION`` of them are absurd.
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
    world_map = read_map(directory)
    poses = _read_json(directory / POSES) if _inside(directory, POSES, "file").is_file() else None
    meta.pop("version")
    grid = _load_visibility(directory, meta.get("visibility"), len(scene))
    scene, keep, dropped = drop_absurd(scene, world_map, str(directory / GAUSSIANS))
    if dropped and grid is not None:
        grid = _renumbered(grid, keep)
    return Bundle(scene, rig, world_map, meta, grid, poses, dropped)


def _renumbered(grid: VisibilityGrid, keep: np.ndarray) -> VisibilityGrid:
    """``grid`` naming only the kept Gaussians, by their index among them (ascending order within a cell holds)."""
    kept = keep[grid.indices]
    cell_of_entry = np.repeat(np.arange(grid.nx * grid.ny), np.diff(grid.offsets))
    counts = np.bincount(cell_of_entry[kept], minlength=grid.nx * grid.ny)
    new_index = np.cumsum(keep) - 1
    return replace(grid, offsets=np.concatenate([[0], np.cumsum(counts)]).astype(np.int64),
                   indices=new_index[grid.indices[kept]].astype(np.int32))


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
