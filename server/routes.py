"""HTTP handlers: /render (GET one pose, POST a batch, single-view images), /scenes, /healthz, /metrics, viewer."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Literal

from fastapi import APIRouter, Depends, Path as PathParam, Query, Request
from fastapi.responses import FileResponse, PlainTextResponse, Response

from .auth import require_api_key
from .jobs import RenderJob, Reply
from .metrics import CONTENT_TYPE
from .schemas import (ErrorMessage, Health, RenderBatchRequest, RenderQuery, SceneInfo, SceneList, SceneSummary,
                      ViewQuery, parse_cameras, parse_pose)

__all__ = ["router", "VIEWER_DIR"]

VIEWER_DIR = Path(__file__).parent / "viewer"
_ERRORS = {code: {"model": ErrorMessage} for code in (401, 404, 413, 422, 503)}
_IMAGE_REPLY = {200: {"content": {"application/x-npz": {}, "image/png": {}, "image/jpeg": {}},
                      "description": "npz (uint8 images, float32 depth, JSON meta) or one PNG/JPEG image"}}
router = APIRouter(responses=_ERRORS)
protected = APIRouter(dependencies=[Depends(require_api_key)], responses=_ERRORS)


def _response(request: Request, reply: Reply) -> Response:
    """The reply with its timing headers; the job's stage times go to the metrics."""
    t = reply.meta.timings_ms
    n_images = len(reply.meta.cameras) + int(reply.meta.bev)
    request.app.state.metrics.render({k: v / 1000 for k, v in t.items()}, n_images * len(reply.meta.poses))
    headers = {"X-Render-Timings": ", ".join(f"{k}={v:.1f}ms" for k, v in t.items()),
               "X-Render-Time-Ms": f"{t.get('views', 0) + t.get('bev', 0):.1f}", "Cache-Control": "no-store"}
    return Response(reply.body, media_type=reply.media_type, headers=headers)


async def _run(request: Request, job: RenderJob) -> Response:
    state = request.app.state
    return _response(request, await job.run(state.pool, state.settings.jpeg_quality))


@router.get("/healthz", response_model=Health, summary="liveness, loaded scenes, pool state and limits")
def healthz(request: Request) -> Health:
    s = request.app.state.settings
    return Health(status="ok", scenes=request.app.state.registry.ids, pool=request.app.state.pool.stats(),
                  limits={"min_scale": s.min_scale, "max_scale": s.max_scale, "max_batch": s.max_batch,
                          "pose_margin_m": s.pose_margin_m, "max_tilt_rad": s.max_tilt_rad})


@protected.get("/metrics", response_class=PlainTextResponse, summary="Prometheus metrics (text format 0.0.4)")
def metrics(request: Request) -> PlainTextResponse:
    return PlainTextResponse(request.app.state.metrics.text(request.app.state.pool.stats()), media_type=CONTENT_TYPE)


@protected.get("/scenes", response_model=SceneList, summary="the loaded scenes")
def scenes(request: Request) -> SceneList:
    sims = request.app.state.registry.sims.values()
    return SceneList(scenes=[SceneSummary(id=s.id, gaussians=len(s.bundle.scene), cameras=s.cameras) for s in sims])


@protected.get("/scenes/{scene_id}", response_model=SceneInfo, summary="rig, BEV spec, bounds and slot map of a scene")
def scene_info(request: Request, scene_id: Annotated[str, PathParam(description="scene id from GET /scenes")]
               ) -> SceneInfo:
    sim = request.app.state.registry.get(scene_id)
    return SceneInfo(**sim.info(), pose_margin_m=request.app.state.settings.pose_margin_m)


@protected.get("/render", responses=_IMAGE_REPLY, response_class=Response,
               summary="render the requested views at one pose (npz, or one PNG/JPEG view)")
async def render_get(request: Request, q: Annotated[RenderQuery, Query()]) -> Response:
    state = request.app.state
    job = RenderJob.build(state.registry, state.settings, q.scene, [parse_pose(q.pose)], parse_cameras(q.cameras),
                          q.bev, q.scale, q.depth, q.format)
    return await _run(request, job)


@protected.post("/render", responses=_IMAGE_REPLY, response_class=Response,
                summary="render the same views at a batch of poses in one request (npz, arrays stacked per pose)")
async def render_post(request: Request, body: RenderBatchRequest) -> Response:
    state = request.app.state
    job = RenderJob.build(state.registry, state.settings, body.scene, body.poses, body.cameras, body.bev, body.scale,
                          body.depth, batch=True)
    return await _run(request, job)


@protected.get("/render/{view}.{ext}", responses=_IMAGE_REPLY, response_class=Response,
               summary="one view as an image: a camera name or 'bev'")
async def render_view(request: Request,
                      view: Annotated[str, PathParam(max_length=100, description="camera name, or bev")],
                      ext: Annotated[Literal["png", "jpg", "jpeg"], PathParam(description="image format")],
                      q: Annotated[ViewQuery, Query()]) -> Response:
    state = request.app.state
    bev = view == "bev"
    job = RenderJob.build(state.registry, state.settings, q.scene, [parse_pose(q.pose)], [] if bev else [view], bev,
                          q.scale, False, "png" if ext == "png" else "jpeg")
    return await _run(request, job)


@router.get("/", include_in_schema=False)
def viewer() -> FileResponse:
    return FileResponse(VIEWER_DIR / "index.html", headers={"Cache-Control": "no-cache"})
