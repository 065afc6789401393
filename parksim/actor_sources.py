"""Where actor assets come from: synth cars and pedestrians baked to Gaussians, crops of a scene, 3DGS PLYs.

Baking samples the surfaces of the same boxes the synthetic garage ray-casts (``parksim.synth.cars`` and the
classic car of scene1-4) with flat Gaussian discs, coloured by each box's albedo lit as the garage shader lights a
box (tops fully, sides less; no light map, so an asset looks the same wherever it is placed), SH degree 0. A
pedestrian is a few boxes (legs, torso, arms, head) baked the same way. Every asset is in its own frame: x forward,
y left, z up, the origin on the floor under its centre (``parksim.actor_asset``).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from .actor_asset import ActorAsset
from .gaussians import SH_C0, GaussianScene
from .geometry import pose_from_xy_yaw, quaternion_from_rotation
from .ply_3dgs import T_parksim_ply, proper_similarity, read_ply, transform_scene
from .synth import cars
from .synth.garage import Box
from .synth.layout import _car_boxes
from .synth.points import _box_samples
from .synth.raycast import BoxSet
from .synth.shading import to_srgb

__all__ = ["BAKE_KINDS", "CropBox", "bake", "bake_boxes", "pedestrian_boxes", "crop_asset", "asset_from_ply",
           "DEFAULT_GAUSSIANS", "CAR_GAUSSIANS", "PLY_BOX_PERCENTILES"]

BAKE_KINDS = ("car", "sedan", "hatchback", "suv", "van", "pickup", "pedestrian")
"""``bake``'s kinds: the classic car of scene1-4, the body types of ``parksim.synth.cars``, a pedestrian."""
DEFAULT_GAUSSIANS = {"pedestrian": 600}
"""Gaussians of a baked asset when none is asked for, per kind (cars: ``CAR_GAUSSIANS``): about 10 cm apart on a
car's ~20 m^2 of visible faces, 6 cm on a pedestrian's ~2.2 m^2."""
CAR_GAUSSIANS = 2000
_SIGMA_PER_SPACING = 1.0
"""Disc standard deviation over the mean sample spacing: random samples this wide leave no see-through holes."""
_THICKNESS = 0.1
"""Disc thickness (standard deviation along the face normal) over its width."""
_OPACITY_LOGIT = 3.0
"""Baked discs' opacity logit (opacity 0.95)."""
_SIDE_LIGHT = 0.65
"""Light on a box's sides relative to its top (the garage shader gives sides 0.5-0.8 by height)."""
PLY_BOX_PERCENTILES = (0.5, 99.5)
"""Percentiles of a PLY asset's means that bound its box (a few floaters do not widen it)."""
_RGB = tuple[float, float, float]
_SKIN: tuple[_RGB, ...] = ((0.80, 0.62, 0.50), (0.55, 0.38, 0.28), (0.35, 0.24, 0.18))
_CLOTHES: tuple[_RGB, ...] = ((0.12, 0.14, 0.22), (0.20, 0.20, 0.20), (0.30, 0.22, 0.14), (0.55, 0.10, 0.10),
                              (0.15, 0.35, 0.55), (0.75, 0.72, 0.65), (0.20, 0.40, 0.20))


def pedestrian_boxes(seed: int = 0) -> list[Box]:
    """A standing person facing +x, about 1.75 m tall, as boxes: legs, torso, arms, head (colours by ``seed``).

    Args:
        seed: picks the skin tone, shirt and trousers.

    Returns:
        The boxes in the asset frame (centred on the origin, standing on z = 0).
    """
    rng = np.random.default_rng(seed)
    skin, shirt, trousers = (palette[int(rng.integers(len(palette)))] for palette in (_SKIN, _CLOTHES, _CLOTHES))
    boxes = [Box(0.0, side * 0.1, 0.0, 0.85, 0.16, 0.15, 0.0, "clothes", trousers) for side in (1, -1)]
    boxes.append(Box(0.0, 0.0, 0.85, 1.45, 0.24, 0.42, 0.0, "clothes", shirt))
    boxes += [Box(0.0, side * 0.27, 0.82, 1.42, 0.11, 0.1, 0.0, "clothes", shirt) for side in (1, -1)]
    boxes.append(Box(0.0, 0.0, 1.45, 1.52, 0.1, 0.1, 0.0, "skin", skin))
    boxes.append(Box(0.01, 0.0, 1.52, 1.75, 0.21, 0.18, 0.0, "skin", skin))
    return boxes


