"""Slot labels and detections drawn on BEV images, and a labelled grid of such BEVs (figures and eval panels).

Green: labels (circle = the 10 px-at-600 px match tolerance, line = slot entrance p1 -> p2).
Red: detections (dot, direction arrow, L/T, entrance line).
"""

from __future__ import annotations

import math
from pathlib import Path

import cv2
import numpy as np

from parksim.fileio import atomic_write

from .detectors import Detections, SlotLabels
from .detectors.evaluate import MatchOptions

__all__ = ["draw_labels", "draw_detections", "caption", "write_grid"]

GREEN, RED, WHITE = (40, 220, 40), (255, 50, 50), (255, 255, 255)


def _pt(x: float, y: float) -> tuple[int, int]:
    return int(round(x)), int(round(y))


def draw_labels(img: np.ndarray, labels: SlotLabels) -> None:
    """Labelled points (tolerance circles, direction) and slot entrances in green, in place on uint8 RGB."""
    radius = int(round(MatchOptions().distance(labels.m_per_px)))
    for x, y, d, _ in labels.marks:
        cv2.circle(img, _pt(x, y), radius, GREEN, 2, cv2.LINE_AA)
        cv2.line(img, _pt(x, y), _pt(x + 30 * math.cos(d), y + 30 * math.sin(d)), GREEN, 2, cv2.LINE_AA)
    for p1, p2 in labels.slots:
        a, b = labels.marks[p1], labels.marks[p2]
        cv2.line(img, _pt(a[0], a[1]), _pt(b[0], b[1]), GREEN, 2, cv2.LINE_AA)


def draw_detections(img: np.ndarray, det: Detections) -> None:
    """Detected points (dot + direction arrow + L/T) and slot entrances in red, in place on uint8 RGB."""
    for p in det.points:
        cv2.circle(img, _pt(p.x, p.y), 4, RED, -1, cv2.LINE_AA)
        cv2.arrowedLine(img, _pt(p.x, p.y), _pt(p.x + 45 * math.cos(p.direction), p.y + 45 * math.sin(p.direction)),
                        RED, 2, cv2.LINE_AA, tipLength=0.3)
        cv2.putText(img, p.shape, _pt(p.x + 8, p.y - 8), cv2.FONT_HERSHEY_SIMPLEX, 0.6, RED, 2, cv2.LINE_AA)
    for s in det.slots:
        a, b = det.points[s.p1], det.points[s.p2]
        cv2.line(img, _pt(a.x, a.y), _pt(b.x, b.y), RED, 1, cv2.LINE_AA)


def caption(img: np.ndarray, text: str) -> None:
    """White text on a dark band at the top of the image, in place."""
    scale = max(img.shape[1] / 900.0, 0.35)
    band = int(32 * scale) + 6
    img[:band] = img[:band] // 3
    cv2.putText(img, text, (6, band - 8), cv2.FONT_HERSHEY_SIMPLEX, scale, WHITE, max(1, int(2 * scale)), cv2.LINE_AA)


def write_grid(path: str | Path, rows: list[list[np.ndarray]], tile: int = 360, gap: int = 6) -> None:
    """Write a grid of uint8 RGB images (each resized to ``tile`` x ``tile``) as a PNG, atomically."""
    white = np.full((tile, gap, 3), 255, np.uint8)
    lines = []
    for row in rows:
        cells = [cv2.resize(img, (tile, tile), interpolation=cv2.INTER_AREA) for img in row]
        lines.append(np.concatenate([x for cell in cells for x in (cell, white)][:-1], axis=1))
    width = max(line.shape[1] for line in lines)
    lines = [np.pad(line, ((0, gap), (0, width - line.shape[1]), (0, 0)), constant_values=255) for line in lines]
    grid = np.concatenate(lines, axis=0)[:-gap]
    atomic_write(path, lambda p: cv2.imwrite(str(p), cv2.cvtColor(grid, cv2.COLOR_RGB2BGR)))
