"""Graded scenario sets made from a scene's map: easy, medium and hard parking episodes, drawn from a seed.

``make_set`` reads only the map (``map.json``: ``garage.lanes``, the aisle centre lines along x; ``slots`` with
``corners``; ``obstacles`` as boxes) and writes nothing; each scenario it returns passes ``prepare`` on that map.

**Grading rules.**

- *Every level.* The target is a free slot named by id, whose entrance opens on an aisle lane (within 4 m of its
  centre line), the corridor from the entrance to the lane clear of obstacles and the ego's body clear of them when
  parked at the slot's centre. The ego starts in a region on that lane (x 1 m long, y +-0.3 m about the lane,
  heading +-0.1 rad about the aisle's direction towards the slot: the direction an angled slot is entered forward,
  either way for a perpendicular or parallel one), its front a gap before the entrance; the whole region, grown by
  the 0.3 m ``prepare`` keeps, is clear of obstacles and the body can drive along the lane from it to 3 m past the
  entrance without touching anything. Default time limit and tolerances.
- *easy*: a free path: nothing filled, no actors, the front 2 to 5 m before the entrance.
- *medium*: a tight slot: every neighbour of the target (a slot of the same row sharing an entrance mark, or
  whose entrance lies within 1.5 m along the row) is filled with a parked car (``occupy``) unless the map has one
  there already, and so are up to 2 other free slots drawn at random; the target has at least one neighbour. The
  front starts 4 to 10 m before the entrance.
- *hard*: medium, plus 1 to 3 moving actors of these kinds, tried in a random order: ``car_through``, a car (IDM,
  ``lane``) coming down the lane behind the ego to the aisle's end; ``car_leaving``, a car parked nose-in in a
  free slot of the same aisle within 12 m that backs out to the lane and drives off along it (``path``);
  ``walker_crossing``, a pedestrian crossing the aisle between the ego and 4 m past the target once the ego comes
  within 3 to 6 m (``pedestrian``, distance trigger); ``walker_passing``, a pedestrian walking along the aisle
  1 m in front of the target's entrance from a time of 4 to 12 s on. Actors use the built-in ``car`` and
  ``pedestrian`` assets. No actor starts on an obstacle, a parked car, another actor or the ego's start region;
  every actor's whole route (straight segments, with its turns on the spot) stays clear of the obstacles and
  parked cars; the route of an actor that ignores the others (``path``, ``pedestrian``) also stays clear of the
  ego's start region and of where the other actors stand or go, so an ego that stays put is never run into.

Targets that cannot host a scenario of a level are skipped: a target is drawn again, up to ``TRIES`` times per
scenario. Each scenario draws from its own stream of the set's seed keyed by its level and number, so
``medium_003`` is the same whatever ``count`` and the other levels; its ``seed`` (the episode's draws) is drawn
from that stream too.
"""

from __future__ import annotations

import math
import re
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal, cast

import numpy as np

from ..vehicle import Obstacles, VehicleParams
from .resolve import START_MARGIN, prepare
from .shapes import Box, box_polygon, overlap_matrix
from .spec import _NAME as NAME_PATTERN
from .spec import (
    BUILTIN_BOXES,
    ActorSpec,
    EgoStart,
    LaneSpec,
    PathSpec,
    PedestrianSpec,
    Region,
    Scenario,
    ScenarioError,
    ScenarioSet,
    TriggerSpec,
)
from .task import slot_pose

__all__ = ["make_set", "DIFFICULTIES", "TRIES"]

