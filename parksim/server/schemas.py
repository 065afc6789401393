"""Request and response models of the simulator API (pydantic); the handlers in ``routes`` only use them."""

from __future__ import annotations

import math
import re
from typing import Annotated, Any, Literal

from pydantic import AfterValidator, BaseModel, ConfigDict, Field, FiniteFloat, model_validator

from parksim.scenarios.spec import BUILTIN_BOXES

__all__ = ["Pose", "parse_number", "parse_pose", "parse_cameras", "RenderQuery", "ViewQuery", "RenderBatchRequest",
           "RenderMeta", "SceneSummary", "RefusedScene", "SceneList", "SceneInfo", "Health", "ErrorMessage",
           "POSE_HELP", "builtin_asset", "PlacedActor", "EpisodeRequest", "StepRequest", "Observation",
           "EpisodeCreated", "StepReply", "EpisodeResult"]

POSE_HELP = ("ego pose T_world_vehicle as 'x,y,yaw' (metres, radians; z = roll = pitch = 0) or "
             "'x,y,z,roll,pitch,yaw'; yaw about world z, rotation Rz(yaw) Ry(pitch) Rx(roll)")
_MAX_POSE_TEXT = 200
_DECIMAL = re.compile(r"[+-]?(?:[0-9]+(?:\.[0-9]*)?|\.[0-9]+)(?:[eE][+-]?[0-9]+)?")
"""ASCII decimal float syntax: no digit separators ('1_0'), no other scripts' digits, no 'nan' or 'inf'."""


def parse_number(text: str) -> float:
    """A finite pose value written as an ASCII decimal (``ValueError`` otherwise); the one parser of pose text."""
    if not _DECIMAL.fullmatch(text.strip(" \t")):
        raise ValueError(f"pose value {text!r} is not a number in decimal notation (finite; ASCII digits 0-9 with an "
                         f"optional sign, point and exponent)")
    value = float(text)
    if not math.isfinite(value):
        raise ValueError(f"pose value {text!r} is not finite; every pose value must be a finite number")
    return value


def _pose_value(value: Any) -> Any:
    """Text through ``parse_number``; a JSON boolean refused (pydantic would take ``true`` as 1.0); else as given."""
    if isinstance(value, bool):
        raise ValueError(f"pose value {value!r} is a boolean, not a number")
    return parse_number(value) if isinstance(value, str) else value


class Pose(BaseModel):
    """An ego pose: position (m) of the rear-axle centre on the ground and orientation (rad)."""

    model_config = ConfigDict(extra="forbid")
    x: FiniteFloat
    y: FiniteFloat
    z: FiniteFloat = 0.0
    roll: FiniteFloat = 0.0
    pitch: FiniteFloat = 0.0
    yaw: FiniteFloat

    @model_validator(mode="before")
    @classmethod
    def _from_list(cls, value: Any) -> Any:
        """Accept ``[x, y, yaw]`` and ``[x, y, z, roll, pitch, yaw]`` as well as an object; text values go
        through ``parse_number``."""
        if isinstance(value, (list, tuple)):
            if len(value) not in (3, 6):
                raise ValueError(f"a pose list needs 3 values (x, y, yaw) or 6 (x, y, z, roll, pitch, yaw), "
                                 f"got {len(value)}")
            value = dict(zip(("x", "y", "yaw") if len(value) == 3 else ("x", "y", "z", "roll", "pitch", "yaw"), value))
        if isinstance(value, dict):
            return {k: _pose_value(v) for k, v in value.items()}
        return value

    def values(self) -> list[float]:
        """``[x, y, z, roll, pitch, yaw]``."""
        return [self.x, self.y, self.z, self.roll, self.pitch, self.yaw]


def parse_pose(text: str) -> Pose:
    """``'x,y,yaw'`` or ``'x,y,z,roll,pitch,yaw'`` -> ``Pose``; ``ValueError`` says what is wrong."""
    if len(text) > _MAX_POSE_TEXT:
        raise ValueError(f"pose text is longer than {_MAX_POSE_TEXT} characters")
    parts = text.split(",")
    if len(parts) not in (3, 6):
        raise ValueError(f"pose needs 3 comma-separated numbers (x,y,yaw) or 6 (x,y,z,roll,pitch,yaw), "
                         f"got {len(parts)} in {text!r}")
    return Pose.model_validate([parse_number(p) for p in parts])


def parse_cameras(text: str | None) -> list[str] | None:
    """``'front,left'`` -> ``['front', 'left']``; '' -> [] (no camera: BEV only); None -> None (all cameras)."""
    if text is None:
        return None
    return [n.strip() for n in text.split(",") if n.strip()]


def _checked(parse: Any) -> AfterValidator:
    """A validator that runs ``parse`` for its errors and keeps the text as given."""
    return AfterValidator(lambda v: (parse(v), v)[1])


PoseText = Annotated[str, _checked(parse_pose)]
CamerasText = Annotated[str | None, _checked(parse_cameras)]

