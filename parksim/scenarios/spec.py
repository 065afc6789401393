"""Scenario files: one closed-loop parking episode as YAML, validated into frozen typed models.

A scenario names the scene, where the ego starts (a pose, or a region drawn from with the seed), the target slot
(an id, or the free slot nearest the start), slots to fill with parked cars, the other road users (an asset, a
start pose and a behaviour each), the time limit and the success tolerances. A *set* is a folder of scenario files
plus ``index.yaml`` listing them. Unknown keys are errors, and every error is one line naming the file, the key path
and the value (as training configs, ``parksim.recon.config``). docs/scenarios.md describes the format.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Any, Literal

import numpy as np
import yaml
from pydantic import AfterValidator, BaseModel, ConfigDict, Field, ValidationError, model_validator

from ..fileio import atomic_directory, atomic_write
from .shapes import Box

__all__ = ["ScenarioError", "Scenario", "ActorSpec", "EgoStart", "Region", "Tolerance", "StaticSpec", "PathSpec",
           "LaneSpec", "PedestrianSpec", "TriggerSpec", "BehaviourSpec", "ScenarioSet", "BUILTIN_BOXES", "INDEX_NAME",
           "draw", "parse_scenario", "load_scenario", "dump_scenario", "load_set", "write_set", "load_scenarios",
           "scenario_schema"]

INDEX_NAME = "index.yaml"
"""The file of a scenario set's folder that lists its scenarios."""
BUILTIN_BOXES: dict[str, Box] = {"car": (-2.25, 2.25, -0.9, 0.9), "pedestrian": (-0.25, 0.25, -0.3, 0.3)}
"""Footprints of the built-in assets, ``(x_min, x_max, y_min, y_max)`` about the pose (the synthetic garage's
parked car is 4.5 m x 1.8 m; a walking adult takes about 0.5 m x 0.6 m)."""
_NAME = r"^[A-Za-z0-9][A-Za-z0-9_.-]*$"
"""Scenario and actor names: usable as file names."""


class ScenarioError(ValueError):
    """A scenario file or set is missing, not YAML, or does not validate; one line naming the file and the key."""


def _plain(value: float | tuple[float, ...]) -> str:
    """A number or a tuple as the file writes it: ``-1``, ``[2, 1]``."""
    return f"[{', '.join(f'{v:g}' for v in value)}]" if isinstance(value, tuple) else f"{value:g}"


def _ordered(span: tuple[float, float]) -> tuple[float, float]:
    """A ``[low, high]`` pair must not run backwards."""
    if span[0] > span[1]:
        raise ValueError(f"{_plain(span)} runs backwards: low above high")
    return span


def _positive(value: float | tuple[float, float]) -> float | tuple[float, float]:
    """Every number of a range is > 0."""
    if min(value if isinstance(value, tuple) else (value,)) <= 0:
        raise ValueError(f"must be > 0, got {_plain(value)}")
    return value


def _non_negative(value: float | tuple[float, float]) -> float | tuple[float, float]:
    """Every number of a range is >= 0."""
    if min(value if isinstance(value, tuple) else (value,)) < 0:
        raise ValueError(f"must be >= 0, got {_plain(value)}")
    return value


def _box(box: Box) -> Box:
    """A footprint box has positive length and width."""
    if not (box[0] < box[1] and box[2] < box[3]):
        raise ValueError(f"{_plain(box)} is not [x_min, x_max, y_min, y_max] with min < max")
    return box


Pose = tuple[float, float, float]
Point = tuple[float, float]
Span = Annotated[tuple[float, float], AfterValidator(_ordered)]
PositiveRange = Annotated[float | Span, AfterValidator(_positive)]
"""A number > 0, or ``[low, high]`` drawn uniformly with the scenario's seed (``draw``)."""
NonNegativeRange = Annotated[float | Span, AfterValidator(_non_negative)]
"""A number >= 0, or ``[low, high]`` drawn uniformly with the scenario's seed (``draw``)."""


def _waypoint(point: tuple[float, ...]) -> tuple[float, ...]:
    """``[x, y]`` or ``[x, y, 1]`` (forward), or ``[x, y, -1]`` (reverse)."""
    if len(point) not in (2, 3) or (len(point) == 3 and point[2] not in (1.0, -1.0)):
        raise ValueError(f"must be [x, y] or [x, y, -1] (reversing to it), got {_plain(point)}")
    return point