Level = Literal["easy", "medium", "hard"]
"""A scenario's difficulty (``Scenario.difficulty``)."""
DIFFICULTIES: tuple[Level, ...] = ("easy", "medium", "hard")
"""The levels, in the order a set lists them."""
TRIES = 100
"""Target draws per scenario before giving up on a level."""
_LANE_REACH = 4.0
"""An entrance whose midpoint lies within this (m) of a lane's centre line opens on that lane's aisle."""
_ADJACENT = 1.5
"""Slots of one row whose entrances are this close (m) along the row are neighbours (a bay gap is 1.2 m)."""
_EXTRA = 2
"""The most free slots a medium or hard scenario fills beside the target's neighbours."""
_GAP: dict[Level, tuple[float, float]] = {"easy": (2.0, 5.0), "medium": (4.0, 10.0), "hard": (4.0, 10.0)}
"""How far (m) the ego's front starts before the target's entrance, per level."""
_HALF_X, _HALF_Y, _HALF_YAW = 0.5, 0.3, 0.1
"""Half spans of the ego's start region: along the lane, across it (m), heading (rad)."""
_PASS = 3.0
"""How far (m) past the entrance the ego must be able to drive down the lane (to swing in, or to back in)."""
_STEP = 0.25
"""Spacing (m) of the footprints along a swept route."""
_TURN = math.radians(10.0)
"""Spacing (rad) of the footprints of a turn on the spot along a swept route."""
_NEAR = 12.0
"""How far (m) along the aisle a leaving car's slot may be from the target."""
_WALK_HALF = 2.6
"""A crossing pedestrian walks from this far (m) on one side of the lane centre to as far on the other."""


@dataclass(frozen=True)
class _Slot:
    """A map slot as the generator sees it: its entrance and the lane whose aisle it opens on.

    Attributes:
        id: the slot's id.
        centre: ``[2]`` its centre (``slot_pose``).
        yaw: its axis (``slot_pose``): into the slot, or along it for a parallel slot.
        lane: y of the lane's centre line.
        side: +1 when the slot lies at larger y than the lane, -1 when at smaller.
        lo: smallest x of the entrance.
        hi: largest x of the entrance.
        entrance_y: y of the entrance's midpoint.
        slant: the sign of the slot axis's x for an angled slot (the direction it is entered forward), else 0.
        parallel: a parallel slot (its entrance is its longer side).
        marks: the ids of its entrance marks (``p1``, ``p2``), where the map gives them.
        corners: ``[4, 2]`` its corners.
    """

    id: int
    centre: np.ndarray
    yaw: float
    lane: float
    side: float
    lo: float
    hi: float
    entrance_y: float
    slant: float
    parallel: bool
    marks: frozenset[int]
    corners: np.ndarray


@dataclass(frozen=True)
class _Placed:
    """An actor as the placement checks see it.

    Attributes:
        spec: the actor.
        start: ``[1, 4, 2]`` its footprint at its pose.
        route: ``[S, 4, 2]`` its footprints along everything it may drive or walk (``start`` first).
        area: where it may be whatever the others do: ``route`` for an actor that ignores them, ``start`` for one
            that stops for them (``lane``).
    """

    spec: ActorSpec
    start: np.ndarray
    route: np.ndarray
    area: np.ndarray


def _r(value: float) -> float:
    """A coordinate as the file keeps it: a Python float rounded to the millimetre."""
    return round(float(value), 3)


def _slot(slot: Mapping[str, Any], lanes: Sequence[float]) -> _Slot | None:
    """The slot's entrance and lane, or None when no lane's aisle is in front of it."""
    c = np.asarray(slot["corners"], np.float64)
    mid = c[:2].mean(0)
    into = c[2:].mean(0) - mid
    if abs(into[1]) < 1e-6:
        return None                 # opens along x: no lane (along x) in front of it
    side = float(np.sign(into[1]))
    serving = [float(y) for y in lanes if (float(y) - mid[1]) * side < 0 and abs(float(y) - mid[1]) <= _LANE_REACH]
    if not serving:
        return None
    centre, yaw = slot_pose(dict(slot))
    parallel = bool(np.linalg.norm(c[1] - c[0]) > np.linalg.norm(into))
    angled = not parallel and abs(into[0]) > 0.1 * np.linalg.norm(into)
    marks = frozenset(int(slot[k]) for k in ("p1", "p2") if k in slot)
    return _Slot(int(slot["id"]), centre, yaw, min(serving, key=lambda y: abs(y - mid[1])), side,
                 float(c[:2, 0].min()), float(c[:2, 0].max()), float(mid[1]),
                 float(np.sign(into[0])) if angled else 0.0, parallel, marks, c)


