"""Numba helpers shared by binning and kernels: the alpha-threshold ellipse of a Gaussian and a fast exp.

A Gaussian reaches alpha >= ALPHA_MIN only inside q(dx, dy) = a dx^2 + 2 b dx dy + c dy^2 <= 2 ln(255 o);
bounding that ellipse exactly (its rows, and its columns per tile row) is what keeps the pair count low.
"""

from __future__ import annotations

import math

import numba
import numpy as np

from .constants import ALPHA_MIN

__all__ = ["threshold_q", "half_height", "x_span", "pixel_range", "fast_exp", "SPAN_MARGIN"]

SPAN_MARGIN = 1e-3
"""Pixels added on each side of an ellipse span so float rounding never drops a pair at the threshold."""


@numba.njit(inline="always", cache=True)
def threshold_q(opacity: float) -> float:
    """Largest q = -2 power at which opacity * exp(power) still reaches ALPHA_MIN."""
    return 2.0 * math.log(opacity / ALPHA_MIN)


@numba.njit(inline="always", cache=True)
def half_height(a: float, b: float, c: float, q: float) -> float:
    """Half of the ellipse's vertical extent: sqrt(q * Sigma_yy) with Sigma = conic^-1."""
    return math.sqrt(q * a / (a * c - b * b)) + SPAN_MARGIN


@numba.njit(inline="always", cache=True)
def x_span(a: float, b: float, c: float, q: float, dy_lo: float, dy_hi: float) -> tuple[float, float]:
    """Horizontal extent (dx_min, dx_max) of the ellipse over the band dy in [dy_lo, dy_hi] (float64).

    dx_max(dy) is concave and dx_min(dy) convex, so each extreme sits at its unconstrained optimum
    clipped into the band; an empty band returns dx_min > dx_max.
    """
    det = a * c - b * b
    dy_right = -b * math.sqrt(q / (c * det))
    dy_r = min(max(dy_right, dy_lo), dy_hi)
    dy_l = min(max(-dy_right, dy_lo), dy_hi)
    disc_r = a * q - det * dy_r * dy_r
    disc_l = a * q - det * dy_l * dy_l
    if disc_r < 0.0 and disc_l < 0.0:
        return 1.0, -1.0
    dx_max = (-b * dy_r + math.sqrt(max(disc_r, 0.0))) / a + SPAN_MARGIN
    dx_min = (-b * dy_l - math.sqrt(max(disc_l, 0.0))) / a - SPAN_MARGIN
    return dx_min, dx_max


@numba.njit(inline="always", cache=True)
def pixel_range(center: float, d_lo: float, d_hi: float, lo: int, hi: int) -> tuple[int, int]:
    """Integer pixel centres p with center + d_lo <= p <= center + d_hi, clipped to [lo, hi].

    Bounds are clamped to [lo - 1, hi + 1] before the integer conversion, so huge extents cannot overflow.
    """
    first = min(max(center + d_lo, lo - 1.0), hi + 1.0)
    last = min(max(center + d_hi, lo - 1.0), hi + 1.0)
    return max(lo, int(math.ceil(first))), min(hi, int(math.floor(last)))


_LOG2E = np.float32(1.4426950408889634)
_LN2_HI = np.float32(0.693359375)
_LN2_LO = np.float32(-2.12194440e-4)


@numba.njit(inline="always", fastmath=True, cache=True)
def fast_exp(x: np.float32) -> np.float32:
    """exp(x) for float32 x <= 0 to ~2 ulp, branch free so loops around it vectorise (no SVML here).

    Cody-Waite reduction to r in [-ln2/2, ln2/2], degree-7 Taylor polynomial, 2^n built from the exponent bits;
    x is clamped at -40 (alpha there is far below ALPHA_MIN) so no denormal ever slows the arithmetic.
    """
    x = max(x, np.float32(-40.0))
    n_int = np.int32(x * _LOG2E - np.float32(0.5))  # truncation toward 0 rounds to nearest for x <= 0
    n = np.float32(n_int)
    r = x - n * _LN2_HI - n * _LN2_LO
    p = np.float32(1.0 / 5040.0)
    p = p * r + np.float32(1.0 / 720.0)
    p = p * r + np.float32(1.0 / 120.0)
    p = p * r + np.float32(1.0 / 24.0)
    p = p * r + np.float32(1.0 / 6.0)
    p = p * r + np.float32(0.5)
    p = p * r + np.float32(1.0)
    p = p * r + np.float32(1.0)
    scale = np.int32((n_int + np.int32(127)) << np.int32(23)).view(np.float32)
    return p * scale
