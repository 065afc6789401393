"""Compositing thresholds shared by every rasterizer backend (the 3DGS values)."""

__all__ = ["ALPHA_MIN", "ALPHA_MAX", "T_MIN", "TILE"]

ALPHA_MIN: float = 1.0 / 255.0
"""A Gaussian-pixel pair with alpha below this is skipped."""

ALPHA_MAX: float = 0.99
"""Alpha is clamped here so that 1 - alpha never vanishes (the backward divides by it)."""

T_MIN: float = 1e-4
"""A pixel stops when the next Gaussian would push its transmittance below this; that Gaussian is not added."""

TILE: int = 16
"""Tile edge in pixels for the binned CPU kernel."""