def _hits(polygons: np.ndarray, blocked: np.ndarray) -> bool:
    """Whether any of ``[S, K, 2]`` polygons overlaps any of ``[M, L, 2]`` (touching counts)."""
    return bool(len(polygons) and len(blocked) and overlap_matrix(polygons, blocked).any())


def _car_in(slot: _Slot) -> np.ndarray:
    """``[1, 4, 2]``: the parked car ``prepare`` puts in a filled slot (the built-in car, centred on its axis)."""
    x0, x1, y0, y1 = BUILTIN_BOXES["car"]
    half = ((x1 - x0) / 2, (y1 - y0) / 2)
    return box_polygon((*slot.centre, slot.yaw), (-half[0], half[0], -half[1], half[1]))[None]


def _hosts(slot: _Slot, blocked: np.ndarray, vehicle: VehicleParams) -> bool:
    """Whether the ego fits parked at the slot's centre and its entrance is open to the lane."""
    x0, x1, _, _ = vehicle.extent
    back = (x0 + x1) / 2
    rear = (slot.centre[0] - back * math.cos(slot.yaw), slot.centre[1] - back * math.sin(slot.yaw), slot.yaw)
    c0, c1 = slot.corners[0], slot.corners[1]
    corridor = np.array([c0, c1, [c1[0], slot.lane], [c0[0], slot.lane]])
    return not _hits(np.stack([box_polygon(rear, vehicle.extent), corridor]), blocked)


def _neighbours(target: _Slot, slots: Sequence[_Slot]) -> list[_Slot]:
    """The slots of the target's row sharing an entrance mark with it or within ``_ADJACENT`` along the row."""
    return [s for s in slots if s.id != target.id and s.lane == target.lane and s.side == target.side
            and (s.marks & target.marks or max(s.lo - target.hi, target.lo - s.hi) <= _ADJACENT)]


def _sweep(pose: Sequence[float], box: Box, points: Sequence[Sequence[float]]) -> np.ndarray:
    """``[S, 4, 2]`` footprints of ``box`` from ``pose`` along straight segments through ``points``.

    Each segment is driven facing along it (away from it for a point ``[x, y, -1]``), turning on the spot at its
    start from the heading before.

    Returns:
        The footprints every ``_STEP`` m and ``_TURN`` rad, both ends included.
    """
    poses = [np.array(pose, np.float64)[None]]
    at, yaw = np.array(pose[:2], np.float64), float(pose[2])
    for p in points:
        d = np.array(p[:2], np.float64) - at
        heading = math.atan2(d[1], d[0]) + (math.pi if len(p) == 3 and p[2] < 0 else 0.0)
        turn = math.remainder(heading - yaw, math.tau)
        yaws = yaw + turn * np.linspace(0.0, 1.0, math.ceil(abs(turn) / _TURN) + 1)
        poses.append(np.column_stack([np.tile(at, (len(yaws), 1)), yaws]))
        u = np.linspace(0.0, 1.0, math.ceil(float(np.hypot(*d)) / _STEP) + 1)[:, None]
        poses.append(np.column_stack([at + u * d, np.full(len(u), heading)]))
        at, yaw = at + d, heading
    return box_polygon(np.concatenate(poses), box)


def _placed(spec: ActorSpec) -> _Placed:
    """The actor's start footprint, route and area (``_Placed``)."""
    b, box = spec.behaviour, spec.resolved_box()
    points = (b.waypoints if isinstance(b, (PathSpec, LaneSpec)) else (b.to,) if isinstance(b, PedestrianSpec)
              else ())
    start = box_polygon(spec.pose, box)[None]
    route = _sweep(spec.pose, box, points)
    return _Placed(spec, start, route, start if isinstance(b, LaneSpec) else route)


def _fits(actor: _Placed, placed: Sequence[_Placed], blocked: np.ndarray, envelope: np.ndarray) -> bool:
    """Whether the actor's route is clear of the obstacles, and its area of the ego's region and the others'."""
    if _hits(actor.route, blocked) or _hits(actor.area, envelope[None]):
        return False
    return not any(_hits(actor.area, other.area) for other in placed)


