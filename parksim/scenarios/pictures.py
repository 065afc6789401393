"""Pictures of scenarios drawn from the scene itself, not from a schematic.

``bev_mosaic`` stitches the garage floor into one top view from the simulator's rendered BEVs, ``thumbnail`` shows
a scenario's first BEV frame with its slot and ego outlined, and ``plot_episode`` draws an episode's trajectories
over the top view. The top view is what the scene's Gaussians look like from above (IPM of the rendered fisheye
views): ``parksim scenarios make`` shows each scenario with it and ``parksim scenarios run`` plots each episode over
it. World axes: x to the right, y up; images are RGB ``uint8``.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from ..fileio import atomic_write
from ..vehicle import VehicleParams
from .score import EpisodeLog, Scorecard
from .shapes import box_polygon

if TYPE_CHECKING:
    from ..rig import BEVSpec
    from ..sim import LocalSim
    from .episode import Episode

__all__ = ["BevMap", "bev_mosaic", "thumbnail", "plot_episode", "summary", "MOSAIC_STEP", "RENDERS_PER_BATCH",
           "SLOT_RGB", "EGO_RGB"]

MOSAIC_STEP = 0.6
"""Spacing of the mosaic's render poses along x, as a fraction of the BEV's extent: neighbours overlap by 40 %."""
RENDERS_PER_BATCH = 8
"""Mosaic poses rendered together (``LocalSim.render_batch``): bounds the memory of one batch on a large scene."""
SLOT_RGB = (40, 220, 60)
"""The target slot's outline (green, as ``ParkingEnv.render``)."""
EGO_RGB = (255, 140, 0)
"""The ego's footprint outline (orange, as ``ParkingEnv.render``)."""
_FORWARD, _REVERSE = (0.1, 0.5, 1.0), (0.9, 0.1, 0.8)
"""``plot_episode``'s path colours (matplotlib RGB) where the ego drives forward and where it reverses."""
_FEATHER = 1.0
"""Metres over which a BEV's weight fades out towards its masked ego box in ``bev_mosaic``."""
_CROP_MARGIN = 3.0
"""Metres of floor shown around an episode's footprints in ``plot_episode``."""


@dataclass(frozen=True)
class BevMap:
    """A top-view image of the garage floor in world metres.

    Pixel ``(row, col)`` shows the world point ``x = x0 + (col + 0.5) * m_per_px``,
    ``y = y1 - (row + 0.5) * m_per_px``: x to the right, y up, as ``matplotlib``'s ``imshow(extent=...)`` draws it.

    Attributes:
        image: uint8 ``[H, W, 3]`` RGB, black where no view saw the floor.
        extent: ``(x0, x1, y0, y1)`` world metres of the image's outer edges.
        seen: bool ``[H, W]``, the pixels some rendered BEV covered.
    """

    image: np.ndarray
    extent: tuple[float, float, float, float]
    seen: np.ndarray

    @property
    def m_per_px(self) -> float:
        """Metres per pixel (square pixels)."""
        return (self.extent[1] - self.extent[0]) / self.image.shape[1]

    def crop(self, x0: float, x1: float, y0: float, y1: float) -> BevMap:
        """The part of the map over a world box, on whole pixels (the box's pixels that the map holds).

        Args:
            x0: box's left edge (m).
            x1: box's right edge (m).
            y0: box's bottom edge (m).
            y1: box's top edge (m).

        Returns:
            The map's pixels that overlap the box, with their extent.

        Raises:
            ValueError: the box does not overlap the map.
        """
        m, (ex0, _, _, ey1) = self.m_per_px, self.extent
        h, w = self.seen.shape
        c0, c1 = max(math.floor((x0 - ex0) / m), 0), min(math.ceil((x1 - ex0) / m), w)
        r0, r1 = max(math.floor((ey1 - y1) / m), 0), min(math.ceil((ey1 - y0) / m), h)
        if c0 >= c1 or r0 >= r1:
            raise ValueError(f"box x [{x0:g}, {x1:g}] y [{y0:g}, {y1:g}] lies outside the BEV map {self.extent}")
        return BevMap(self.image[r0:r1, c0:c1], (ex0 + c0 * m, ex0 + c1 * m, ey1 - r1 * m, ey1 - r0 * m),
                      self.seen[r0:r1, c0:c1])


