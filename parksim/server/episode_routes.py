"""HTTP handlers of the episode API: a scenario driven step by step by a client in any language.

``POST /episodes`` (a scenario -> id and the first observation), ``POST /episodes/{id}/step`` (an action -> the
observation, reward, done), ``GET /episodes/{id}/result`` (the scorecard), ``DELETE /episodes/{id}``. The work runs
on the render pool, an observation's bytes are held in the reply budget until sent, and the API key applies as on
``/render``; docs/episode_api.md describes the API.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Annotated

from fastapi import APIRouter, Depends
from fastapi import Path as PathParam
from fastapi.responses import Response

from .auth import require_api_key
from .budget import ReplyBudget
from .deps import BudgetDep, EpisodesDep, PoolDep, RegistryDep, SettingsDep
from .episodes import open_episode
from .pool import RenderPool
from .replies import BudgetedResponse
from .routes import _errors
from .schemas import EpisodeCreated, EpisodeRequest, EpisodeResult, StepReply, StepRequest

__all__ = ["episode_router"]

EpisodeId = Annotated[str, PathParam(max_length=64, description="the id POST /episodes answered")]
_UNKNOWN = "no live episode has this id: it was never made, was deleted, or expired (episode_ttl_s without a request)"
_BUSY = "the render queue, the reply budget or the episode store (max_episodes) is full: retry after Retry-After s"
_BODY = "the body exceeds max_body_bytes"

episode_router = APIRouter(prefix="/episodes", dependencies=[Depends(require_api_key)])


async def _answer(pool: RenderPool, budget: ReplyBudget, nbytes: int, work: Callable[[], bytes],
                  status: int = 200) -> Response:
    """Run ``work`` (JSON bytes) on ``pool`` with ``nbytes`` of reply reserved in ``budget`` until sent."""
    reservation = budget.reserve(nbytes)
    try:
        body, _ = await pool.run(work)
    except BaseException:
        reservation.release()
        raise
    response = BudgetedResponse(body, reservation, "application/json", {"Cache-Control": "no-store"})
    response.status_code = status
    return response


@episode_router.post("", status_code=201, response_model=EpisodeCreated,
                     summary="start an episode of a scenario: its id and first observation",
                     responses=_errors(400, 401, 404, 411, 413, 422, 503, why={
                         404: "the scenario's scene is not loaded (GET /scenes lists the loaded ones)",
                         413: f"{_BODY}, or one observation would exceed max_reply_bytes", 503: _BUSY}))
async def create_episode(body: EpisodeRequest, registry: RegistryDep, settings: SettingsDep, pool: PoolDep,
                         budget: BudgetDep, episodes: EpisodesDep) -> Response:
    with episodes.opening() as add:
        live, _ = await pool.run(lambda: open_episode(registry, settings, body))
        response = await _answer(pool, budget, live.reply_bytes, lambda: live.first(body.seed), 201)
        add(live)
    return response


@episode_router.post("/{episode_id}/step", response_model=StepReply,
                     summary="apply one action for one time step (0.1 s): the observation, reward and done",
                     responses=_errors(400, 401, 404, 409, 411, 413, 422, 503, why={
                         404: _UNKNOWN, 409: "the episode is over: its result is final", 413: _BODY,
                         503: "the render queue or the reply budget is full: retry after Retry-After seconds"}))
async def step_episode(episode_id: EpisodeId, body: StepRequest, pool: PoolDep, budget: BudgetDep,
                       episodes: EpisodesDep) -> Response:
    with episodes.using(episode_id) as live:
        if live.episode.done:
            raise live.over()
        return await _answer(pool, budget, live.reply_bytes, lambda: live.step(body.action))


@episode_router.get("/{episode_id}/result", response_model=EpisodeResult,
                    summary="the episode's scorecard so far (final once done)",
                    responses=_errors(401, 404, 422, 503, why={
                        404: _UNKNOWN, 503: "the render queue is full: retry after Retry-After seconds"}))
async def episode_result(episode_id: EpisodeId, pool: PoolDep, episodes: EpisodesDep) -> Response:
    with episodes.using(episode_id) as live:
        body, _ = await pool.run(live.result)
    return Response(body, media_type="application/json", headers={"Cache-Control": "no-store"})


@episode_router.delete("/{episode_id}", status_code=204, response_class=Response,
                       summary="drop an episode (it is dropped anyway after episode_ttl_s without a request)",
                       responses=_errors(401, 404, 422, why={404: _UNKNOWN}))
async def delete_episode(episode_id: EpisodeId, episodes: EpisodesDep) -> Response:
    episodes.delete(episode_id)
    return Response(status_code=204)