def _reach(pose: tuple[float, float, float], box: Box, blocked: np.ndarray, limit: float) -> float:
    """How far (m) ``box`` moves straight ahead from ``pose`` (up to ``limit``) before it would touch an obstacle.

    Returns:
        The distance, in ``_STEP`` steps; -1 when it touches one where it stands.
    """
    s = np.arange(0.0, max(limit, 0.0) + 1e-9, _STEP)
    x, y, yaw = pose
    polygons = box_polygon(np.column_stack([x + s * math.cos(yaw), y + s * math.sin(yaw), np.full(len(s), yaw)]),
                           box)
    hit = overlap_matrix(polygons, blocked).any(1) if len(blocked) else np.zeros(len(s), bool)
    first = int(np.argmax(hit)) if hit.any() else len(s)
    return float(s[first - 1]) if first else -1.0


def _envelope(region: Region, vehicle: VehicleParams) -> np.ndarray:
    """A box around every body ``prepare`` may draw from ``region``, each grown by ``START_MARGIN``.

    A drawn pose's body point lies within ``hypot(x, y half spans) + yaw half span * reach`` of the same point at
    the region's middle pose (a turn moves a point by at most its arc), so growing the middle body by that much
    more covers them all.

    Returns:
        ``[4, 2]`` its corners.
    """
    half = [(span[1] - span[0]) / 2 for span in (region.x, region.y, region.yaw)]
    mid = [(span[0] + span[1]) / 2 for span in (region.x, region.y, region.yaw)]
    x0, x1, y0, y1 = vehicle.extent
    reach = math.hypot(max(-x0, x1) + START_MARGIN, max(-y0, y1) + START_MARGIN)
    g = START_MARGIN + math.hypot(half[0], half[1]) + half[2] * reach
    return box_polygon(mid, (x0 - g, x1 + g, y0 - g, y1 + g))


@dataclass(frozen=True)
class _Start:
    """The ego's start region for a target and what the actors must keep clear of.

    Attributes:
        region: the region.
        envelope: ``[4, 2]`` its ``_envelope``.
        direction: +1 when the ego drives towards +x, -1 towards -x.
    """

    region: Region
    envelope: np.ndarray
    direction: float


def _start(target: _Slot, direction: float, gap: float, blocked: np.ndarray, vehicle: VehicleParams
           ) -> _Start | None:
    """The start region ``gap`` m before the entrance driving ``direction``, if it and the way to the slot are clear.

    Returns:
        The start, or None when the region touches an obstacle or the lane is blocked before ``_PASS`` m past the
        entrance.
    """
    x0, x1, _, _ = vehicle.extent
    near, far = (target.lo, target.hi) if direction > 0 else (target.hi, target.lo)
    x = near - direction * (gap + x1)
    yaw = 0.0 if direction > 0 else math.pi
    region = Region(x=(_r(x - _HALF_X), _r(x + _HALF_X)), y=(_r(target.lane - _HALF_Y), _r(target.lane + _HALF_Y)),
                    yaw=(_r(yaw - _HALF_YAW), _r(yaw + _HALF_YAW)))
    envelope = _envelope(region, vehicle)
    if _hits(envelope[None], blocked):
        return None
    drive = direction * (far - x) + _PASS - x1
    if _reach((x, target.lane, yaw), vehicle.extent, blocked, drive) < drive - _STEP:
        return None
    return _Start(region, envelope, direction)


def _along(start: _Start, x: np.ndarray | float) -> np.ndarray:
    """Positions along the ego's driving direction: ``x`` times the direction."""
    return start.direction * np.asarray(x, np.float64)


@dataclass(frozen=True)
class _Ground:
    """What the actors of a draw are placed among.

    Attributes:
        slots: the map's slots that open on a lane.
        free: ids of the slots left free (not occupied in the map, not filled, not the target).
        blocked: ``[M, 4, 2]`` the obstacles with the filled slots' cars.
    """

    slots: Sequence[_Slot]
    free: set[int]
    blocked: np.ndarray