def _kind_boxes(kind: str, seed: int, color: Sequence[float] | None) -> list[Box]:
    """The boxes of a ``BAKE_KINDS`` kind in its own frame; a car's colour from ``color`` or ``cars.PALETTE``."""
    if kind == "pedestrian":
        return pedestrian_boxes(seed)
    rng = np.random.default_rng(seed)
    r, g, b = (float(v) for v in (color if color is not None else cars.PALETTE[rng.integers(len(cars.PALETTE))]))
    if kind == "car":
        return _car_boxes(0.0, 0.0, 0.0, (r, g, b))
    return cars.car_boxes(cars.random_shape(rng, kind), 0.0, 0.0, 0.0, (r, g, b))


def _extent(boxes: Sequence[Box]) -> tuple[tuple[float, float, float], tuple[float, float, float]]:
    """The axis-aligned box around every box's corners (x, y) and z range."""
    xy = np.concatenate([b.corners_xy() for b in boxes])
    lo = (float(xy[:, 0].min()), float(xy[:, 1].min()), min(b.z0 for b in boxes))
    hi = (float(xy[:, 0].max()), float(xy[:, 1].max()), max(b.z1 for b in boxes))
    return lo, hi


_FACE_NORMALS = np.array([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1]], np.float64)
"""Outward normals of the faces ``_box_samples`` draws on (0..4: +-x, +-y, +z), in the box's frame."""
_COVER_PROBE = 1e-4
"""How far off its face a sample is moved (m) to ask whether another box covers it there."""
_MAX_DRAWS = 8
"""Rounds of drawing twice as many samples before a set of boxes counts as covering itself entirely."""


