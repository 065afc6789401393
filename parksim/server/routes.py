"""HTTP handlers: /render (GET one pose, POST a batch, single-view images), /scenes, /healthz, /metrics, viewer.

Handlers take their state through the typed dependencies of ``deps``; each route documents only the errors it
can answer.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Annotated, Any, Literal

from fastapi import APIRouter, Depends, Query
from fastapi import Path as PathParam
from fastapi.responses import FileResponse, Response

from parksim.frames import NPZ_LAYOUT

from .auth import require_api_key
from .deps import BudgetDep, MetricsDep, PoolDep, RegistryDep, RendererDep, SettingsDep
from .jobs import RenderJob
from .metrics import CONTENT_TYPE
from .replies import TIMING_HEADERS
from .scenes import SceneRegistry
from .schemas import (
    ErrorMessage,
    Health,
    RefusedScene,
    RenderBatchRequest,
    RenderQuery,
    SceneInfo,
    SceneList,
    SceneSummary,
    ViewQuery,
    parse_cameras,
    parse_pose,
)

__all__ = ["router", "VIEWER_DIR"]

VIEWER_DIR = Path(__file__).parent / "viewer"
_WHY = {400: "the body is not parseable JSON: malformed, not UTF-8, nested too deeply or an integer too long",
        401: "missing or wrong API key (only when the server was started with one)",
        404: "unknown scene (GET /scenes lists the loaded ones)",
        411: "a POST body without a Content-Length header",
        413: "the reply would exceed the server's max_reply_bytes per request (the message gives both sizes)",
        422: "an invalid request value (the message says which and what is allowed)",
        503: "the render queue or the reply budget is full, or a render timed out: retry after Retry-After seconds"}
_BODY_TOO_LARGE = "the body exceeds max_body_bytes, or " + _WHY[413].removeprefix("the ")
_BINARY = {"schema": {"type": "string", "format": "binary"}}
_NPZ_HELP = f"npz (uncompressed numpy.savez):\n\n```\n{NPZ_LAYOUT}\n```"


def _errors(*codes: int, too_large: str = _WHY[413], why: Mapping[int, str] | None = None
            ) -> dict[int | str, dict[str, Any]]:
    """OpenAPI ``responses`` for the error ``codes`` a route can answer (``too_large`` says what 413 means there,
    ``why`` what other codes mean there)."""
    texts = {**_WHY, 413: too_large, **(why or {})}
    out: dict[int | str, dict[str, Any]] = {}
    for code in codes:
        out[code] = {"model": ErrorMessage, "description": texts[code]}
        if code == 503:
            out[code]["headers"] = {"Retry-After": {"description": "seconds to wait before retrying",
                                                    "schema": {"type": "integer"}}}
    return out


def _reply(description: str, *media_types: str) -> dict[int | str, dict[str, Any]]:
    """OpenAPI 200 response of a render route: its media types and the X-Render-* headers."""
    return {200: {"description": description, "content": {m: _BINARY for m in media_types},
                  "headers": {name: {"description": text, "schema": {"type": "string"}}
                              for name, text in TIMING_HEADERS.items()}}}


router = APIRouter()
protected = APIRouter(dependencies=[Depends(require_api_key)])


@router.get("/healthz", response_model=Health,
            summary="liveness, loaded and refused scenes, pool and reply budget state, limits")
def healthz(registry: RegistryDep, settings: SettingsDep, pool: PoolDep, budget: BudgetDep) -> Health:
    return Health(status="ok", scenes=registry.ids, pool=pool.stats(), replies=budget.stats(),
                  limits={name: getattr(settings, name) for name in ("min_scale", "max_scale", "max_batch",
                                                                     "pose_margin_m", "max_tilt_rad",
                                                                     "max_reply_bytes")},
                  refused=_refused(registry))


@protected.get("/metrics", response_class=Response, summary="Prometheus metrics (text format 0.0.4)",
               responses={200: {"content": {CONTENT_TYPE: {"schema": {"type": "string"}}}}, **_errors(401)})
def metrics(m: MetricsDep) -> Response:
    return Response(m.text(), media_type=CONTENT_TYPE)


@protected.get("/scenes", response_model=SceneList, summary="the loaded scenes and the refused bundles",
               responses=_errors(401))
def scenes(registry: RegistryDep) -> SceneList:
    return SceneList(scenes=[SceneSummary(id=s.id, gaussians=len(s.bundle.scene), cameras=s.cameras)
                             for s in registry.sims.values()], refused=_refused(registry))


def _refused(registry: SceneRegistry) -> list[RefusedScene]:
    return [RefusedScene(id=scene_id, reason=reason) for scene_id, reason in registry.refused.items()]


@protected.get("/scenes/{scene_id}", response_model=SceneInfo, summary="rig, BEV spec, bounds and slot map of a scene",
               responses=_errors(401, 404, 422))
def scene_info(registry: RegistryDep, settings: SettingsDep,
               scene_id: Annotated[str, PathParam(max_length=200, description="scene id from GET /scenes")]
               ) -> SceneInfo:
    return SceneInfo(**registry.get(scene_id).info(), pose_margin_m=settings.pose_margin_m)


@protected.get("/render", response_class=Response, summary="render the requested views at one pose (npz, or one "
               "PNG/JPEG view)", responses={**_reply(f"{_NPZ_HELP}\n\nor, with format=png/jpeg, one view as an image",
                                                     "application/x-npz", "image/png", "image/jpeg"),
                                            **_errors(401, 404, 413, 422, 503)})
async def render_get(q: Annotated[RenderQuery, Query()], registry: RegistryDep, settings: SettingsDep,
                     renderer: RendererDep) -> Response:
    return await renderer.respond(RenderJob.build(registry, settings, q.scene, [parse_pose(q.pose)],
                                                  parse_cameras(q.cameras), q.bev, q.scale, q.depth, q.format))


@protected.post("/render", response_class=Response, summary="render the same views at a batch of poses in one "
                "request (npz, arrays stacked per pose)",
                responses={**_reply(_NPZ_HELP, "application/x-npz"),
                           **_errors(400, 401, 404, 411, 413, 422, 503, too_large=_BODY_TOO_LARGE)})
async def render_post(body: RenderBatchRequest, registry: RegistryDep, settings: SettingsDep,
                      renderer: RendererDep) -> Response:
    return await renderer.respond(RenderJob.build(registry, settings, body.scene, body.poses, body.cameras, body.bev,
                                                  body.scale, body.depth, batch=True, actors=body.actors))


@protected.get("/render/{view}.{ext}", response_class=Response, summary="one view as an image: a camera name or 'bev'",
               responses={**_reply("the view as a PNG or JPEG image", "image/png", "image/jpeg"),
                          **_errors(401, 404, 413, 422, 503)})
async def render_view(view: Annotated[str, PathParam(max_length=100, description="camera name, or bev")],
                      ext: Annotated[Literal["png", "jpg", "jpeg"], PathParam(description="image format")],
                      q: Annotated[ViewQuery, Query()], registry: RegistryDep, settings: SettingsDep,
                      renderer: RendererDep) -> Response:
    bev = view == "bev"
    return await renderer.respond(RenderJob.build(registry, settings, q.scene, [parse_pose(q.pose)],
                                                  [] if bev else [view], bev, q.scale, False,
                                                  "png" if ext == "png" else "jpeg"))


@router.get("/", include_in_schema=False)
def viewer() -> FileResponse:
    return FileResponse(VIEWER_DIR / "index.html", headers={"Cache-Control": "no-cache"})