def _car_through(target: _Slot, start: _Start, ground: _Ground, rng: np.random.Generator) -> ActorSpec | None:
    """A car behind the ego's region coming down the lane (IDM) to the aisle's end, or None if there is no room."""
    back = float(_along(start, start.envelope[:, 0]).min())
    x = start.direction * (back - float(rng.uniform(2.0, 8.0)) - BUILTIN_BOXES["car"][1])
    yaw = 0.0 if start.direction > 0 else math.pi
    run = _reach((x, target.lane, yaw), BUILTIN_BOXES["car"], ground.blocked, 200.0)
    end = x + start.direction * run
    if run < 0 or _along(start, end) < _along(start, target.hi if start.direction > 0 else target.lo) + 5.0:
        return None
    return ActorSpec(name="car_through", asset="car", pose=(_r(x), _r(target.lane), _r(yaw)),
                     behaviour=LaneSpec(type="lane", waypoints=((_r(end), _r(target.lane)),), speed=(1.5, 3.0)))


def _car_leaving(target: _Slot, start: _Start, ground: _Ground, rng: np.random.Generator) -> ActorSpec | None:
    """A car nose-in in a free slot of the aisle near the target that backs out to the lane and drives off."""
    mid = (target.lo + target.hi) / 2
    near = [s for s in ground.slots if s.id in ground.free and not s.parallel and s.lane == target.lane
            and abs((s.lo + s.hi) / 2 - mid) <= _NEAR and not _hits(_car_in(s), ground.blocked)]
    if not near:
        return None
    slot = near[int(rng.integers(len(near)))]
    axis = np.array([math.cos(slot.yaw), math.sin(slot.yaw)])
    out = slot.centre - axis * (slot.centre[1] - slot.lane) / axis[1]        # straight back out onto the lane
    direction = slot.slant or start.direction
    run = min(_reach((float(out[0]), slot.lane, 0.0 if direction > 0 else math.pi), BUILTIN_BOXES["car"],
                     ground.blocked, 20.0), 20.0)
    if run < 6.0:
        return None
    return ActorSpec(name="car_leaving", asset="car", pose=(_r(slot.centre[0]), _r(slot.centre[1]), _r(slot.yaw)),
                     behaviour=PathSpec(type="path", waypoints=((_r(out[0]), _r(slot.lane), -1.0),
                                                                (_r(out[0] + direction * run), _r(slot.lane))),
                                        speed=(0.8, 1.5), start_time=(0.0, 3.0)))


def _walker_crossing(target: _Slot, start: _Start, ground: _Ground, rng: np.random.Generator) -> ActorSpec | None:
    """A pedestrian at one edge of the aisle, between the ego and just past the target, crossing when it nears."""
    low = float(_along(start, start.envelope[:, 0]).max()) + 1.0
    high = float(_along(start, target.hi if start.direction > 0 else target.lo)) + 4.0
    if high <= low:
        return None
    x = start.direction * float(rng.uniform(low, high))
    side = float(rng.choice([-1.0, 1.0]))
    return ActorSpec(name="walker_crossing", asset="pedestrian",
                     pose=(_r(x), _r(target.lane + side * _WALK_HALF), _r(-side * math.pi / 2)),
                     behaviour=PedestrianSpec(type="pedestrian", to=(_r(x), _r(target.lane - side * _WALK_HALF)),
                                              speed=(1.0, 1.6), trigger=TriggerSpec(distance=(3.0, 6.0))))


def _walker_passing(target: _Slot, start: _Start, ground: _Ground, rng: np.random.Generator) -> ActorSpec | None:
    """A pedestrian walking along the aisle 1 m in front of the target's entrance from a drawn time on."""
    mid = float(_along(start, (target.lo + target.hi) / 2))
    low = max(mid - 6.0, float(_along(start, start.envelope[:, 0]).max()) + 0.5)
    high = mid + 6.0
    if high - low < 3.0:
        return None
    ends = [start.direction * low, start.direction * high]
    if rng.random() < 0.5:
        ends.reverse()
    y = target.entrance_y - target.side * 1.0
    return ActorSpec(name="walker_passing", asset="pedestrian",
                     pose=(_r(ends[0]), _r(y), 0.0 if ends[1] > ends[0] else _r(math.pi)),
                     behaviour=PedestrianSpec(type="pedestrian", to=(_r(ends[1]), _r(y)), speed=(1.0, 1.6),
                                              trigger=TriggerSpec(time=(4.0, 12.0))))