def _yawed(solid: BoxSet, index: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Vectors ``v`` ``(N, 3)`` in their boxes' frames (box ``index``), turned by each box's yaw into the asset's."""
    c, s = solid.yaw_cs[index, 0:1], solid.yaw_cs[index, 1:2]
    return np.concatenate([c * v[:, :1] - s * v[:, 1:2], s * v[:, :1] + c * v[:, 1:2], v[:, 2:]], axis=1)


def _covered(solid: BoxSet, points: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """Samples inside another box once moved ``_COVER_PROBE`` outward (a body's top under its cabin, a wheel's top in
    the body); faces that only touch, coplanar and facing the same way, both stay."""
    probe = points + _COVER_PROBE * normals
    rel = probe[:, None, :] - solid.centres[None]
    c, s = solid.yaw_cs[None, :, 0], solid.yaw_cs[None, :, 1]
    local = np.stack([c * rel[..., 0] + s * rel[..., 1], -s * rel[..., 0] + c * rel[..., 1], rel[..., 2]], -1)
    return (np.abs(local) < solid.halves[None]).all(-1).any(-1)


def _visible_samples(solid: BoxSet, count: int, rng: np.random.Generator
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    """``count`` area-weighted samples on the boxes' sides and tops that no box covers: points, box, face, and the
    visible area (m^2) they share."""
    area = float(sum(8 * h[2] * (h[0] + h[1]) + 4 * h[0] * h[1] for h in solid.halves))   # four sides and the top
    drawn = count
    for _ in range(_MAX_DRAWS):
        drawn *= 2
        points, index, face = _box_samples(solid, np.ones(len(solid.centres), bool), drawn, rng)
        visible = np.flatnonzero(~_covered(solid, points, _yawed(solid, index, _FACE_NORMALS[face])))
        if len(visible) >= count:
            keep = visible[:count]
            return points[keep], index[keep], face[keep], area * len(visible) / drawn
    raise ValueError(f"bake: the boxes cover almost all of their own faces ({len(visible)} of {drawn} samples seen)")


def bake_boxes(boxes: Sequence[Box], name: str, count: int, seed: int = 0,
               meta: Mapping[str, Any] | None = None) -> ActorAsset:
    """Boxes (in the asset frame) as an asset: ``count`` flat discs on the parts of their sides and tops that no other
    box covers, area-weighted.

    Args:
        boxes: ``parksim.synth.garage.Box`` es standing on the floor of the asset frame.
        name: the asset's name.
        count: Gaussians to sample (>= 1).
        seed: seed of the samples.
        meta: provenance for ``asset.json``.

    Returns:
        The asset: SH degree 0, float32, box the boxes' extent; discs as wide as the samples' mean spacing.

    Raises:
        ValueError: no box, ``count`` < 1, or boxes that cover almost all of their own faces.
    """
    if not boxes or count < 1:
        raise ValueError(f"bake: needs at least one box and one Gaussian, got {len(boxes)} box(es), count {count}")
    rng = np.random.default_rng(seed)
    solid = BoxSet.from_boxes(boxes)
    points, index, face, area = _visible_samples(solid, count, rng)
    sigma = _SIGMA_PER_SPACING * math.sqrt(area / count)
    # each disc's frame: a tangent (x along the box for its top, up for a side), the second tangent, the normal
    normals = _yawed(solid, index, _FACE_NORMALS[face])
    tangents = _yawed(solid, index, np.where(face[:, None] == 4, [[1.0, 0.0, 0.0]], [[0.0, 0.0, 1.0]]))
    frames = np.stack([tangents, np.cross(normals, tangents), normals], axis=2)
    colors = np.array([b.color for b in boxes], np.float64)[index]
    lit = to_srgb(colors * np.where(face == 4, 1.0, _SIDE_LIGHT)[:, None])
    scene = GaussianScene(
        torch.from_numpy(points), quaternion_from_rotation(torch.from_numpy(frames)),
        torch.tensor([math.log(sigma)] * 2 + [math.log(_THICKNESS * sigma)], dtype=torch.float64).expand(count, 3)
        .clone(), torch.full((count,), _OPACITY_LOGIT, dtype=torch.float64),
        torch.from_numpy((lit - 0.5) / SH_C0)[:, None, :], sh_degree=0).to(torch.float32)
    return ActorAsset(name, scene.spatially_sorted(), _extent(boxes), dict(meta or {}))


def bake(kind: str, count: int | None = None, seed: int = 0, color: Sequence[float] | None = None) -> ActorAsset:
    """A synth garage car or a pedestrian baked to Gaussians (``parksim asset bake``).

    Args:
        kind: one of ``BAKE_KINDS``: ``car`` (the classic car of scene1-4), a ``parksim.synth.cars`` body type
            (its proportions drawn by ``seed``), or ``pedestrian``.
        count: Gaussians (None: ``DEFAULT_GAUSSIANS``).
        seed: seed of the proportions, colours and samples.
        color: a car's body colour, linear RGB in [0, 1] (None: drawn from ``cars.PALETTE``).

    Returns:
        The asset named ``kind``; its box is the union of the boxes' extents.

    Raises:
        ValueError: an unknown kind, ``count`` < 1, or a colour that is not three numbers in [0, 1].
    """
    if kind not in BAKE_KINDS:
        raise ValueError(f"bake: unknown kind {kind!r}; one of {', '.join(BAKE_KINDS)}")
    if color is not None and (len(color) != 3 or not all(0.0 <= float(v) <= 1.0 for v in color)):
        raise ValueError(f"bake: color must be three numbers in [0, 1], got {list(color)}")
    n = DEFAULT_GAUSSIANS.get(kind, CAR_GAUSSIANS) if count is None else count
    meta = {"source": f"synth {kind} baked to Gaussians", "seed": seed,
            "color": None if color is None else [float(v) for v in color]}
    return bake_boxes(_kind_boxes(kind, seed, color), kind, n, seed, meta)


@dataclass(frozen=True)
class CropBox:
    """An oriented box in the world, whose frame becomes a cropped asset's.

    Centre ``(x, y)``, heading ``yaw``, ``length`` along it, ``width`` across, and the height range ``[z0, z1]``; its
    frame has the origin on the floor under the centre and x along ``yaw``.

    Raises:
        ValueError: a value that is not finite, a non-positive length or width, or ``z0 >= z1``.
    """

    x: float
    y: float
    yaw: float
    length: float
    width: float
    z0: float
    z1: float

    def __post_init__(self) -> None:
        """Check the values (one line)."""
        values = [self.x, self.y, self.yaw, self.length, self.width, self.z0, self.z1]
        if not all(math.isfinite(v) for v in values) or self.length <= 0 or self.width <= 0 or self.z0 >= self.z1:
            raise ValueError(f"crop box (x, y, yaw, length, width, z0, z1) needs finite values, a positive length "
                             f"and width and z0 < z1, got {values}")

    @classmethod
    def from_obstacle(cls, obstacle: Mapping[str, Any]) -> CropBox:
        """A ``map.json`` obstacle's box (``center``, ``size``, ``yaw``, ``z``; a parked car, say).

        Args:
            obstacle: the obstacle's dict.

        Returns:
            The box.

        Raises:
            ValueError: the obstacle lacks one of the fields, or holds a bad value.
        """
        try:
            (x, y), (length, width), (z0, z1) = obstacle["center"], obstacle["size"], obstacle["z"]
            return cls(float(x), float(y), float(obstacle["yaw"]), float(length), float(width), float(z0), float(z1))
        except (KeyError, TypeError, ValueError) as e:
            raise ValueError(f"obstacle {dict(obstacle)}: not a box with center, size, yaw and z "
                             f"({type(e).__name__}: {e})") from None

    @property
    def pose(self) -> tuple[float, float, float]:
        """``(x, y, yaw)``: where the cropped asset goes to stand where it was cut from."""
        return (self.x, self.y, self.yaw)

    def contains(self, means: torch.Tensor) -> torch.Tensor:
        """Which points lie inside (boundary included).

        Args:
            means: ``(N, 3)`` world points.

        Returns:
            ``(N,)`` bool.
        """
        p = means.detach().to(torch.float64)
        dx, dy = p[:, 0] - self.x, p[:, 1] - self.y
        c, s = math.cos(self.yaw), math.sin(self.yaw)
        along, across = c * dx + s * dy, -s * dx + c * dy
        return ((along.abs() <= self.length / 2) & (across.abs() <= self.width / 2)
                & (p[:, 2] >= self.z0) & (p[:, 2] <= self.z1))


def crop_asset(scene: GaussianScene, box: CropBox, name: str) -> ActorAsset:
    """The Gaussians whose means lie in ``box``, as an asset in the box's frame (``parksim asset crop``).

    Placed at ``box.pose`` the asset stands where it was cut from; ``scene.subset(~box.contains(scene.means))``
    is the rest of the scene.

    Args:
        scene: the Gaussians to cut from (a bundle's scene).
        box: the box, in the scene's world.
        name: the asset's name.

    Returns:
        The asset (the scene's SH degree and dtype; box ``(-length/2, -width/2, z0)`` to ``(length/2, width/2,
        z1)``).

    Raises:
        ValueError: the box holds no Gaussian.
    """
    inside = box.contains(scene.means)
    if not bool(inside.any()):
        raise ValueError(f"crop box {box.pose + (box.length, box.width, box.z0, box.z1)} holds none of the scene's "
                         f"{len(scene)} Gaussians")
    T_box_world = np.linalg.inv(pose_from_xy_yaw(box.x, box.y, box.yaw).numpy())
    local = transform_scene(scene.subset(inside.to(scene.means.device)), T_box_world)
    meta = {"source": "cropped from a scene", "crop_box": {"x": box.x, "y": box.y, "yaw": box.yaw,
                                                           "length": box.length, "width": box.width,
                                                           "z": [box.z0, box.z1]}}
    return ActorAsset(name, local, ((-box.length / 2, -box.width / 2, box.z0), (box.length / 2, box.width / 2, box.z1)),
                      meta)


def asset_from_ply(ply: str | Path, name: str | None = None, frame: str = "parksim",
                   transform: np.ndarray | None = None) -> ActorAsset:
    """A third-party INRIA 3DGS PLY (SH degree 0-3) as an asset (``parksim asset from-ply``).

    Args:
        ply: the PLY file.
        name: the asset's name (None: the file's stem).
        frame: the PLY's axis convention, a key of ``parksim.ply_3dgs.FRAMES``.
        transform: 4x4 similarity applied after ``frame`` (None: identity), to put the object's floor point at the
            origin, facing +x.

    Returns:
        The asset, float32; its box spans the ``PLY_BOX_PERCENTILES`` of the means on each axis.

    Raises:
        ValueError: an unknown frame, a transform that is not a similarity.
        parksim.gaussians.PLYFormatError: a missing property, a non-finite value, no Gaussians.
    """
    ply = Path(ply)
    correction = 0.0
    if transform is not None:
        transform, correction = proper_similarity(transform)
    T = T_parksim_ply(frame, transform)
    scene = read_ply(ply, T)
    lo, hi = np.percentile(scene.means.double().numpy(), PLY_BOX_PERCENTILES, axis=0)
    hi = np.maximum(hi, lo + 1e-3)   # a flat or one-point object still gets a box
    meta = {"source": f"3DGS PLY {ply.resolve()}", "frame": frame, "T_asset_ply": T.tolist(),
            "transform_correction": correction}
    (x0, y0, z0), (x1, y1, z1) = lo.tolist(), hi.tolist()
    return ActorAsset(name or ply.stem, scene, ((x0, y0, z0), (x1, y1, z1)), meta)