_SCENE = Field(None, max_length=200, description="scene id (GET /scenes); default: the first scene")
_SCALE = Field(1.0, description="resolution factor of the fisheye views (1 = the rig's size); the server's "
                                "limits are in GET /healthz")
_DEPTH = Field(False, description="also return per-camera depth (float32, metres along the ray; npz only)")


class RenderQuery(BaseModel):
    """Query of ``GET /render``: what to render, where, and how to encode it."""

    model_config = ConfigDict(extra="forbid")
    pose: PoseText = Field(..., max_length=_MAX_POSE_TEXT, description=POSE_HELP, examples=["12.0,0.5,0.0"])
    scene: str | None = _SCENE
    cameras: CamerasText = Field(None, max_length=1000, description="comma-separated camera names (default: all "
                                "of the rig; empty: none, e.g. with bev=on for the BEV only)")
    bev: bool = Field(False, description="also render the bird's-eye view (on/off, true/false, 1/0)")
    scale: float = _SCALE
    depth: bool = _DEPTH
    format: Literal["npz", "png", "jpeg"] = Field("npz", description="npz: uint8 images + metadata for programs; "
                                                  "png/jpeg: one image, so exactly one view must be asked for")


class ViewQuery(BaseModel):
    """Query of ``GET /render/{view}.{ext}``: one camera (or ``bev``) as an image file."""

    model_config = ConfigDict(extra="forbid")
    pose: PoseText = Field(..., max_length=_MAX_POSE_TEXT, description=POSE_HELP, examples=["12.0,0.5,0.0"])
    scene: str | None = _SCENE
    scale: float = _SCALE


def builtin_asset(name: str, where: str = "asset") -> str:
    """``name`` when it is a built-in actor asset; over HTTP no other is accepted, since any other names a file.

    Args:
        name: an actor's ``asset``.
        where: what to call it in the error (the key path).

    Returns:
        ``name``.

    Raises:
        ValueError: not a built-in asset (one line naming the accepted ones).
    """
    if name not in BUILTIN_BOXES:
        raise ValueError(f"{where}: {name!r} is not a built-in asset; over HTTP only {', '.join(BUILTIN_BOXES)} are "
                         f"accepted (the server reads no file a request names)")
    return name


class PlacedActor(BaseModel):
    """A built-in actor asset standing at a world pose, drawn into every view of a ``POST /render``."""

    model_config = ConfigDict(extra="forbid")
    asset: Annotated[str, AfterValidator(builtin_asset)] = Field(
        ..., json_schema_extra={"enum": list(BUILTIN_BOXES)}, description="a built-in asset")
    pose: Pose = Field(..., description="T_world_actor as [x, y, yaw], [x, y, z, roll, pitch, yaw] or an object "
                                        "(metres, radians)")


class RenderBatchRequest(BaseModel):
    """Body of ``POST /render``: several poses rendered with the same options, answered as one npz."""

    model_config = ConfigDict(extra="forbid")
    poses: list[Pose] = Field(..., min_length=1, max_length=1024,
                              description="poses as [x, y, yaw], [x, y, z, roll, pitch, yaw] or objects; "
                                          "the server's batch limit is in GET /healthz")
    scene: str | None = _SCENE
    cameras: list[str] | None = Field(None, max_length=64, description="camera names (default: all; []: none)")
    bev: bool = Field(False, description="also render the bird's-eye view")
    scale: float = _SCALE
    depth: bool = _DEPTH
    actors: list[PlacedActor] = Field(default_factory=list, max_length=64, description="actors drawn with the "
                                      "scene at every pose (in the views, the BEV and depth)")


_Action = Annotated[float, Field(strict=True, allow_inf_nan=False)]
"""A JSON number, finite (strict: no string, no boolean)."""


class EpisodeRequest(BaseModel):
    """Body of ``POST /episodes``: a scenario and what each observation holds."""

    model_config = ConfigDict(extra="forbid")
    scenario: dict[str, Any] | str = Field(..., description="the scenario: its fields as an object (as in its "
                                           "YAML file), or the text of a scenario file (YAML or JSON; no "
                                           "anchors/aliases). Its scene is a loaded scene id (GET /scenes); actor "
                                           "assets are built-in names only")
    cameras: list[str] | None = Field(None, max_length=64, description="views in each observation (default: all "
                                      "of the rig; []: none)")
    bev: bool = Field(False, description="add the bird's-eye view to each observation")
    scale: float = Field(0.25, description="resolution factor of the views (the server's limits are in "
                                           "GET /healthz)")
    privileged: bool = Field(False, description="add the world pose [x, y, yaw] to each observation and info")
    image_format: Literal["png", "jpeg"] = Field("png", description="encoding of the views (base64 in the JSON): "
                                                 "png is lossless, jpeg smaller")
    seed: int | None = Field(None, ge=0, description="replaces the scenario's seed (its start region and actor "
                             "ranges are drawn from it)")