Waypoint = Annotated[tuple[float, ...], AfterValidator(_waypoint)]
"""``[x, y]`` driven forward, or ``[x, y, -1]``: the segment ending here is driven in reverse."""


def draw(value: float | tuple[float, float], rng: np.random.Generator) -> float:
    """The value of a range field: the number itself, or uniform in ``[low, high]``.

    One draw is taken either way, so turning one field from a number into a range leaves the others' draws as
    they were.

    Args:
        value: a number, or ``(low, high)``.
        rng: the actor's (or the ego's) generator.

    Returns:
        The drawn value.
    """
    u = float(rng.random())
    low, high = value if isinstance(value, tuple) else (value, value)
    return low + (high - low) * u if high > low else low


class _Strict(BaseModel):
    """Frozen, unknown keys are errors, numbers finite."""

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)


class StaticSpec(_Strict):
    """Stands at its start pose (a parked car, a pillar-like obstruction)."""

    type: Literal["static"] = "static"


class PathSpec(_Strict):
    """Drives along straight segments from its start pose through ``waypoints`` with a trapezoidal speed profile.

    The speed rises at ``accel`` to ``speed``, then falls at ``decel`` to stop at each change of direction and at
    the end. A reversing segment is driven backwards (the actor faces away from where it goes), as a car backing out
    of a slot. It ignores everyone else.
    """

    type: Literal["path"]
    waypoints: tuple[Waypoint, ...] = Field(min_length=1)
    speed: PositiveRange = Field(1.5, description="cruise speed, m/s")
    accel: float = Field(1.0, gt=0, description="m/s^2")
    decel: float = Field(1.5, gt=0, description="m/s^2")
    start_time: NonNegativeRange = Field(0.0, description="seconds standing before it moves")


class LaneSpec(_Strict):
    """Drives forward along its start pose and ``waypoints`` keeping its gap to whoever is ahead (IDM).

    The Intelligent Driver Model (Treiber et al. 2000) sets the acceleration from the gap to the first footprint
    (the ego's or another actor's) that its own footprint would touch further along the lane, and that one's speed
    along the lane; the lane's end counts as a standing obstacle, so it stops there.
    """

    type: Literal["lane"]
    waypoints: tuple[Point, ...] = Field(min_length=1)
    speed: PositiveRange = Field(2.0, description="desired speed v0, m/s")
    initial_speed: float = Field(0.0, ge=0, description="m/s")
    headway: float = Field(1.5, gt=0, description="desired time gap T, s")
    min_gap: float = Field(2.0, ge=0, description="standstill gap s0, m")
    accel: float = Field(1.0, gt=0, description="maximum acceleration a, m/s^2")
    decel: float = Field(1.5, gt=0, description="comfortable deceleration b, m/s^2")
    exponent: float = Field(4.0, gt=0, description="free-road exponent delta")


class TriggerSpec(_Strict):
    """When a pedestrian starts walking.

    At ``time``, or once the ego's footprint comes within ``distance`` of its own, whichever comes first.
    """

    time: NonNegativeRange | None = Field(None, description="seconds")
    distance: PositiveRange | None = Field(None, description="metres between the footprints")

    @model_validator(mode="after")
    def _some(self) -> TriggerSpec:
        """A trigger that can never fire is a mistake."""
        if self.time is None and self.distance is None:
            raise ValueError("give time, distance or both")
        return self


class PedestrianSpec(_Strict):
    """Walks in a straight line from its start pose to ``to`` at ``speed`` once triggered, then stands there."""

    type: Literal["pedestrian"]
    to: Point
    speed: PositiveRange = Field(1.4, description="m/s")
    trigger: TriggerSpec = TriggerSpec(time=0.0)


BehaviourSpec = Annotated[StaticSpec | PathSpec | LaneSpec | PedestrianSpec, Field(discriminator="type")]
"""A behaviour's parameters, told apart by ``type`` (the name in ``parksim.scenarios.behaviours.BEHAVIOURS``)."""


