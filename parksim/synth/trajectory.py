"""Ego trajectory: a slow drive along the aisles, smooth in position and yaw, sampled at 10 Hz.

A path is a polyline of straight pieces and quarter-circle turns through the garage's
aisles, smoothed with a Gaussian along its arc length (so curvature, and hence the yaw
rate, is continuous), then sampled at constant speed; yaw follows the path's tangent.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .garage import CROSS_AISLE, Garage

__all__ = ["TrajectoryParams", "drive"]

_STEP = 0.05  # m between path samples before smoothing


@dataclass(frozen=True)
class TrajectoryParams:
    """How the ego drives: ``kind`` "aisle" (along aisle 0 with a gentle weave) or "turn"
    (down the cross aisle, then a left turn into aisle 0); speed in m/s; frame rate in Hz."""

    kind: str = "aisle"
    speed: float = 2.0
    rate: float = 10.0
    start_x: float = 5.0
    weave: float = 0.5


def _smooth(xy: np.ndarray, sigma: float) -> np.ndarray:
    """Gaussian smoothing of a polyline along its samples, ends held in place (edge padding)."""
    r = int(4 * sigma)
    k = np.exp(-0.5 * (np.arange(-r, r + 1) / sigma) ** 2)
    k /= k.sum()
    padded = np.pad(xy, ((r, r), (0, 0)), mode="edge")
    return np.stack([np.convolve(padded[:, i], k, mode="valid") for i in range(xy.shape[1])], 1)


def _polyline(garage: Garage, p: TrajectoryParams, length: float) -> np.ndarray:
    """Dense (x, y) samples of the unsmoothed path, at least ``length`` metres long."""
    lane = garage.lanes[0]
    if p.kind == "aisle":
        s = np.arange(0.0, length + 10.0, _STEP)
        x = p.start_x + s
        y = lane + p.weave * np.sin(2 * math.pi * s / 18.0) * np.clip(s / 4.0, 0, 1)
        return np.stack([x, y], 1)
    if p.kind == "turn":
        x_turn, radius = CROSS_AISLE / 2, 4.5
        start_y = min(lane + radius + 6.0, garage.y_max - 1.0)
        down = np.arange(start_y, lane + radius, -_STEP)
        leg1 = np.stack([np.full_like(down, x_turn), down], 1)
        a = np.arange(math.pi, 1.5 * math.pi, _STEP / radius)
        arc = np.stack([x_turn + radius + radius * np.cos(a), lane + radius + radius * np.sin(a)], 1)
        along = np.arange(x_turn + radius, x_turn + radius + length + 10.0, _STEP)
        leg2 = np.stack([along, np.full_like(along, lane)], 1)
        return np.concatenate([leg1, arc, leg2])
    raise ValueError(f"unknown trajectory kind {p.kind!r}; use 'aisle' or 'turn'")


def drive(garage: Garage, params: TrajectoryParams, frames: int) -> tuple[np.ndarray, np.ndarray]:
    """Poses ``T_world_vehicle [frames, 4, 4]`` and timestamps (s) of a drive through ``garage``."""
    if frames < 1:
        raise ValueError(f"need at least one frame, got {frames}")
    length = params.speed * (frames - 1) / params.rate
    xy = _smooth(_polyline(garage, params, length), 1.0 / _STEP)
    seg = np.linalg.norm(np.diff(xy, axis=0), axis=1)
    s = np.concatenate([[0.0], np.cumsum(seg)])
    t = np.arange(frames) / params.rate
    target = params.speed * t
    if target[-1] > s[-1]:
        raise ValueError(f"garage too short for {frames} frames at {params.speed} m/s ({s[-1]:.1f} m of path)")
    x, y = np.interp(target, s, xy[:, 0]), np.interp(target, s, xy[:, 1])
    eps = 0.05
    dx = np.interp(target + eps, s, xy[:, 0]) - np.interp(target - eps, s, xy[:, 0])
    dy = np.interp(target + eps, s, xy[:, 1]) - np.interp(target - eps, s, xy[:, 1])
    yaw = np.arctan2(dy, dx)
    poses = np.tile(np.eye(4), (frames, 1, 1))
    c, sn = np.cos(yaw), np.sin(yaw)
    poses[:, 0, 0], poses[:, 0, 1], poses[:, 1, 0], poses[:, 1, 1] = c, -sn, sn, c
    poses[:, 0, 3], poses[:, 1, 3] = x, y
    return poses, t
