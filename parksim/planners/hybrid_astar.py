"""Hybrid A*: a kinematically feasible path, forward and backward, among footprint obstacles, to one of a few goals.

The search runs over a lattice of ``(x, y, yaw)`` bins, but each node keeps the continuous pose it was reached at
(Dolgov et al., 2008). A node expands by short constant-steering arcs (``HybridAStarConfig.steering`` fractions
of the planning lock, forward and backward); an arc is kept when the vehicle footprint, sampled along it, clears
every obstacle. The cost of a move is its length (reverse weighted), plus a charge per change of direction, per
unit of steering and per change of steering. The heuristic is the larger of two lower bounds of the length still
to drive: the shortest path of a point among the obstacles on a 2D grid (Dijkstra from the goals, cells closer
to an obstacle than the footprint's inscribed radius blocked) and the Reeds-Shepp length ignoring obstacles. Near
a goal, each expansion also tries the Reeds-Shepp paths to it ("analytic expansion"), and the first one that
clears the obstacles ends the search.

Obstacles (``FootprintChecker``) are convex polygons: the map's boxes and any extra polygons, such as the
predicted footprints of other road users, each present in a time window. The plan's clock is distance over
``HybridAStarConfig.speed``. The search is deterministic (ties are broken by insertion order); only the wall-clock
budget can end it at a different node from one run to the next.
"""

from __future__ import annotations

import heapq
import math
import time
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from enum import Enum
from typing import Any

import numpy as np

from ..vehicle import Obstacles, VehicleParams, wrap_angle
from .reeds_shepp import ReedsSheppPath, reeds_shepp_length, reeds_shepp_paths

_OCTILE = 1 / math.cos(math.pi / 8)
"""Most an 8-connected grid path exceeds the straight line between its cells by (a run at 22.5 degrees)."""
_CHUNK = 24
"""Poses per collision test along an analytic path."""

__all__ = ["TimedPolygon", "FootprintChecker", "HybridAStarConfig", "PlanStatus", "PlanResult", "hybrid_astar"]


@dataclass(frozen=True, eq=False)
class TimedPolygon:
    """A convex obstacle present from ``start`` to ``end`` seconds of the plan (an actor's predicted footprint).

    Attributes:
        corners: ``[K, 2]`` world corners in order (either winding), K >= 3.
        start: first second it is there (default: always).
        end: last second it is there (default: always).
    """

    corners: np.ndarray
    start: float = -math.inf
    end: float = math.inf


def _polygon_array(corners: Any) -> np.ndarray:
    """``corners`` as a checked ``[K, 2]`` float64 array."""
    c = np.asarray(corners, np.float64)
    if c.ndim != 2 or c.shape[1] != 2 or c.shape[0] < 3 or not np.isfinite(c).all():
        raise ValueError(f"an obstacle polygon must be K >= 3 finite (x, y) corners, got shape {c.shape}")
    return c


def _padded(polygons: Sequence[np.ndarray]) -> np.ndarray:
    """``[n, K, 2]`` polygons padded to the most corners by repeating their last corner (a zero edge adds no axis)."""
    k = max((len(p) for p in polygons), default=3)
    out = np.zeros((len(polygons), k, 2))
    for i, p in enumerate(polygons):
        out[i, :len(p)] = p
        out[i, len(p):] = p[-1]
    return out


def _normals(polygons: np.ndarray) -> np.ndarray:
    """``[..., K, 2]`` edge normals (not normalised: the separating-axis test needs none; a zero edge gives 0)."""
    edges = np.roll(polygons, -1, axis=-2) - polygons
    return np.stack([-edges[..., 1], edges[..., 0]], -1)


