"""The contract of a densification strategy (as gsplat's ``strategy/base.py``): three hooks around each step.

The trainer calls, per iteration, ``step_pre_backward`` (the strategy's loss term), ``step_post_backward``
(after ``loss.backward()``, before the optimizer: gradients are there, parameters not yet moved) and
``step_post_update`` (after the optimizer step: grow, prune, relocate), each with the same ``StepInfo``.
A new strategy is one subclass plus its name in ``parksim.recon.strategy.STRATEGIES``.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass
from typing import Any

import torch
from torch import Tensor

from .config import DensifyConfig
from .params import GaussianParams

__all__ = ["Strategy", "StepInfo", "ViewInfo"]


@dataclass(frozen=True)
class ViewInfo:
    """A view rendered this step: camera centre in the world ``[3]`` (on the Gaussians' device), focal length and
    image width in pixels."""

    centre: Tensor
    focal: float
    width: int


@dataclass(frozen=True)
class StepInfo:
    """One iteration as the hooks see it: its number (1 for the first), views, position lr and the run's RNG on the
    Gaussians' device (the trainer's only generator on the CPU)."""

    step: int
    views: list[ViewInfo]
    means_lr: float
    generator: torch.Generator


class Strategy(ABC):
    """Densification strategy: built from the densify config and the scene extent (m), stateful across a resume."""

    @abstractmethod
    def __init__(self, densify: DensifyConfig, extent: float) -> None:
        """Take this strategy's part of ``densify``; ``extent`` is 3DGS's scene scale."""

    def step_pre_backward(self, params: GaussianParams, info: StepInfo) -> Tensor:
        """The strategy's term added to the loss (none by default), on the Gaussians' device."""
        return params["means"].new_zeros(())

    def step_post_backward(self, params: GaussianParams, info: StepInfo) -> None:  # noqa: B027 (an optional hook)
        """Read gradients before the optimizer moves the parameters (nothing by default)."""

    @abstractmethod
    def step_post_update(self, params: GaussianParams, info: StepInfo) -> dict[str, int]:
        """Edit the Gaussians after the optimizer step; returns counts for the step's log record."""

    def state_dict(self) -> dict[str, Any]:
        """State a resume needs beyond the parameters (none by default)."""
        return {}

    def load_state_dict(self, state: dict[str, Any]) -> None:  # noqa: B027 (an optional hook)
        """Restore ``state_dict`` output (nothing by default)."""
