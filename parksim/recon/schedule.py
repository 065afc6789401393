"""Learning-rate and SH-degree schedules of 3DGS: exponential position-lr decay, stepwise SH degree."""

from __future__ import annotations

import math

__all__ = ["exp_decay", "sh_degree_at"]


def exp_decay(step: int, total: int, lr_init: float, final_factor: float) -> float:
    """Log-linear interpolation from ``lr_init`` at step 0 to ``lr_init * final_factor`` at ``total`` (held after)."""
    t = min(max(step / max(total, 1), 0.0), 1.0)
    return math.exp((1.0 - t) * math.log(lr_init) + t * math.log(lr_init * final_factor))


def sh_degree_at(step: int, interval: int, max_degree: int) -> int:
    """SH degree in use at ``step``: one more every ``interval`` steps, up to ``max_degree`` (all of it from step 0
    when ``interval`` is 0: a scene that already has its full degree, e.g. one being fine-tuned)."""
    return max_degree if interval == 0 else min(step // interval, max_degree)