_ACTORS: dict[str, Callable[[_Slot, _Start, _Ground, np.random.Generator], ActorSpec | None]] = {
    "car_through": _car_through, "car_leaving": _car_leaving, "walker_crossing": _walker_crossing,
    "walker_passing": _walker_passing}
"""The moving actors of a hard scenario by name (see the module docstring); None where one has no room."""


def _actors(target: _Slot, start: _Start, ground: _Ground, rng: np.random.Generator) -> tuple[ActorSpec, ...]:
    """1 to 3 moving actors of the kinds in a drawn order, each kept only where it fits beside those before it."""
    wanted = int(rng.integers(1, 4))
    makers = list(_ACTORS.values())
    placed: list[_Placed] = []
    for i in rng.permutation(len(makers)):
        if len(placed) == wanted:
            break
        spec = makers[int(i)](target, start, ground, rng)
        if spec is not None and _fits(actor := _placed(spec), placed, ground.blocked, start.envelope):
            placed.append(actor)
    return tuple(a.spec for a in placed)


def _scenario(world_map: Mapping[str, Any], scene: str, level: Level, index: int, target: _Slot,
              slots: Sequence[_Slot], blocked: np.ndarray, vehicle: VehicleParams,
              rng: np.random.Generator) -> Scenario | None:
    """One draw of a scenario of ``level`` aiming at ``target``.

    Returns:
        The scenario (``prepare`` accepts it on ``world_map``), or None when this draw does not fit.
    """
    free = {int(s["id"]) for s in world_map["slots"] if not s.get("occupied", False)} - {target.id}
    occupy: list[int] = []
    if level != "easy":
        occupy = [s.id for s in _neighbours(target, slots) if s.id in free]
        others = [s.id for s in slots if s.id in free and s.id not in occupy and not _hits(_car_in(s), blocked)]
        extra = rng.choice(others, size=min(len(others), int(rng.integers(0, _EXTRA + 1))), replace=False)
        occupy = sorted(occupy + [int(i) for i in extra])
    by_id = {s.id: s for s in slots}
    filled = np.concatenate([blocked, *(_car_in(by_id[i]) for i in occupy)])
    direction = target.slant or float(rng.choice([-1.0, 1.0]))
    start = _start(target, direction, float(rng.uniform(*_GAP[level])), filled, vehicle)
    if start is None:
        return None
    actors = _actors(target, start, _Ground(slots, free - set(occupy), filled), rng) if level == "hard" else ()
    if level == "hard" and not actors:
        return None
    scenario = Scenario(name=f"{level}_{index:03d}", scene=scene, difficulty=level, seed=int(rng.integers(2 ** 31)),
                        ego=EgoStart(region=start.region), target=target.id, occupy=tuple(occupy), actors=actors)
    try:
        prepare(scenario, world_map, vehicle)
    except ScenarioError:
        return None
    return scenario


def _targets(world_map: Mapping[str, Any], vehicle: VehicleParams) -> tuple[list[_Slot], dict[Level, list[_Slot]]]:
    """The map's slots that open on a lane, and the free ones each level can aim at (the module docstring's rules).

    Returns:
        ``(slots, targets by level)``.

    Raises:
        ValueError: the map has no ``garage.lanes`` or no ``slots``.
    """
    lanes = (world_map.get("garage") or {}).get("lanes") or []
    if not lanes:
        raise ValueError("the map has no aisle lanes (garage.lanes): cannot place the ego in an aisle")
    if not world_map.get("slots"):
        raise ValueError("the map has no slots")
    blocked = Obstacles(world_map.get("obstacles", [])).corners()
    occupied = {int(s["id"]) for s in world_map["slots"] if s.get("occupied", False)}
    slots = [s for s in (_slot(m, lanes) for m in world_map["slots"]) if s is not None]
    easy = [s for s in slots if s.id not in occupied and _hosts(s, blocked, vehicle)]
    tight = [s for s in easy
             if (near := _neighbours(s, slots)) and all(n.id in occupied or not _hits(_car_in(n), blocked)
                                                          for n in near)]
    return slots, {"easy": easy, "medium": tight, "hard": tight}


