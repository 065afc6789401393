"""Calibration importers that need more than reading a file (poses recovered from homographies)."""