def _garage(world_map: Mapping[str, Any]) -> tuple[float, float, float, float]:
    """The map's garage floor ``(x0, x1, y0, y1)``; ValueError for a map without a proper one."""
    try:
        g = world_map["garage"]
        x0, x1, y0, y1 = (float(v) for v in (*g["x"], *g["y"]))
    except (KeyError, TypeError, ValueError):
        raise ValueError("the world map needs a garage with x and y spans ([low, high] metres each)") from None
    if not all(map(math.isfinite, (x0, x1, y0, y1))) or x0 >= x1 or y0 >= y1:
        raise ValueError(f"the world map's garage x [{x0:g}, {x1:g}] y [{y0:g}, {y1:g}] is empty or not finite")
    return x0, x1, y0, y1


def _mosaic_centres(garage: tuple[float, float, float, float], spec: BEVSpec) -> np.ndarray:
    """Where ``bev_mosaic`` centres its BEVs.

    Rows of centres ``MOSAIC_STEP`` BEV lengths apart along x, each row shifted by half a step against the last,
    the rows close enough that the next row sees the floor under a pose's masked ego box (two rows at least when
    the spec masks one; the row step never drops below a tenth of the BEV, whatever the box).

    Args:
        garage: the floor ``(x0, x1, y0, y1)`` (m).
        spec: the BEV.

    Returns:
        ``[P, 2]`` world xy of the BEV centres (m).
    """
    x0, x1, y0, y1 = garage
    length, breadth = spec.height * spec.m_per_px, spec.width * spec.m_per_px     # along x, along y (yaw 0)
    hy = 0.0 if spec.ego_box is None else max(abs(spec.ego_box[2] - spec.center_y),
                                              abs(spec.ego_box[3] - spec.center_y))
    step_y = max(min(MOSAIC_STEP * breadth, 0.5 * breadth - hy), 0.1 * breadth)
    nx = max(math.ceil((x1 - x0) / (MOSAIC_STEP * length)), 1)
    ny = max(math.ceil((y1 - y0) / step_y), 1 if spec.ego_box is None else 2)
    sx, sy = (x1 - x0) / nx, (y1 - y0) / ny
    centres = [(x0 + (i + 0.5 * (1 - j % 2)) * sx, y0 + (j + 0.5) * sy)
               for j in range(ny) for i in range(nx + j % 2)]
    return np.array(centres)


def _centre_weight(mask: np.ndarray, feather_px: float) -> np.ndarray:
    """A BEV's blend weight in ``bev_mosaic``.

    A tent squared, 1 at the centre and 0 at the edges, so each view counts most where its IPM is sharpest (near
    the car), faded to 0 over ``feather_px`` towards the IPM's unseen pixels (the ego box), so that the views that
    fill those in blend in without a seam.

    Args:
        mask: ``[H, W]`` bool, the BEV pixels the IPM sees (``IPM.mask``).
        feather_px: width of the fade (px).

    Returns:
        ``[H, W]`` float32 weights in [0, 1].
    """
    import cv2

    h, w = mask.shape
    tent_v = 1.0 - np.abs(np.linspace(-1.0, 1.0, h + 2)[1:-1])
    tent_u = 1.0 - np.abs(np.linspace(-1.0, 1.0, w + 2)[1:-1])
    inside = np.clip(cv2.distanceTransform(mask.astype(np.uint8), cv2.DIST_L2, 3) / feather_px, 0.0, 1.0)
    return (np.outer(tent_v, tent_u) ** 2 * inside * inside * (3 - 2 * inside)).astype(np.float32)


