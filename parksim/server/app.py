"""``create_app``: the FastAPI app over a scenes folder (or given bundles), with error mapping and metrics.

Errors are answered with ``{"detail": "..."}`` saying what is wrong and what is allowed:
400 a body that is not parseable JSON (malformed, not UTF-8, nested too deeply, an integer too long) or a key
in the query string, 422 bad request values (in a body that parsed), 404 unknown scene or route, 401 missing key,
421 a ``Host`` the server does not answer to (``Settings.allowed_hosts``), 413 body or reply too large (or a
render larger than the GPU's memory), 409 a step of an episode that is over, 503 (with Retry-After) when the render
queue, the reply budget, the episode store or the GPU's free memory is full.
"""

from __future__ import annotations

import sys
import time
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from fastapi.staticfiles import StaticFiles
from starlette.exceptions import HTTPException as StarletteHTTPException

from parksim.bundle import Bundle
from parksim.frames import RequestError
from parksim.render.device_memory import DeviceMemoryError
from parksim.scenarios.spec import ScenarioError
from parksim.sim import LocalSim

from .auth import host_name
from .budget import BudgetFull, ReplyBudget, ReplyTooLarge
from .docs import install_docs
from .episode_routes import episode_router
from .episodes import EpisodeError, EpisodeStore
from .gather import Gatherer
from .metrics import Metrics
from .pool import PoolBusy, RenderPool
from .routes import VIEWER_DIR, protected, router
from .scenes import SceneRegistry, UnknownScene
from .settings import Settings

__all__ = ["create_app"]


def _registry(scenes: str | Path | SceneRegistry | Mapping[str, Bundle | str | Path], strict: bool,
              device: str) -> SceneRegistry:
    """A registry from a scenes folder (``strict``: no bundle refused), a registry, or ``{id: bundle or folder}``."""
    if isinstance(scenes, SceneRegistry):
        return scenes
    if isinstance(scenes, Mapping):
        return SceneRegistry(LocalSim(b, scene_id, device) for scene_id, b in scenes.items())
    return SceneRegistry.from_dir(scenes, strict, device)


_BODY_PARSE_FAILED = "There was an error parsing the body"  # FastAPI's 400 when json.loads raises not a JSONDecodeError


def _json_invalid(exc: RequestValidationError) -> str | None:
    """The one-line reason when FastAPI's ``json.loads`` of the body failed (a syntax error), else None."""
    for err in exc.errors():
        if err.get("type") == "json_invalid":
            return (f"the request body is not valid JSON: {err.get('ctx', {}).get('error', 'parse error')} "
                    f"at character {err['loc'][-1]}")
    return None


def _unparsable(cause: BaseException | None) -> str:
    """Why a body that is not a JSON syntax error still failed ``json.loads`` (FastAPI keeps it as ``__cause__``)."""
    if isinstance(cause, RecursionError):
        return "the request body is not usable JSON: its arrays/objects are nested too deeply for the parser"
    if isinstance(cause, UnicodeDecodeError):
        return (f"the request body is not valid UTF-8: byte 0x{cause.object[cause.start]:02x} at offset {cause.start} "
                f"({cause.reason})")
    if isinstance(cause, ValueError) and "integer string conversion" in str(cause):
        return (f"the request body is not usable JSON: an integer has more than {sys.get_int_max_str_digits()} "
                "digits")
    return f"the request body could not be parsed as JSON: {cause!r}"


def _validation_message(exc: RequestValidationError) -> str:
    """Pydantic's errors as one readable line: where, what is wrong."""
    parts = []
    for err in exc.errors():
        loc = ".".join(str(p) for p in err.get("loc", ()) if p not in ("query", "body", "path"))
        msg = str(err.get("msg", "invalid value")).removeprefix("Value error, ")
        parts.append(f"{loc or 'request'}: {msg}")
    return "; ".join(parts)


def _error(status: int, detail: str, headers: dict[str, str] | None = None) -> JSONResponse:
    return JSONResponse({"detail": detail}, status_code=status, headers=headers)


def _install_errors(app: FastAPI) -> None:
    """Map request errors to 4xx/503 with a clear message."""

    @app.exception_handler(RequestValidationError)
    async def _invalid(_: Request, exc: RequestValidationError) -> JSONResponse:
        syntax = _json_invalid(exc)
        return _error(400, syntax) if syntax else _error(422, _validation_message(exc))

    @app.exception_handler(RequestError)
    @app.exception_handler(ScenarioError)
    async def _bad_request(_: Request, exc: RequestError | ScenarioError) -> JSONResponse:
        return _error(422, str(exc))

    @app.exception_handler(EpisodeError)
    async def _episode(_: Request, exc: EpisodeError) -> JSONResponse:
        return _error(exc.status, str(exc), exc.headers)

    @app.exception_handler(UnknownScene)
    async def _unknown_scene(_: Request, exc: UnknownScene) -> JSONResponse:
        return _error(404, str(exc.args[0]))

    @app.exception_handler(ReplyTooLarge)
    async def _too_large(_: Request, exc: ReplyTooLarge) -> JSONResponse:
        return _error(413, str(exc))

    @app.exception_handler(DeviceMemoryError)
    async def _gpu_memory(_: Request, exc: DeviceMemoryError) -> JSONResponse:
        return _error(413, str(exc)) if exc.never else _error(503, str(exc), {"Retry-After": str(exc.retry_after)})

    @app.exception_handler(PoolBusy)
    @app.exception_handler(BudgetFull)
    async def _busy(_: Request, exc: PoolBusy | BudgetFull) -> JSONResponse:
        return _error(503, str(exc), {"Retry-After": str(exc.retry_after)})

    @app.exception_handler(StarletteHTTPException)
    async def _http(request: Request, exc: StarletteHTTPException) -> JSONResponse:
        detail = exc.detail
        if exc.status_code == 404 and detail == "Not Found":
            detail = f"no route {request.url.path}; see /docs for the API"
        elif exc.status_code == 405:
            detail = f"method {request.method} is not allowed on {request.url.path}; see /docs"
        elif exc.status_code == 400 and detail == _BODY_PARSE_FAILED:
            detail = _unparsable(exc.__cause__)
        return _error(exc.status_code, str(detail), getattr(exc, "headers", None))