class FootprintChecker:
    """Vectorised separating-axis tests of the vehicle footprint at many poses against convex obstacle polygons.

    Example:
        >>> pillar = Obstacles([{"center": [3.0, 0.0], "size": [1.0, 1.0]}])
        >>> walker = TimedPolygon(np.array([[0.0, 3.0], [1.0, 3.0], [1.0, 4.0], [0.0, 4.0]]), start=5.0, end=8.0)
        >>> checker = FootprintChecker(VehicleParams(), pillar, [walker])
        >>> checker.collides(np.array([[0.0, 0.0, 0.0], [0.0, 3.0, 0.0], [0.0, 3.0, 0.0]]), np.array([0, 0, 6.0]))
        array([ True, False,  True])
    """

    def __init__(self, vehicle: VehicleParams, obstacles: Obstacles | None = None,
                 polygons: Iterable[np.ndarray | TimedPolygon] = (), margin: float = 0.0) -> None:
        """Gather the obstacles.

        Args:
            vehicle: the car whose footprint is tested.
            obstacles: the map's boxes (always present).
            polygons: extra convex polygons, ``[K, 2]`` corners (always present) or ``TimedPolygon``.
            margin: metres added on every side of the footprint.

        Raises:
            ValueError: a polygon is not K >= 3 finite corners, or a time window ends before it starts.
        """
        x0, x1, y0, y1 = vehicle.extent
        self.vehicle, self.margin = vehicle, margin
        self._local = np.array([[x1 + margin, y1 + margin], [x0 - margin, y1 + margin],
                                [x0 - margin, y0 - margin], [x1 + margin, y0 - margin]])
        shapes = list(obstacles.corners()) if obstacles is not None and len(obstacles) else []
        windows = [(-math.inf, math.inf)] * len(shapes)
        for p in polygons:
            timed = p if isinstance(p, TimedPolygon) else TimedPolygon(p)
            if not timed.start <= timed.end:
                raise ValueError(f"an obstacle's time window must not end before it starts, got [{timed.start}, "
                                 f"{timed.end}]")
            shapes.append(_polygon_array(timed.corners))
            windows.append((float(timed.start), float(timed.end)))
        self.polygons = _padded(shapes)                       # (n, K, 2)
        self.windows = np.array(windows, np.float64).reshape(-1, 2)
        self.static = (self.windows[:, 0] == -math.inf) & (self.windows[:, 1] == math.inf)
        self._normals = _normals(self.polygons)
        self._low, self._high = self.polygons.min(axis=1), self.polygons.max(axis=1)      # (n, 2) bounding boxes

    def __len__(self) -> int:
        """The number of obstacle polygons."""
        return len(self.polygons)

    def footprints(self, poses: np.ndarray) -> np.ndarray:
        """The grown footprint at each pose.

        Args:
            poses: ``[M, 3]`` rear-axle ``(x, y, yaw)``.

        Returns:
            ``[M, 4, 2]`` world corners, front-left first, counter-clockwise.
        """
        c, s = np.cos(poses[:, 2])[:, None], np.sin(poses[:, 2])[:, None]
        x = self._local[:, 0] * c - self._local[:, 1] * s + poses[:, 0:1]
        y = self._local[:, 0] * s + self._local[:, 1] * c + poses[:, 1:2]
        return np.stack([x, y], -1)

    def collides(self, poses: np.ndarray, times: np.ndarray | None = None) -> np.ndarray:
        """Whether the footprint at each pose overlaps an obstacle present at that pose's time (touching counts).

        Args:
            poses: ``[M, 3]`` rear-axle ``(x, y, yaw)``.
            times: ``[M]`` seconds of the plan; None tests only the obstacles that are always present.

        Returns:
            ``[M]`` bool.
        """
        poses = np.asarray(poses, np.float64).reshape(-1, 3)
        out = np.zeros(len(poses), bool)
        if not len(self) or not len(poses):
            return out
        feet = self.footprints(poses)                                                 # (M, 4, 2)
        low, high = feet.min(axis=1), feet.max(axis=1)
        near = ((low[:, None] <= self._high[None]) & (self._low[None] <= high[:, None])).all(-1)   # (M, n)
        if times is None:
            near &= self.static[None]
        else:
            t = np.asarray(times, np.float64).reshape(-1, 1)
            near &= (t >= self.windows[None, :, 0]) & (t <= self.windows[None, :, 1])
        m, n = np.nonzero(near)
        if not len(m):
            return out
        feet, obstacles = feet[m], self.polygons[n]                                  # (Q, 4, 2), (Q, K, 2)
        axes = np.concatenate([_normals(feet)[:, :2], self._normals[n]], axis=1)     # (Q, 2 + K, 2)
        pf = np.einsum("qad,qcd->qac", axes, feet)
        po = np.einsum("qad,qcd->qac", axes, obstacles)
        apart = ((pf.max(2) < po.min(2)) | (po.max(2) < pf.min(2))).any(axis=1)
        out[m[~apart]] = True
        return out

    def distances(self, points: np.ndarray) -> np.ndarray:
        """Euclidean distance from each point to the nearest always-present obstacle (0 inside one).

        Args:
            points: ``[G, 2]`` world points.

        Returns:
            ``[G]`` metres (inf when there is no obstacle).
        """
        polys = self.polygons[self.static]
        if not len(polys):
            return np.full(len(points), np.inf)
        a, b = polys, np.roll(polys, -1, axis=1)                                       # (n, K, 2) edge ends
        ab = b - a
        ap = points[:, None, None] - a[None]                                           # (G, n, K, 2)
        length2 = np.maximum((ab * ab).sum(-1), 1e-300)
        u = np.clip((ap * ab[None]).sum(-1) / length2[None], 0.0, 1.0)
        edge = np.linalg.norm(ap - u[..., None] * ab[None], axis=-1).min(axis=2)     # (G, n)
        cross = ab[None, ..., 0] * ap[..., 1] - ab[None, ..., 1] * ap[..., 0]         # (G, n, K)
        real = (ab * ab).sum(-1) > 0                                                   # padded edges are not
        inside = (np.where(real[None], cross, 1.0) >= 0).all(-1) | (np.where(real[None], cross, -1.0) <= 0).all(-1)
        return np.where(inside, 0.0, edge).min(axis=1)


