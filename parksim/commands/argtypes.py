"""Argument types for the ``parksim`` parsers: each checks its range while the command line is parsed,
so a bad value is one line of usage error before any file is read or written."""

from __future__ import annotations

import argparse
import math
from collections.abc import Callable

__all__ = ["integer", "number", "tcp_port", "resolution"]


def integer(low: int = 1, high: int | None = None) -> Callable[[str], int]:
    """An ``int`` in ``[low, high]`` (no upper bound when ``high`` is None)."""
    span = f">= {low}" if high is None else f"in [{low}, {high}]"

    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected an integer {span}, got {text!r}") from None
        if value < low or (high is not None and value > high):
            raise argparse.ArgumentTypeError(f"must be an integer {span}, got {value}")
        return value

    return parse


def number(low: float, high: float = math.inf, *, open_low: bool = False, open_high: bool = False
           ) -> Callable[[str], float]:
    """A finite ``float`` between ``low`` and ``high``, each end included unless ``open_low`` / ``open_high``."""
    span = (f"{'>' if open_low else '>='} {low:g}" if math.isinf(high) else
            f"in {'(' if open_low else '['}{low:g}, {high:g}{')' if open_high else ']'}")

    def parse(text: str) -> float:
        try:
            value = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected a number {span}, got {text!r}") from None
        inside = (value > low if open_low else value >= low) and (value < high if open_high else value <= high)
        if not (math.isfinite(value) and inside):
            raise argparse.ArgumentTypeError(f"must be a finite number {span}, got {text}")
        return value

    return parse


tcp_port = integer(1, 65535)
"""A TCP port number."""


def resolution(max_side: int) -> Callable[[str], tuple[int, int]]:
    """``WxH`` as ``(width, height)``, each side from 1 to ``max_side`` pixels."""
    def parse(text: str) -> tuple[int, int]:
        try:
            width, height = (int(v) for v in text.lower().split("x"))
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected WxH like 640x480, got {text!r}") from None
        if not (0 < width <= max_side and 0 < height <= max_side):
            raise argparse.ArgumentTypeError(f"each side must be 1 to {max_side} px, got {text}")
        return width, height

    return parse