def _default_name(scene: str) -> str:
    """``<scene folder's name>-graded``, with characters a set name refuses replaced by ``-``."""
    base = re.sub(r"[^A-Za-z0-9_.-]", "-", Path(scene).name).lstrip("-_.")
    return f"{base or 'scenarios'}-graded"


def make_set(world_map: Mapping[str, Any], scene: str, count: int, seed: int, name: str | None = None,
             difficulties: Sequence[str] = DIFFICULTIES, vehicle: VehicleParams = VehicleParams()) -> ScenarioSet:
    """A graded scenario set on a scene's map, by the rules of the module docstring.

    ``count`` is split evenly over ``difficulties`` in order, the remainder going to the first ones (``count=10``:
    4 easy, 3 medium, 3 hard); the scenarios are named ``easy_000``, ``medium_003``, ... and listed level by level.
    The same map, ``count`` and ``seed`` give an equal set.

    Args:
        world_map: the scene's ``map.json`` content (``garage.lanes``, ``slots``, ``obstacles``).
        scene: what every scenario names as its scene (a name under the scenes folder or a bundle path).
        count: how many scenarios, >= 1.
        seed: the set's seed, >= 0.
        name: the set's name; default ``<scene's folder name>-graded``.
        difficulties: the levels to make, each of ``DIFFICULTIES`` once.
        vehicle: the ego (its body for the start and slot checks).

    Returns:
        The set (write it with ``write_set``).

    Raises:
        ValueError: ``count`` < 1, a negative ``seed``, an empty ``scene``, a bad set name, an unknown or repeated
            level, a map without lanes or slots, no slot that can host a level asked for, or no scenario of a level
            found in ``TRIES`` draws.
    """
    if not isinstance(count, (int, np.integer)) or isinstance(count, bool) or count < 1:
        raise ValueError(f"count must be an integer >= 1, got {count!r}")
    if not isinstance(seed, (int, np.integer)) or isinstance(seed, bool) or seed < 0:
        raise ValueError(f"seed must be an integer >= 0, got {seed!r}")
    if not scene:
        raise ValueError("scene must name a scene bundle, got an empty string")
    unknown = [d for d in difficulties if d not in DIFFICULTIES]
    if not difficulties or unknown or len(set(difficulties)) != len(difficulties):
        raise ValueError(f"difficulties must be distinct levels of {', '.join(DIFFICULTIES)}, got "
                         f"{list(difficulties)}")
    levels = [cast(Level, d) for d in difficulties]
    set_name = _default_name(scene) if name is None else name
    if not re.fullmatch(NAME_PATTERN, set_name):
        raise ValueError(f"set name {set_name!r} must be letters, digits, _ . - (starting with a letter or digit)")
    slots, targets = _targets(world_map, vehicle)
    blocked = Obstacles(world_map.get("obstacles", [])).corners()
    per, rest = divmod(int(count), len(levels))
    scenarios = []
    for j, level in enumerate(levels):
        n = per + (j < rest)
        if n and not targets[level]:
            why = "" if level == "easy" else " with neighbours that can all be filled"
            raise ValueError(f"no free slot of the map fits {level} scenarios (facing an aisle lane, entrance and "
                             f"slot clear of obstacles{why})")
        for k in range(n):
            rng = np.random.default_rng(np.random.SeedSequence(int(seed), spawn_key=(DIFFICULTIES.index(level), k)))
            for _ in range(TRIES):
                target = targets[level][int(rng.integers(len(targets[level])))]
                made = _scenario(world_map, scene, level, k, target, slots, blocked, vehicle, rng)
                if made is not None:
                    scenarios.append(made)
                    break
            else:
                raise ValueError(f"no {level} scenario fits the map in {TRIES} draws (targets: "
                                 f"{[s.id for s in targets[level]]})")
    return ScenarioSet(set_name, tuple(scenarios))