class StepRequest(BaseModel):
    """Body of ``POST /episodes/{id}/step``."""

    model_config = ConfigDict(extra="forbid")
    action: list[_Action] = Field(..., min_length=2, max_length=2, description="[acceleration, steering], "
                                 "normalised to [-1, 1] (clipped)")


class Observation(BaseModel):
    """What the ego sees after a reset or a step."""

    state: list[float] = Field(description="[v (m/s), steer (rad), slot_x, slot_y (m), slot_yaw (rad)]: the ego's "
                                           "speed and steering, the target slot in the ego frame")
    pose: list[float] | None = Field(None, description="[x, y, yaw] in the world, when privileged")
    images: dict[str, str] = Field(description="camera name -> base64 PNG/JPEG (uint8 RGB)")
    bev: str | None = Field(None, description="base64 PNG/JPEG of the bird's-eye view, when asked")


_INFO = ("slot, distance, heading_error, collision, is_success, speed, actor_collision, truncated, time (and pose "
         "when privileged); the scorecard once done")


class EpisodeCreated(BaseModel):
    """``POST /episodes``: the episode's id and its first observation."""

    id: str = Field(description="the episode's id in the other /episodes routes")
    observation: Observation
    info: dict[str, Any] = Field(description=_INFO + "; scenario (its name)")


class StepReply(BaseModel):
    """``POST /episodes/{id}/step``: as gymnasium's ``step`` (``done`` = the episode is over)."""

    observation: Observation
    reward: float
    done: bool = Field(description="parked, touched something, or out of time: the episode is over")
    truncated: bool = Field(description="the scenario's time limit ended it")
    info: dict[str, Any] = Field(description=_INFO)


class EpisodeResult(BaseModel):
    """``GET /episodes/{id}/result``: the scorecard so far (final once done; docs/scenarios.md defines it)."""

    id: str
    scenario: str
    done: bool
    scorecard: dict[str, Any]


class RenderMeta(BaseModel):
    """The ``meta`` entry of a render npz (also summarised in X-Render-* headers)."""

    scene: str
    poses: list[Pose]
    cameras: list[str]
    bev: bool
    scale: float
    sizes: dict[str, list[int]] = Field(description="[width, height] per returned view")
    timings_ms: dict[str, float] = Field(description="queue, views, bev, encode")
    gathered: int = Field(1, description="requests rendered together with this one (parksim.server.gather): 1 when "
                          "it was rendered alone")


class SceneSummary(BaseModel):
    """One entry of ``GET /scenes``."""

    id: str
    gaussians: int
    cameras: list[str]


class RefusedScene(BaseModel):
    """A bundle under the scenes folder that did not load, so is not served."""

    id: str = Field(description="the bundle folder's name")
    reason: str = Field(description="the one-line load error, naming the bad file")


_REFUSED = "bundles under the scenes folder that did not load, so are not served (empty when all loaded)"


class SceneList(BaseModel):
    scenes: list[SceneSummary]
    refused: list[RefusedScene] = Field(default_factory=list, description=_REFUSED)


class SceneInfo(BaseModel):
    """``GET /scenes/{id}``: rig (cameras, intrinsics, extrinsics), BEV spec, bounds, slot map, metadata."""

    id: str
    gaussians: int
    cameras: list[str]
    rig: dict[str, Any]
    bev: dict[str, Any]
    bounds: dict[str, list[float]] = Field(description="scene extent per axis (m); poses may lie up to "
                                                       "pose_margin_m outside it in x and y")
    pose_margin_m: float
    map: dict[str, Any] | None = Field(description="world slot map and obstacles (parksim synth map.json), if any")
    meta: dict[str, Any]
    recorded_path: list[list[float]] | None = Field(None, description="the ego path the dataset was recorded along, "
                                                    "[[x, y, yaw], ...] (m, rad; at most 256 evenly spaced frames): "
                                                    "renders are sharpest near it; None when the bundle has none")
    footprint: list[float] = Field(description="ego body in the vehicle frame (m): [x_min, x_max, y_min, y_max]")
    dropped: dict[str, int] = Field(default_factory=dict, description="absurd Gaussians dropped when the bundle "
                                    "loaded, per reason (mean, scale, opacity); empty when none was")


class Health(BaseModel):
    """``GET /healthz``: liveness, loaded scenes, render pool state and request limits."""

    status: Literal["ok"]
    scenes: list[str]
    pool: dict[str, int]
    replies: dict[str, int] = Field(description="reply byte budget: budget_bytes, in_flight_bytes (reserved by "
                                                "replies being rendered or sent), rejected (answered 503)")
    limits: dict[str, float]
    refused: list[RefusedScene] = Field(default_factory=list, description=_REFUSED)


class ErrorMessage(BaseModel):
    """Every 4xx/503 body: what was wrong and what is allowed."""

    detail: str