def bev_mosaic(sim: LocalSim, world_map: Mapping[str, Any], m_per_px: float | None = None,
               scale: float = 0.5) -> BevMap:
    """The garage floor as one top view, stitched from the simulator's rendered BEVs.

    The simulator renders its BEV (IPM of all fisheye views) at a grid of ego poses (yaw 0) over the garage:
    ``MOSAIC_STEP`` (0.6) BEV lengths apart along x, rows shifted by half a step and close enough that a
    neighbouring row sees the floor under each pose's masked ego box. Every mosaic pixel blends the BEVs that
    cover it, each weighted by its IPM mask times a tent that is largest at the BEV's centre, so each view
    contributes mainly its central part.

    Cost: for a garage of ``Lx x Ly`` m and a BEV of ``Bx x By`` m, ``ny = ceil(Ly / min(0.6 By, By / 2 - h))``
    rows (``h``: the ego box's half width) of ``nx`` or ``nx + 1`` renders, ``nx = ceil(Lx / (0.6 Bx))``; each
    render draws every camera at ``scale`` and its IPM (``RENDERS_PER_BATCH`` at a time), then one resampling
    onto the mosaic. scene1 (48 m x 17.4 m, 10 m BEV): 42 renders; on two CPU cores about 2 s for 300 Gaussians
    and a 64 px BEV, 13 s for 100 000 Gaussians and a 600 px BEV.

    Args:
        sim: the scene's simulator (its rig's BEV spec sets the views; its camera response applies).
        world_map: the scene's map; its ``garage`` ``x`` and ``y`` spans (m) are the mosaic's extent.
        m_per_px: the mosaic's resolution (None: the BEV's ``m_per_px``).
        scale: fisheye render size relative to the rig's cameras.

    Returns:
        The map: uint8 ``[ceil(Ly / m_per_px), ceil(Lx / m_per_px), 3]`` from the garage's lower-left corner.

    Raises:
        ValueError: a map without a garage, or ``m_per_px`` not a positive finite number.
        parksim.frames.RequestError: a bad ``scale`` (``LocalSim.check``).
    """
    import cv2

    from ..render import bev_ipm

    garage = _garage(world_map)
    spec = sim.bundle.rig.bev
    m = spec.m_per_px if m_per_px is None else float(m_per_px)
    if not (math.isfinite(m) and m > 0):
        raise ValueError(f"m_per_px must be a positive finite number, got {m_per_px}")
    sim.check([], scale)
    x0, x1, y0, y1 = garage
    w, h = math.ceil((x1 - x0) / m - 1e-9), math.ceil((y1 - y0) / m - 1e-9)
    ys, xs = y0 + h * m - (np.arange(h) + 0.5) * m, x0 + (np.arange(w) + 0.5) * m     # pixel centres
    weight = _centre_weight(bev_ipm(sim.bundle.rig, scale).mask.cpu().numpy(), _FEATHER / spec.m_per_px)
    colour_sum = np.zeros((h, w, 3), np.float32)
    weight_sum = np.zeros((h, w), np.float32)
    centres = _mosaic_centres(garage, spec)
    half_x, half_y = spec.height * spec.m_per_px / 2, spec.width * spec.m_per_px / 2
    for first in range(0, len(centres), RENDERS_PER_BATCH):
        batch = centres[first:first + RENDERS_PER_BATCH]
        poses = [(cx - spec.center_x, cy - spec.center_y, 0.0) for cx, cy in batch]
        for (cx, cy), frame in zip(batch, sim.render_batch(poses, cameras=[], bev=True, scale=scale)):
            cols = np.flatnonzero(np.abs(xs - cx) < half_x)
            rows = np.flatnonzero(np.abs(ys - cy) < half_y)
            # spec.ground_to_pixel at yaw 0: BEV column from world y, BEV row from world x
            u = ((spec.width - 1) / 2 - (ys[rows] - cy) / spec.m_per_px).astype(np.float32)
            v = ((spec.height - 1) / 2 - (xs[cols] - cx) / spec.m_per_px).astype(np.float32)
            map_v, map_u = np.meshgrid(v, u)        # [rows, cols]: BEV row per mosaic column, column per row
            window = np.s_[rows[0]:rows[-1] + 1, cols[0]:cols[-1] + 1]
            # weighted colours resampled as such: the masked (black) pixels, of weight 0, add nothing
            colour_sum[window] += cv2.remap(weight[..., None] * frame.bev, map_u, map_v, cv2.INTER_LINEAR,
                                            borderMode=cv2.BORDER_CONSTANT, borderValue=0)
            weight_sum[window] += cv2.remap(weight, map_u, map_v, cv2.INTER_LINEAR,
                                            borderMode=cv2.BORDER_CONSTANT, borderValue=0)
    seen = weight_sum > 0
    image = np.zeros((h, w, 3), np.uint8)
    image[seen] = np.clip(np.round(colour_sum[seen] / weight_sum[seen, None]), 0, 255).astype(np.uint8)
    return BevMap(image, (x0, x0 + w * m, y0, y0 + h * m), seen)