class ActorSpec(_Strict):
    """Another road user: an asset placed at ``pose`` and moved by its behaviour.

    ``pose`` is the asset's origin; ``box`` its footprint about it. Without ``box``, the footprint is the asset's
    own (``resolved_box``): a built-in asset's from ``BUILTIN_BOXES``, another's from its folder, given by whoever
    loads it.
    """

    name: str = Field(pattern=_NAME)
    asset: str = Field(min_length=1, description="an asset folder or PLY path, or a built-in name: car, pedestrian")
    pose: Pose
    box: Annotated[Box, AfterValidator(_box)] | None = None
    behaviour: BehaviourSpec = StaticSpec()

    @model_validator(mode="after")
    def _no_repeated_points(self) -> ActorSpec:
        """A path or walk must not stand still between two of its points (its heading would be undefined)."""
        b = self.behaviour
        points = (b.waypoints if isinstance(b, (PathSpec, LaneSpec)) else (b.to,) if isinstance(b, PedestrianSpec)
                  else ())
        before: tuple[float, ...] = self.pose[:2]
        for i, p in enumerate(points):
            if tuple(p[:2]) == before:
                key = "to" if isinstance(b, PedestrianSpec) else f"waypoints.{i}"
                raise ValueError(f"behaviour.{key}: {_plain(tuple(p))} repeats the point before it (pose or waypoint)")
            before = tuple(p[:2])
        return self

    def resolved_box(self, asset_boxes: Mapping[str, Box] | None = None) -> Box:
        """The actor's footprint: ``box``, else ``asset_boxes[asset]``, else the built-in asset's.

        Args:
            asset_boxes: footprints of assets read from their folders, by the ``asset`` string.

        Returns:
            ``(x_min, x_max, y_min, y_max)`` about the pose, metres.

        Raises:
            ScenarioError: no footprint is known for the asset.
        """
        known = {**BUILTIN_BOXES, **(asset_boxes or {})}
        if self.box is not None:
            return self.box
        if self.asset not in known:
            raise ScenarioError(f"actor {self.name!r}: no footprint for asset {self.asset!r}: give box: [x_min, "
                                f"x_max, y_min, y_max] or use a built-in asset ({', '.join(BUILTIN_BOXES)})")
        return known[self.asset]


class Region(_Strict):
    """Where a start pose is drawn from, uniformly in each coordinate."""

    x: Span
    y: Span
    yaw: Span = Field(description="radians")


class EgoStart(_Strict):
    """The ego's start: exactly one of a rear-axle ``pose`` or a ``region`` to draw it from with the seed."""

    pose: Pose | None = None
    region: Region | None = None

    @model_validator(mode="after")
    def _one(self) -> EgoStart:
        """Both or neither is ambiguous."""
        if (self.pose is None) == (self.region is None):
            raise ValueError("give exactly one of pose: [x, y, yaw] or region: {x, y, yaw}")
        return self


class Tolerance(_Strict):
    """When the ego counts as parked.

    The body centre within ``position`` of the slot centre, the heading within ``heading`` of the slot axis (either
    way), and stopped: the env's rule, whose ``pos_tol`` and ``yaw_tol`` are the defaults.
    """

    position: float = Field(0.35, gt=0, description="metres")
    heading: float = Field(math.degrees(0.15), gt=0, le=90, description="degrees")


class Scenario(_Strict):
    """One episode (see the module docstring and docs/scenarios.md)."""

    version: Literal[1] = Field(1, description="the file format's version")
    name: str = Field(pattern=_NAME)
    scene: str = Field(min_length=1, description="a scene bundle: a name under the scenes folder or a path")
    difficulty: Literal["easy", "medium", "hard"] = "easy"
    seed: int = Field(0, ge=0)
    ego: EgoStart
    target: int | Literal["nearest_free"] = Field("nearest_free", description="a free slot's id")
    occupy: tuple[int, ...] = Field((), description="slot ids filled with a parked car")
    actors: tuple[ActorSpec, ...] = ()
    time_limit: float = Field(50.0, gt=0, description="seconds")
    tolerance: Tolerance = Tolerance()

    @model_validator(mode="after")
    def _consistent(self) -> Scenario:
        """Actor names are unique, a slot is filled once, the target is not filled."""
        names = [a.name for a in self.actors]
        twice = sorted({n for n in names if names.count(n) > 1})
        if twice:
            raise ValueError(f"actors: names must be unique, repeated: {', '.join(twice)}")
        if len(set(self.occupy)) != len(self.occupy):
            raise ValueError(f"occupy: a slot is listed twice in {list(self.occupy)}")
        if self.target in self.occupy:
            raise ValueError(f"target: slot {self.target} is also in occupy")
        return self


