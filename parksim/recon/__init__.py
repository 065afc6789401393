"""Offline reconstruction: train a Gaussian scene from surround-view fisheye data, evaluate it, import COLMAP."""

__all__: list[str] = []