@dataclass(frozen=True)
class HybridAStarConfig:
    """What the search explores and what it prefers.

    Attributes:
        xy_resolution: lattice bin side (m); also the heuristic grid's cell.
        yaw_bins: heading bins over a full turn.
        step: arc length of one move (m); longer than a bin's diagonal so that a move leaves its bin.
        radius_factor: planning turning radius as a multiple of the car's minimum (slack for the tracker).
        steering: steering fractions of the planning lock tried per move (each forward and backward).
        sample: spacing of the footprint tests along a move or an analytic path (m).
        path_step: spacing of the returned path's poses (m).
        reverse_cost: cost per metre backward (forward: 1).
        switch_cost: cost of a change of direction (m).
        steer_cost: cost per metre at full lock (scaled by the steering fraction).
        steer_change_cost: cost of a full-lock change of steering between two moves.
        analytic_range: try the Reeds-Shepp paths to the goals from nodes this close to one (m, straight line).
        analytic_paths: how many of the shortest Reeds-Shepp candidates an analytic expansion tries.
        heuristic_weight: the heuristic's weight in a node's priority (above 1: fewer expansions, costlier paths).
        speed: the plan's clock: metres per second, for the time windows of the obstacles.
        max_nodes: expansions before the search gives up.
        max_seconds: wall-clock seconds before the search gives up.
    """

    xy_resolution: float = 0.5
    yaw_bins: int = 72
    step: float = 0.9
    radius_factor: float = 1.15
    steering: tuple[float, ...] = (-1.0, -0.5, 0.0, 0.5, 1.0)
    sample: float = 0.3
    path_step: float = 0.1
    reverse_cost: float = 1.5
    switch_cost: float = 3.0
    steer_cost: float = 0.2
    steer_change_cost: float = 0.5
    analytic_range: float = 15.0
    analytic_paths: int = 4
    heuristic_weight: float = 1.5
    speed: float = 1.0
    max_nodes: int = 20_000
    max_seconds: float = 10.0

    def __post_init__(self) -> None:
        """Refuse settings the search cannot run with."""
        if not (self.xy_resolution > 0 and self.step > self.xy_resolution * math.sqrt(2)):
            raise ValueError(f"step ({self.step}) must exceed the diagonal of a bin of side xy_resolution "
                             f"({self.xy_resolution}) > 0")
        if self.yaw_bins < 4 or not self.steering or not all(-1 <= s <= 1 for s in self.steering):
            raise ValueError("yaw_bins must be >= 4 and steering a non-empty tuple of fractions in [-1, 1]")
        if not (min(self.radius_factor, self.reverse_cost) >= 1 and min(self.sample, self.path_step, self.speed) > 0):
            raise ValueError("radius_factor and reverse_cost must be >= 1; sample, path_step and speed > 0")

    def radius(self, vehicle: VehicleParams) -> float:
        """The planning turning radius (m): the car's minimum times ``radius_factor``.

        Args:
            vehicle: the car.

        Returns:
            Metres.
        """
        return self.radius_factor * vehicle.min_turn_radius