def _key_path(loc: Sequence[int | str], data: Any) -> str:
    """``loc`` as the dotted key path in the file.

    Without the union members' tags pydantic adds (``float``, ``path``), which are not keys of the file.

    Returns:
        ``actors.1.behaviour.speed``.
    """
    keys: list[str] = []
    for i, part in enumerate(loc):
        if isinstance(data, dict) and part in data:
            keys.append(str(part))
            data = data[part]
        elif isinstance(data, list) and isinstance(part, int) and 0 <= part < len(data):
            keys.append(str(part))
            data = data[part]
        elif isinstance(data, dict) and i == len(loc) - 1:
            keys.append(str(part))            # a missing key
        elif isinstance(part, int):
            keys.append(str(part))
            data = None
    return ".".join(keys)


def _short(value: Any) -> str:
    """``repr`` cut to 60 characters."""
    text = repr(value)
    return text if len(text) <= 60 else text[:57] + "..."


def _format(err: ValidationError, data: Any) -> str:
    """One ``key.path: message, got value`` per key, joined on one line.

    A value that fits no member of a union fails once per member: the file's own rules (a range backwards, a
    reversed box) are kept over the type mismatches of the other members, whose messages are joined with "or".
    A list with a bad item also reports itself too short (the item is left out): only the item's error is kept.

    Returns:
        The line (without the file name).
    """
    by_key: dict[str, list[Any]] = {}
    for e in err.errors():
        by_key.setdefault(_key_path(e["loc"], data), []).append(e)
    for where in [w for w in by_key if any(k.startswith(f"{w}.") for k in by_key)]:
        # a list whose bad item was dropped also reports itself too short: the item's error says it all
        by_key[where] = [e for e in by_key[where] if e["type"] != "too_short"]
        if not by_key[where]:
            del by_key[where]
    lines = []
    for where, errors in by_key.items():
        own = [e for e in errors if e["type"] == "value_error"]
        msg = " or ".join(dict.fromkeys(str(e["msg"]).removeprefix("Value error, ") for e in own or errors))
        first = (own or errors)[0]
        shown = (own or first["type"] == "missing" or isinstance(first["input"], (dict, list)))
        text = msg if shown else f"{msg}, got {_short(first['input'])}"
        lines.append(f"{where}: {text}" if where else text)
    return "; ".join(lines)


def parse_scenario(data: object, source: str) -> Scenario:
    """Validate parsed YAML as a ``Scenario``.

    Args:
        data: the parsed YAML.
        source: what to name in errors (the file).

    Returns:
        The scenario.

    Raises:
        ScenarioError: not a mapping, or a key or value the format refuses (``source: key.path: message``).
    """
    if not isinstance(data, dict):
        raise ScenarioError(f"{source}: expected a mapping at the top level, got {type(data).__name__}")
    try:
        return Scenario.model_validate(data)
    except ValidationError as e:
        raise ScenarioError(f"{source}: {_format(e, data)}") from None


def _read_yaml(path: Path) -> Any:
    """The YAML content of ``path``, or a one-line ``ScenarioError``."""
    try:
        return yaml.safe_load(path.read_text())
    except OSError as e:
        raise ScenarioError(f"{path}: cannot read: {e.strerror or e}") from None
    except yaml.YAMLError as e:
        raise ScenarioError(f"{path}: not valid YAML: {' '.join(str(e).split())}") from None


def load_scenario(path: str | Path) -> Scenario:
    """Read and validate a scenario file.

    Args:
        path: the YAML file.

    Returns:
        The scenario.

    Raises:
        ScenarioError: the file is missing, not YAML, or does not validate.
    """
    path = Path(path)
    return parse_scenario(_read_yaml(path), str(path))


def _yaml(model: BaseModel) -> str:
    """Every field as YAML, in the models' order (floats written exactly, so reading gives the same numbers)."""
    return yaml.safe_dump(model.model_dump(mode="json"), sort_keys=False)


def dump_scenario(scenario: Scenario, path: str | Path) -> None:
    """Write a scenario file atomically; ``load_scenario`` reads back an equal scenario.

    Args:
        scenario: the scenario.
        path: the YAML file to write.
    """
    atomic_write(path, lambda p: p.write_text(_yaml(scenario)))


