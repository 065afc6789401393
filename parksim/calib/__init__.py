"""Calibration importers that need more than reading a file (poses recovered from homographies)."""

__all__: list[str] = []