class PlanStatus(str, Enum):
    """How a search ended."""

    FOUND = "found"
    NO_PATH = "no path"
    BUDGET = "budget exhausted"
    START_IN_COLLISION = "start in collision"
    GOAL_IN_COLLISION = "goal in collision"


@dataclass(frozen=True)
class PlanResult:
    """A search's path or its cause of failure.

    Attributes:
        status: how the search ended.
        path: ``[N, 4]`` ``(x, y, yaw, direction)`` poses ``HybridAStarConfig.path_step`` metres apart or closer,
            yaw continuous, direction +1 / -1 as the car leaves the pose (``ReedsSheppPath.sample``'s layout);
            None unless found.
        goal: index of the goal reached (None unless found).
        cost: the path's cost (inf unless found).
        expanded: nodes expanded.
        seconds: wall-clock time of the search.
    """

    status: PlanStatus
    path: np.ndarray | None = None
    goal: int | None = None
    cost: float = math.inf
    expanded: int = 0
    seconds: float = 0.0

    @property
    def length(self) -> float:
        """Metres along the path (forward and backward), 0 without one."""
        return 0.0 if self.path is None else float(np.hypot(*np.diff(self.path[:, :2], axis=0).T).sum())

    @property
    def switches(self) -> int:
        """Direction changes along the path, 0 without one."""
        return 0 if self.path is None else int((np.diff(self.path[:-1, 3]) != 0).sum())


def _arc(poses: np.ndarray, curvature: np.ndarray, length: np.ndarray) -> np.ndarray:
    """Poses ``[..., 3]`` after driving ``length`` (signed m) at constant ``curvature`` (1/m), exact; broadcasts."""
    x, y, yaw = poses[..., 0], poses[..., 1], poses[..., 2]
    turn = curvature * length
    small = np.abs(turn) < 1e-9
    k = np.where(small, 1.0, curvature)
    dx = np.where(small, length * np.cos(yaw), (np.sin(yaw + turn) - np.sin(yaw)) / k)
    dy = np.where(small, length * np.sin(yaw), (np.cos(yaw) - np.cos(yaw + turn)) / k)
    return np.stack([x + dx, y + dy, yaw + turn], -1)


