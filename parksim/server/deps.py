"""Typed request dependencies: handlers name what they need (``RegistryDep``, ``SettingsDep``, ...) and never read
``app.state`` themselves, so a test can swap any of them through ``app.dependency_overrides[get_x]``."""

from __future__ import annotations

from typing import Annotated

from fastapi import Depends, Request

from .budget import ReplyBudget
from .episodes import EpisodeStore
from .metrics import Metrics
from .pool import RenderPool
from .replies import Renderer
from .scenes import SceneRegistry
from .settings import Settings

__all__ = ["get_settings", "get_registry", "get_pool", "get_budget", "get_metrics", "get_renderer", "get_episodes",
           "SettingsDep", "RegistryDep", "PoolDep", "BudgetDep", "MetricsDep", "RendererDep", "EpisodesDep"]


def get_settings(request: Request) -> Settings:
    return request.app.state.settings


def get_registry(request: Request) -> SceneRegistry:
    return request.app.state.registry


def get_pool(request: Request) -> RenderPool:
    return request.app.state.pool


def get_budget(request: Request) -> ReplyBudget:
    return request.app.state.budget


def get_metrics(request: Request) -> Metrics:
    return request.app.state.metrics


def get_episodes(request: Request) -> EpisodeStore:
    return request.app.state.episodes


SettingsDep = Annotated[Settings, Depends(get_settings)]
RegistryDep = Annotated[SceneRegistry, Depends(get_registry)]
PoolDep = Annotated[RenderPool, Depends(get_pool)]
BudgetDep = Annotated[ReplyBudget, Depends(get_budget)]
MetricsDep = Annotated[Metrics, Depends(get_metrics)]
EpisodesDep = Annotated[EpisodeStore, Depends(get_episodes)]


def get_renderer(request: Request, pool: PoolDep, budget: BudgetDep, metrics: MetricsDep, settings: SettingsDep
                 ) -> Renderer:
    """The render pool, reply budget and metrics a render handler answers through."""
    return Renderer(pool, budget, metrics, settings.jpeg_quality, request.app.state.gatherer, settings.gather)


RendererDep = Annotated[Renderer, Depends(get_renderer)]