def _to_bev_px(points: np.ndarray, pose: tuple[float, float, float], spec: BEVSpec) -> np.ndarray:
    """World ``[..., 2]`` points -> the BEV's pixels ``[..., 2]`` (column, row) with the ego at ``pose``."""
    import torch

    x, y, yaw = pose
    c, s = math.cos(yaw), math.sin(yaw)
    d = np.asarray(points, np.float64) - (x, y)
    local = np.stack([c * d[..., 0] + s * d[..., 1], -s * d[..., 0] + c * d[..., 1]], -1)
    return spec.ground_to_pixel(torch.from_numpy(local)).numpy()


def thumbnail(episode: Episode, size: int = 256) -> np.ndarray:
    """A scenario's first frame seen from above, its target slot and the ego outlined.

    The BEV at the start pose with the actors and parked cars drawn in (``Episode.frame``), the target slot
    outlined in green and the ego's footprint in orange. One render of every camera at the episode's ``scale``
    plus the IPM.

    Args:
        episode: an episode at its start (just made, or ``begin``), with a renderer and ``bev=True``.
        size: the thumbnail's longer side (px); the BEV's aspect is kept.

    Returns:
        uint8 ``[size, size, 3]`` RGB for a square BEV.

    Raises:
        ValueError: an episode without a renderer or the BEV, one past its start, or ``size`` below 8.
    """
    import cv2

    if episode.renderer is None or not episode.bev:
        raise ValueError(f"thumbnail of scenario {episode.scenario.name!r} needs an Episode with a renderer "
                         "and bev=True")
    if episode.t > 0:
        raise ValueError(f"thumbnail of scenario {episode.scenario.name!r} needs the episode at its start "
                         f"(it is at t = {episode.t:g} s): call begin() first")
    if size < 8:
        raise ValueError(f"thumbnail size must be at least 8 px, got {size}")
    frame = episode.frame()
    assert frame is not None and frame.bev is not None     # a renderer and bev=True render the BEV
    spec = episode.renderer.bundle.rig.bev
    f = size / max(spec.width, spec.height)
    image = cv2.resize(frame.bev, (round(spec.width * f), round(spec.height * f)), interpolation=cv2.INTER_AREA)
    pose = episode.state.pose
    thick = max(1, size // 128)
    for corners, colour in ((episode.slot["corners"], SLOT_RGB),
                            (box_polygon(pose, episode.vehicle.extent), EGO_RGB)):
        px = (_to_bev_px(np.asarray(corners, np.float64), pose, spec) + 0.5) * f - 0.5   # pixel centres rescaled
        cv2.polylines(image, [np.round(px * 16).astype(np.int32)], True, colour, thick, cv2.LINE_AA, shift=4)
    return image


def summary(card: Scorecard) -> str:
    """One line on an episode: outcome, final errors, collisions, duration.

    Args:
        card: the episode's scorecard.

    Returns:
        E.g. ``success | 0.12 m, 1.5 deg off | no collision | 14.2 s`` or
        ``failure | 3.40 m, 20.1 deg off | 1 actor collision from 6.3 s | 6.3 s``.
    """
    hits = []
    for count, first, kind in ((card.static_collisions, card.first_static_collision, "static"),
                               (card.actor_collisions, card.first_actor_collision, "actor")):
        if count:
            hits.append(f"{count} {kind} collision{'s' * (count > 1)} from {first:.1f} s")
    return (f"{'success' if card.success else 'failure'} | {card.final_distance:.2f} m, "
            f"{card.final_heading_error:.1f} deg off | {', '.join(hits) or 'no collision'} | {card.time:.1f} s")


def _rgb(colour: tuple[int, int, int]) -> tuple[float, float, float]:
    """A uint8 RGB colour as matplotlib's floats."""
    return (colour[0] / 255, colour[1] / 255, colour[2] / 255)


def _episode_box(log: EpisodeLog, vehicle: VehicleParams) -> tuple[float, float, float, float]:
    """The world box ``(x0, x1, y0, y1)`` of everything an episode plot shows, with ``_CROP_MARGIN``."""
    points = np.concatenate([box_polygon(log.poses, vehicle.extent).reshape(-1, 2), log.actors.reshape(-1, 2),
                             log.slot])
    lo, hi = points.min(0) - _CROP_MARGIN, points.max(0) + _CROP_MARGIN
    return float(lo[0]), float(hi[0]), float(lo[1]), float(hi[1])


def plot_episode(log: EpisodeLog, card: Scorecard, bev: BevMap, path: str | Path, title: str,
                 vehicle: VehicleParams = VehicleParams()) -> Path:
    """A PNG of one episode over the top view: where the ego and the actors went.

    Shows the BEV mosaic around the episode (its footprints and the slot plus 3 m), the static obstacles
    (white outlines), the target slot (green), the ego's body-centre path (blue forward, magenta reversing), its
    footprint at the start (dashed) and the end (orange), each actor's track and its footprint at the end (red),
    and ``title`` over ``summary(card)``. 6 x 5 in at 100 dpi (600 x 500 px), drawn with matplotlib's Agg canvas
    (no display), written atomically.

    Args:
        log: the episode (``Episode.log``).
        card: its scorecard (``Episode.result()``).
        bev: the scene's top view (``bev_mosaic``).
        path: the PNG to write (must end in ``.png``); folders are made.
        title: the plot's first title line (e.g. the scenario's name).
        vehicle: the ego (its footprint box).

    Returns:
        ``path``.

    Raises:
        ValueError: ``path`` not a ``.png``, or an episode that lies outside ``bev``.
    """
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.collections import LineCollection
    from matplotlib.figure import Figure
    from matplotlib.lines import Line2D
    from matplotlib.patches import Polygon

    path = Path(path)
    if path.suffix.lower() != ".png":
        raise ValueError(f"plot_episode writes a PNG: {path} must end in .png")
    x0, x1, y0, y1 = _episode_box(log, vehicle)
    part = bev.crop(x0, x1, y0, y1)
    slot, ego = _rgb(SLOT_RGB), _rgb(EGO_RGB)
    fig = Figure(figsize=(6, 5), dpi=100)
    FigureCanvasAgg(fig)
    ax = fig.add_subplot()
    ax.imshow(part.image, extent=part.extent, origin="upper", interpolation="bilinear")
    for corners in log.obstacles:
        ax.add_patch(Polygon(corners, closed=True, fill=False, edgecolor="white", alpha=0.6, linewidth=0.7))
    ax.add_patch(Polygon(log.slot, closed=True, fill=False, edgecolor=slot, linewidth=2))
    heading = np.stack([np.cos(log.poses[:, 2]), np.sin(log.poses[:, 2])], -1)
    centre = log.poses[:, :2] + (vehicle.extent[0] + vehicle.extent[1]) / 2 * heading    # car_centre of each pose
    forward = (np.diff(log.poses[:, :2], axis=0) * heading[:-1]).sum(-1) >= 0
    ax.add_collection(LineCollection(list(np.stack([centre[:-1], centre[1:]], 1)), linewidths=2,
                                     colors=np.where(forward[:, None], _FORWARD, _REVERSE)))
    first, last = box_polygon(log.poses[[0, -1]], vehicle.extent)
    ax.add_patch(Polygon(first, closed=True, fill=False, edgecolor=ego, linewidth=1.2, linestyle="--"))
    ax.add_patch(Polygon(last, closed=True, fill=False, edgecolor=ego, linewidth=2))
    for n in range(log.actors.shape[1]):
        track = log.actors[:, n].mean(1)
        ax.plot(track[:, 0], track[:, 1], color="red", linewidth=1)
        ax.add_patch(Polygon(log.actors[-1, n], closed=True, fill=False, edgecolor="red", linewidth=1.5))
    ax.legend(handles=[Line2D([], [], color=colour, label=label) for colour, label in
                       ((_FORWARD, "forward"), (_REVERSE, "reverse"), (ego, "ego start / end"), ("red", "actors"),
                        (slot, "target slot"))],
              loc="upper left", bbox_to_anchor=(1.02, 1.0), fontsize=7)
    ax.set(xlim=(x0, x1), ylim=(y0, y1), aspect="equal", xlabel="x (m)", ylabel="y (m)")
    ax.set_title(f"{title}\n{summary(card)}", fontsize=9)
    fig.tight_layout()
    atomic_write(path, lambda tmp: fig.savefig(tmp, format="png"))
    fig.clear()
    return path