@dataclass
class _Grid:
    """The holonomic heuristic: shortest 8-connected grid distance from each cell to the nearest goal (m)."""

    origin: np.ndarray
    resolution: float
    cost: np.ndarray = field(repr=False)   # (nx, ny), inf where blocked or cut off

    @classmethod
    def build(cls, checker: FootprintChecker, bounds: tuple[tuple[float, float], tuple[float, float]],
              resolution: float, goals: np.ndarray, clearance: float) -> _Grid:
        """Block cells whose centre lies within ``clearance`` of an obstacle, then Dijkstra from the goals' cells."""
        (x0, x1), (y0, y1) = bounds
        nx, ny = math.ceil((x1 - x0) / resolution), math.ceil((y1 - y0) / resolution)
        origin = np.array([x0, y0])
        ix, iy = np.meshgrid(np.arange(nx), np.arange(ny), indexing="ij")
        centres = origin + (np.stack([ix, iy], -1).reshape(-1, 2) + 0.5) * resolution
        free = (checker.distances(centres) >= clearance).reshape(nx, ny)
        cost = np.full((nx, ny), np.inf)
        heap: list[tuple[float, int, int]] = []
        for gx, gy in goals[:, :2]:
            i, j = int((gx - x0) // resolution), int((gy - y0) // resolution)
            if 0 <= i < nx and 0 <= j < ny:
                cost[i, j] = 0.0
                heap.append((0.0, i, j))
        heapq.heapify(heap)
        moves = [(di, dj, resolution * math.hypot(di, dj)) for di in (-1, 0, 1) for dj in (-1, 0, 1) if di or dj]
        while heap:
            c, i, j = heapq.heappop(heap)
            if c > cost[i, j]:
                continue
            for di, dj, d in moves:
                a, b = i + di, j + dj
                if 0 <= a < nx and 0 <= b < ny and free[a, b] and c + d < cost[a, b]:
                    cost[a, b] = c + d
                    heapq.heappush(heap, (c + d, a, b))
        return cls(origin, resolution, cost)

    def __call__(self, x: float, y: float) -> float:
        """The distance at the cell of ``(x, y)`` (inf outside the grid)."""
        i, j = int((x - self.origin[0]) // self.resolution), int((y - self.origin[1]) // self.resolution)
        inside = 0 <= i < self.cost.shape[0] and 0 <= j < self.cost.shape[1]
        return float(self.cost[i, j]) if inside else math.inf


@dataclass(frozen=True)
class _Node:
    """A reached pose: its cost so far, its parent's index and the move that reached it."""

    pose: tuple[float, float, float]
    g: float
    parent: int
    steer: float      # steering fraction of the move in
    direction: int    # +1 / -1 of the move in (0 at the start)
    distance: float   # metres driven so far (the plan's clock times speed)


class _Search:
    """One Hybrid A* search (the state ``hybrid_astar`` sets up and runs)."""

    def __init__(self, goals: np.ndarray, checker: FootprintChecker, grid: _Grid, config: HybridAStarConfig,
                 vehicle: VehicleParams) -> None:
        self.goals, self.checker, self.grid, self.config = goals, checker, grid, config
        self.radius = config.radius(vehicle)
        n = max(2, math.ceil(config.step / config.sample))
        self.fractions = np.arange(1, n + 1) / n                                   # samples along a move
        steer = np.array(config.steering, np.float64)
        self.moves = [(s, d) for d in (1, -1) for s in steer]                       # (fraction, direction)
        self.curvature = np.array([s / self.radius for s, _ in self.moves])
        self.signed = np.array([d * config.step for _, d in self.moves])

    def key(self, pose: tuple[float, float, float]) -> tuple[int, int, int]:
        """The lattice bin of a pose."""
        r, bins = self.config.xy_resolution, self.config.yaw_bins
        return (int(pose[0] // r), int(pose[1] // r), int(round(float(wrap_angle(pose[2])) / (2 * math.pi) * bins))
                % bins)

    def heuristic(self, pose: tuple[float, float, float]) -> float:
        """A lower bound of the metres left from ``pose`` to the nearest goal.

        Farther than ``analytic_range`` (by the grid) the grid distance dominates, and the Reeds-Shepp length is
        not worth its cost.

        Returns:
            The grid distance, or within ``analytic_range`` the larger of it and the shortest Reeds-Shepp length.
        """
        h = self.grid(pose[0], pose[1])
        if math.isinf(h) or h > self.config.analytic_range:
            return h
        return max(h, min(reeds_shepp_length(pose, tuple(g), self.radius) for g in self.goals))

    def move_cost(self, node: _Node, steer: float, direction: int, length: float) -> float:
        """Cost of driving ``length`` metres at ``steer`` in ``direction`` after ``node``'s move."""
        c = self.config
        cost = length * (c.reverse_cost if direction < 0 else 1.0) + c.steer_cost * abs(steer) * length
        if node.direction and direction != node.direction:
            cost += c.switch_cost
        return cost + c.steer_change_cost * abs(steer - node.steer) * (node.direction != 0)

    def successors(self, node: _Node, parent: int) -> list[_Node]:
        """The collision-free moves from ``node`` (whose index is ``parent``)."""
        start = np.array(node.pose)
        lengths = self.signed[:, None] * self.fractions[None]                          # (P, S)
        samples = _arc(start, self.curvature[:, None], lengths)                         # (P, S, 3)
        times = (node.distance + np.abs(lengths)) / self.config.speed
        hit = self.checker.collides(samples.reshape(-1, 3), times.reshape(-1)).reshape(lengths.shape)
        out = []
        for p, (steer, direction) in enumerate(self.moves):
            if hit[p].any():
                continue
            x, y, yaw = (float(v) for v in samples[p, -1])
            g = node.g + self.move_cost(node, steer, direction, self.config.step)
            out.append(_Node((x, y, yaw), g, parent, steer, direction, node.distance + self.config.step))
        return out

    def path_cost(self, node: _Node, path: ReedsSheppPath) -> float:
        """Cost of the analytic ``path`` after ``node`` (each segment a move: arcs at full lock)."""
        cost, prev = 0.0, node
        for kind, length in zip(path.word, path.lengths):
            if length == 0.0:
                continue
            steer = 0.0 if kind == "S" else 1.0 if kind == "L" else -1.0
            direction = 1 if length > 0 else -1
            cost += self.move_cost(prev, steer, direction, abs(length))
            prev = _Node(prev.pose, 0.0, -1, steer, direction, 0.0)
        return cost

    def clear(self, path: ReedsSheppPath, distance: float) -> bool:
        """Whether ``path``, driven from ``distance`` metres into the plan, clears the obstacles.

        The poses are tested in chunks from the path's start, so that a path blocked early costs little.

        Returns:
            True when no pose of the path touches an obstacle present at its time.
        """
        poses = path.sample(self.config.sample)
        arc = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(poses[:, :2], axis=0).T))])
        times = (distance + arc) / self.config.speed
        return not any(self.checker.collides(poses[i:i + _CHUNK, :3], times[i:i + _CHUNK]).any()
                       for i in range(0, len(poses), _CHUNK))

    def analytic(self, node: _Node) -> tuple[int, ReedsSheppPath, float] | None:
        """The cheapest collision-free Reeds-Shepp path from ``node`` among the shortest few to each goal in range.

        Returns:
            ``(goal index, path, its cost)`` or None. A path shorter than the grid distance allows is not tested:
            it must cross a blocked cell (the grid's 8-connected distance exceeds a curve's length through free
            cells by at most the octile factor 1 / cos(22.5 deg), plus a cell at either end).
        """
        shortest = (self.grid(node.pose[0], node.pose[1]) - 2 * math.sqrt(2) * self.config.xy_resolution) / _OCTILE
        best: tuple[int, ReedsSheppPath, float] | None = None
        for index, goal in enumerate(self.goals):
            if math.hypot(goal[0] - node.pose[0], goal[1] - node.pose[1]) > self.config.analytic_range:
                continue
            for path in reeds_shepp_paths(node.pose, tuple(goal), self.radius)[:self.config.analytic_paths]:
                cost = self.path_cost(node, path)
                if path.length < shortest or (best is not None and cost >= best[2]):
                    continue
                if self.clear(path, node.distance):
                    best = (index, path, cost)
        return best