class _Entry(_Strict):
    """A line of a set's index."""

    file: str = Field(pattern=r"^[A-Za-z0-9][A-Za-z0-9_.-]*\.yaml$")
    name: str
    difficulty: Literal["easy", "medium", "hard"]


class _Index(_Strict):
    """A set's ``index.yaml``."""

    version: Literal[1] = 1
    name: str = Field(pattern=_NAME)
    scenarios: tuple[_Entry, ...] = Field(min_length=1)


@dataclass(frozen=True)
class ScenarioSet:
    """A named, ordered collection of scenarios (a folder of files and ``index.yaml`` on disk).

    Attributes:
        name: the set's name.
        scenarios: its scenarios, in index order.
    """

    name: str
    scenarios: tuple[Scenario, ...]


def write_set(folder: str | Path, scenario_set: ScenarioSet, overwrite: bool = False,
              extra: Callable[[Path], object] | None = None) -> Path:
    """Write a set: one ``NAME.yaml`` per scenario and ``index.yaml``, into a folder that appears whole.

    Args:
        folder: the set's folder.
        scenario_set: the set.
        overwrite: replace an existing folder.
        extra: writes more files into the folder (its temp folder, given as the argument) before it appears, such
            as thumbnails.

    Returns:
        The folder.

    Raises:
        ValueError: an empty set, a bad set name, or two scenarios of one name.
        FileExistsError: ``folder`` exists and ``overwrite`` is False.
    """
    names = [s.name for s in scenario_set.scenarios]
    if len(set(names)) != len(names):
        raise ValueError(f"scenario set {scenario_set.name!r}: scenario names must be unique (they name the files)")
    try:
        index = _Index(name=scenario_set.name, scenarios=tuple(
            _Entry(file=f"{s.name}.yaml", name=s.name, difficulty=s.difficulty) for s in scenario_set.scenarios))
    except ValidationError as e:
        raise ValueError(f"scenario set {scenario_set.name!r}: {_format(e, {})}") from None
    folder = Path(folder)
    with atomic_directory(folder, overwrite=overwrite) as tmp:
        for s in scenario_set.scenarios:
            (tmp / f"{s.name}.yaml").write_text(_yaml(s))
        (tmp / INDEX_NAME).write_text(_yaml(index))
        if extra is not None:
            extra(tmp)
    return folder


def load_set(folder: str | Path) -> ScenarioSet:
    """Read a set folder: its index and every scenario it lists (each must name itself as the index does).

    Args:
        folder: the set's folder.

    Returns:
        The set.

    Raises:
        ScenarioError: no index, an invalid index or scenario file, or a file that disagrees with its index line.
    """
    folder = Path(folder)
    index_path = folder / INDEX_NAME
    if not index_path.is_file():
        raise ScenarioError(f"{folder}: not a scenario set (no {INDEX_NAME})")
    data = _read_yaml(index_path)
    try:
        index = _Index.model_validate(data)
    except ValidationError as e:
        raise ScenarioError(f"{index_path}: {_format(e, data)}") from None
    scenarios = []
    for i, entry in enumerate(index.scenarios):
        s = load_scenario(folder / entry.file)
        if (s.name, s.difficulty) != (entry.name, entry.difficulty):
            raise ScenarioError(f"{index_path}: scenarios.{i}: lists {entry.name!r} ({entry.difficulty}) but "
                                f"{entry.file} holds {s.name!r} ({s.difficulty})")
        scenarios.append(s)
    return ScenarioSet(index.name, tuple(scenarios))


def load_scenarios(path: str | Path) -> list[Scenario]:
    """The scenarios at ``path``: one file, or every scenario of a set folder.

    Args:
        path: a scenario file or a set folder.

    Returns:
        The scenarios (one for a file), in index order.

    Raises:
        ScenarioError: as ``load_scenario`` or ``load_set``.
    """
    path = Path(path)
    return list(load_set(path).scenarios) if path.is_dir() else [load_scenario(path)]


def scenario_schema() -> dict[str, Any]:
    """The scenario format as a JSON Schema, for editors and tools outside Python.

    Returns:
        The schema (draft 2020-12) of a scenario file.
    """
    return Scenario.model_json_schema()