def _utf16_or_32(body: bytes) -> bool:
    """Whether ``body`` is UTF-16/32 text, which Python's JSON parser would otherwise detect and accept.

    UTF-8 JSON never holds a raw NUL byte (JSON escapes it), and UTF-16/32 text of ASCII JSON is full of them.

    Returns:
        True for a body with a NUL byte or a UTF-16 byte-order mark.
    """
    return b"\x00" in body or body.startswith((b"\xff\xfe", b"\xfe\xff"))


def _install_middleware(app: FastAPI, settings: Settings, metrics: Metrics) -> None:
    """Host check, body size limit and per-request metrics (labelled by route template, not by raw path)."""
    limit, hosts = settings.max_body_bytes, settings.allowed_hosts

    @app.middleware("http")
    async def _observe(request: Request, call_next: Any) -> Any:
        start = time.perf_counter()
        length = request.headers.get("content-length")
        bad_length = length is None or not length.isdigit() or int(length) > limit
        host = request.headers.get("host", "")
        if hosts is not None and host_name(host) not in hosts:
            response = _error(421, f"this server does not answer to Host {host!r}: use one of "
                                   f"{', '.join(hosts)} (a page reaching it through another name is refused)")
        elif request.method in ("POST", "PUT", "PATCH") and bad_length:
            response = _error(413 if length and length.isdigit() else 411,
                              f"the request body must come with a Content-Length of at most {limit} bytes")
        elif request.method in ("POST", "PUT", "PATCH") and _utf16_or_32(await request.body()):
            response = _error(400, "the request body is not UTF-8: it holds NUL bytes or a UTF-16/32 byte-order "
                                   "mark (JSON bodies must be UTF-8)")
        else:
            response = await call_next(request)
        route = request.scope.get("route")
        metrics.request(getattr(route, "path", "unmatched"), request.method, response.status_code,
                        time.perf_counter() - start)
        return response


def create_app(scenes: str | Path | SceneRegistry | Mapping[str, Bundle | str | Path],
               settings: Settings | None = None, strict: bool = False) -> FastAPI:
    """The simulator app serving ``scenes`` (loaded now, once) under ``settings`` (default limits).

    Args:
        scenes: a folder of scene bundles (one sub-folder each, its name the scene id), a ``SceneRegistry``,
            or ``{scene_id: Bundle or bundle folder}``.
        settings: limits, pool size, reply budgets, API key and device; ``Settings()`` when None.
        strict: with a scenes folder, fail on the first bundle that does not load; by default such a bundle is
            refused (logged as a warning, listed under ``refused`` in ``/scenes`` and ``/healthz``) and the
            others are served.

    Returns:
        A FastAPI app: ``GET/POST /render`` (npz of uint8 (H, W, 3) views, optional float32 (H, W) depth,
        the (h, w, 3) BEV), ``GET /render/{view}.{png,jpg}``, the episode API under ``/episodes``, ``/scenes``,
        ``/healthz``, ``/metrics``, the viewer at ``/`` and offline OpenAPI docs at ``/docs``; run it with uvicorn
        (``parksim serve`` does).

    Raises:
        BundleError: no scene to serve (every bundle refused), a missing scenes folder, or, with ``strict`` or
            given bundles, a bundle that does not load.
        DeviceError: ``settings.device`` is a bad name or a GPU this machine lacks.
    """
    settings = settings or Settings()
    registry = _registry(scenes, strict, settings.device)
    registry.warm_up()   # compile the kernels now, not under the first request's render timeout

    app = FastAPI(title="ParkSim simulator", version=__import__("parksim").__version__, docs_url=None, redoc_url=None,
                  description="Renders of reconstructed parking garages (four fisheye views and a BEV) at any ego "
                              "pose, for planners in closed loop. Poses are T_world_vehicle in metres and radians.")
    pool = RenderPool(settings.workers, settings.queue_size, settings.render_timeout_s, settings.retry_after_s)
    budget = ReplyBudget(settings.reply_budget_bytes, settings.retry_after_s)
    metrics = Metrics(pool.stats, budget.stats)
    gatherer = Gatherer(pool, settings.gather_window_ms / 1000, settings.max_batch, settings.jpeg_quality)
    # What parksim.server.deps hands to the handlers:
    app.state.settings, app.state.registry, app.state.pool, app.state.budget, app.state.metrics = (
        settings, registry, pool, budget, metrics)
    app.state.gatherer = gatherer
    app.state.episodes = EpisodeStore(settings.max_episodes, settings.episode_ttl_s)
    _install_errors(app)
    _install_middleware(app, settings, metrics)
    app.include_router(router)
    app.include_router(protected)
    app.include_router(episode_router)
    app.mount("/viewer", StaticFiles(directory=VIEWER_DIR), name="viewer")
    install_docs(app)
    return app