def _trace(nodes: list[_Node], last: int, search: _Search, tail: ReedsSheppPath, step: float) -> np.ndarray:
    """The path ``[N, 4]`` from the start to node ``last`` (its moves re-sampled at ``step``) and on along ``tail``."""
    chain = []
    while last >= 0:
        chain.append(nodes[last])
        last = nodes[last].parent
    chain.reverse()
    rows = []
    n = max(1, math.ceil(search.config.step / step))
    fractions = np.arange(n) / n
    for parent, child in zip(chain, chain[1:]):
        lengths = child.direction * search.config.step * fractions
        poses = _arc(np.array(parent.pose), np.full(n, child.steer / search.radius), lengths)
        rows.append(np.column_stack([poses, np.full(n, float(child.direction))]))
    rest = tail.sample(step)
    if rows and len(rest) == 1:   # a zero tail: the last node is the goal; it leaves as the last move did
        rest[0, 3] = rows[-1][-1, 3]
    path = np.concatenate(rows + [rest]) if rows else rest
    path[:, 2] = path[0, 2] + np.concatenate([[0.0], np.cumsum(wrap_angle(np.diff(path[:, 2])))])
    return path


def hybrid_astar(start: tuple[float, float, float], goals: Sequence[tuple[float, float, float]],
                 checker: FootprintChecker, bounds: tuple[tuple[float, float], tuple[float, float]],
                 vehicle: VehicleParams = VehicleParams(), config: HybridAStarConfig = HybridAStarConfig()
                 ) -> PlanResult:
    """Search a path from ``start`` to the cheapest reachable of ``goals`` whose footprint clears ``checker``.

    Args:
        start: rear-axle ``(x, y, yaw)`` (metres, radians), at time 0 of the plan.
        goals: rear-axle poses, any of which ends the search (e.g. head-in and reverse-in parked in a slot).
        checker: the obstacles (and the margin kept from them).
        bounds: ``((x_min, x_max), (y_min, y_max))`` the rear axle stays within (m).
        vehicle: the car (size and minimum turning radius).
        config: lattice, moves, costs and budgets.

    Returns:
        The result: the path when found, else why not (start or every goal in collision, no path, budget spent).

    Raises:
        ValueError: no goal, or a pose that is not 3 finite numbers.
    """
    began = time.perf_counter()
    s = np.asarray(start, np.float64)
    g = np.asarray(goals, np.float64).reshape(-1, 3) if len(goals) else np.zeros((0, 3))
    if s.shape != (3,) or not len(g) or not (np.isfinite(s).all() and np.isfinite(g).all()):
        raise ValueError(f"hybrid_astar needs a finite start (x, y, yaw) and at least one finite goal, got {start!r} "
                         f"and {goals!r}")
    if checker.collides(s[None], np.zeros(1))[0]:
        return PlanResult(PlanStatus.START_IN_COLLISION, seconds=time.perf_counter() - began)
    reachable = ~checker.collides(g)
    if not reachable.any():
        return PlanResult(PlanStatus.GOAL_IN_COLLISION, seconds=time.perf_counter() - began)
    index = np.flatnonzero(reachable)
    clearance = min(vehicle.rear_overhang, vehicle.width / 2) + checker.margin - config.xy_resolution / math.sqrt(2)
    grid = _Grid.build(checker, bounds, config.xy_resolution, g[index], max(clearance, 0.0))
    search = _Search(g[index], checker, grid, config, vehicle)
    return _run(search, (float(s[0]), float(s[1]), float(s[2])), bounds, index, began)


