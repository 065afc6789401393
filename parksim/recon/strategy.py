"""Densification strategies by name (``densify.strategy`` in the config): the registry the trainer builds from."""

from __future__ import annotations

from .config import ConfigError, DensifyConfig
from .strategy_adc import ADCStrategy
from .strategy_base import StepInfo, Strategy, ViewInfo
from .strategy_mcmc import MCMCStrategy

__all__ = ["STRATEGIES", "make_strategy", "Strategy", "StepInfo", "ViewInfo"]

STRATEGIES: dict[str, type[Strategy]] = {"mcmc": MCMCStrategy, "adc": ADCStrategy}


def make_strategy(densify: DensifyConfig, extent: float) -> Strategy:
    """The strategy ``densify.strategy`` names, built from ``densify`` and the scene extent (m)."""
    try:
        cls = STRATEGIES[densify.strategy]
    except KeyError:
        raise ConfigError(f"densify.strategy: unknown strategy {densify.strategy!r}; "
                          f"choose one of {', '.join(STRATEGIES)}") from None
    return cls(densify, extent)
