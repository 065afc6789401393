"""Sign textures and their lookup: text drawn with OpenCV's Hershey font on a panel (or bare paint), put on box
faces where ``garage.Decal`` says, and floor text drawn into the floor paint coverage."""

from __future__ import annotations

import math
from collections.abc import Sequence

import cv2
import numpy as np

from .garage import Decal, FloorText

__all__ = ["DecalSet", "text_mask", "draw_floor_text"]

_PX_PER_M = 160  # sign texture resolution: 6 mm per texel, finer than a 640x480 fisheye pixel at 1 m
_FONT = cv2.FONT_HERSHEY_DUPLEX


def text_mask(text: str, width_px: int, height_px: int, fill: float = 0.78) -> np.ndarray:
    """Coverage [height_px, width_px] float32 in [0, 1] of ``text`` centred and scaled to fill the box."""
    (tw, th), base = cv2.getTextSize(text, _FONT, 1.0, 2)
    scale = fill * min(width_px / tw, height_px / (th + base))
    thick = max(1, int(round(2.2 * scale)))
    (tw, th), base = cv2.getTextSize(text, _FONT, scale, thick)
    canvas = np.zeros((height_px, width_px), np.uint8)
    org = ((width_px - tw) // 2, (height_px + th) // 2)
    cv2.putText(canvas, text, org, _FONT, scale, 255, thick, cv2.LINE_AA)
    return canvas.astype(np.float32) / 255.0


def _texture(d: Decal) -> np.ndarray:
    """RGBA [h, w, 4] of one decal: ink over the panel colour (opaque), or ink alone (alpha = ink coverage)."""
    w, h = max(8, int(d.width * _PX_PER_M)), max(8, int(d.height * _PX_PER_M))
    ink = text_mask(d.text, w, h)
    rgb = np.array(d.ink, np.float32) * ink[..., None]
    if d.panel is None:
        return np.concatenate([rgb, ink[..., None]], -1)
    rgb += np.array(d.panel, np.float32) * (1.0 - ink[..., None])
    border = max(2, h // 14)  # a thin dark frame, as on printed signs
    rgb[:border], rgb[-border:], rgb[:, :border], rgb[:, -border:] = 0.1, 0.1, 0.1, 0.1
    return np.concatenate([rgb, np.ones((h, w, 1), np.float32)], -1)


class DecalSet:
    """All decals of a garage, grouped by (box, face) for shading the hits on those faces."""

    def __init__(self, decals: Sequence[Decal], n_boxes: int) -> None:
        self.decals = list(decals)
        self.textures = [_texture(d) for d in self.decals]
        self.keys = np.array([d.box * 6 + d.face for d in self.decals], np.int64)
        self.has = np.zeros(n_boxes + 1, bool)  # + 1: the ego, never decorated
        self.has[[d.box for d in self.decals]] = True

    def apply(self, idx: np.ndarray, face: np.ndarray, u_right: np.ndarray, z: np.ndarray,
              albedo: np.ndarray, grain: np.ndarray) -> None:
        """Blend the decals into ``albedo[N, 3]`` in place at hits on box ``idx``, ``face``, face coordinates
        (``u_right``, ``z``); ``grain`` [N] (around 1) lets the surface texture show through the paint."""
        if not self.decals:
            return
        sel = np.nonzero(self.has[idx] & (face < 4))[0]
        key = idx[sel].astype(np.int64) * 6 + face[sel]
        for d, tex, k in zip(self.decals, self.textures, self.keys):
            on = sel[key == k]
            if len(on) == 0:
                continue
            tu = (u_right[on] - d.u) / d.width + 0.5
            tv = (d.z + d.height / 2 - z[on]) / d.height
            inside = (tu >= 0) & (tu < 1) & (tv >= 0) & (tv < 1)
            on, tu, tv = on[inside], tu[inside], tv[inside]
            h, w = tex.shape[:2]
            texel = tex[(tv * h).astype(np.int64), (tu * w).astype(np.int64)]
            alpha = texel[:, 3:]
            albedo[on] = albedo[on] * (1 - alpha) + texel[:, :3] * grain[on, None] * alpha


def draw_floor_text(layer: np.ndarray, t: FloorText, res: float, y_min: float) -> None:
    """Paint ``t`` into a floor coverage ``layer`` (uint8, ``res`` m per texel, row 0 at ``y_min``): a text
    mask warped onto the floor in a window around the text only."""
    h_px = max(8, int(round(t.height / res)))
    w_px = max(8, int(round(t.height * 0.75 * len(t.text) / res)))
    mask = (text_mask(t.text, w_px, h_px, fill=0.95) * 255).astype(np.uint8)
    c, s = math.cos(t.heading), math.sin(t.heading)
    # text pixel (col, row) -> floor texel: columns run along the heading, rows against the "up" direction
    cx, cy = t.x / res - 0.5, (t.y - y_min) / res - 0.5
    up = np.array([-s, c])
    right = np.array([c, s])
    origin = np.array([cx, cy]) - right * w_px / 2 + up * h_px / 2
    half = int(math.hypot(w_px, h_px) / 2) + 2
    x0, y0 = max(int(cx) - half, 0), max(int(cy) - half, 0)
    x1, y1 = min(int(cx) + half, layer.shape[1]), min(int(cy) + half, layer.shape[0])
    if x1 <= x0 or y1 <= y0:
        return
    M = np.array([[right[0], -up[0], origin[0] - x0], [right[1], -up[1], origin[1] - y0]], np.float64)
    warped = cv2.warpAffine(mask, M, (x1 - x0, y1 - y0), flags=cv2.INTER_LINEAR)
    np.maximum(layer[y0:y1, x0:x1], warped, out=layer[y0:y1, x0:x1])