def _run(search: _Search, start: tuple[float, float, float], bounds: tuple[tuple[float, float], tuple[float, float]],
         goal_index: np.ndarray, began: float) -> PlanResult:
    """The A* loop: pop the cheapest node, try the analytic expansion, push its moves; until a path or a budget."""
    config = search.config
    nodes = [_Node(start, 0.0, -1, 0.0, 0, 0.0)]
    h = config.heuristic_weight * search.heuristic(start)
    if math.isinf(h):
        return PlanResult(PlanStatus.NO_PATH, seconds=time.perf_counter() - began)
    heap: list[tuple[float, int]] = [(h, 0)]   # (f, node index): the index breaks ties in insertion order
    best = {search.key(start): 0.0}
    closed: set[tuple[int, int, int]] = set()
    (x0, x1), (y0, y1) = bounds
    while heap:
        _, i = heapq.heappop(heap)
        node = nodes[i]
        key = search.key(node.pose)
        if key in closed:
            continue
        if len(closed) >= config.max_nodes or time.perf_counter() - began > config.max_seconds:
            return PlanResult(PlanStatus.BUDGET, expanded=len(closed), seconds=time.perf_counter() - began)
        closed.add(key)
        shot = search.analytic(node)
        if shot is not None:
            goal, tail, cost = shot
            return PlanResult(PlanStatus.FOUND, _trace(nodes, i, search, tail, config.path_step),
                              int(goal_index[goal]), node.g + cost, len(closed), time.perf_counter() - began)
        for child in search.successors(node, i):
            x, y, _ = child.pose
            k = search.key(child.pose)
            if not (x0 <= x <= x1 and y0 <= y <= y1) or k in closed or best.get(k, math.inf) <= child.g:
                continue
            h = config.heuristic_weight * search.heuristic(child.pose)
            if math.isinf(h):
                continue
            best[k] = child.g
            nodes.append(child)
            heapq.heappush(heap, (child.g + h, len(nodes) - 1))
    return PlanResult(PlanStatus.NO_PATH, expanded=len(closed), seconds=time.perf_counter() - began)
