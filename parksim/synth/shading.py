"""Surface appearance and lighting of the garage, and the camera's sensor effects.

Textures are built once per scene: a tileable concrete noise (1/f spectrum, FFT), floor paint
coverage (anti-aliased polygons at 1 cm), oil stains, and a floor light map (pools of light
under each fixture, contact shadows under cars and pillars). ``Shader.radiance`` turns ray
hits into linear RGB; ``Sensor`` applies exposure, vignetting, gamma and noise per camera.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np
from numba import njit

from .layout import Garage
from .raycast import CEILING, FLOOR, BoxSet, Hits

__all__ = ["Shader", "Sensor", "SensorOptions", "PAINT_RGB", "to_srgb"]

PAINT_RGB = {"white": (0.86, 0.86, 0.84), "yellow": (0.88, 0.68, 0.12)}
"""Albedo of the marking paints."""
_PAINT_RES = 0.01      # m per texel of the paint coverage maps
_LIGHT_RES = 0.1       # m per texel of the floor light map
_NOISE_RES = 0.01      # m per texel of the concrete noise
_NOISE_SIZE = 512      # texels per side of the tileable concrete noise
_MATERIALS = ("wall", "pillar", "car_body", "car_window", "wheel", "fixture", "fixture_off", "ego")


@njit(cache=True)
def _bilinear(tex: np.ndarray, fx: np.ndarray, fy: np.ndarray, wrap: bool) -> np.ndarray:
    """Sample ``tex[H, W, C]`` at texel coordinates (centres at integers); clamp or wrap at edges."""
    h, w, c = tex.shape
    out = np.empty((fx.shape[0], c), np.float32)
    for i in range(fx.shape[0]):
        x0f, y0f = math.floor(fx[i]), math.floor(fy[i])
        ax, ay = fx[i] - x0f, fy[i] - y0f
        x0, y0 = int(x0f), int(y0f)
        if wrap:
            x0, y0 = x0 % w, y0 % h
            x1, y1 = (x0 + 1) % w, (y0 + 1) % h
        else:
            x1, y1 = min(max(x0 + 1, 0), w - 1), min(max(y0 + 1, 0), h - 1)
            x0, y0 = min(max(x0, 0), w - 1), min(max(y0, 0), h - 1)
        for ch in range(c):
            top = tex[y0, x0, ch] * (1 - ax) + tex[y0, x1, ch] * ax
            bot = tex[y1, x0, ch] * (1 - ax) + tex[y1, x1, ch] * ax
            out[i, ch] = top * (1 - ay) + bot * ay
    return out


def _tileable_noise(rng: np.random.Generator, size: int, slope: float) -> np.ndarray:
    """Zero-mean, unit-std periodic noise with a power spectrum ~ 1/f^slope (concrete-like)."""
    f = np.fft.fftfreq(size)
    fr = np.sqrt(f[:, None] ** 2 + f[None, :] ** 2)
    fr[0, 0] = 1.0
    spectrum = np.fft.fft2(rng.normal(size=(size, size))) / fr ** (slope / 2)
    spectrum[0, 0] = 0.0
    n = np.real(np.fft.ifft2(spectrum))
    return ((n - n.mean()) / n.std()).astype(np.float32)


def to_srgb(linear: np.ndarray) -> np.ndarray:
    """Linear [0, 1] -> sRGB-like display values (gamma 1/2.2)."""
    return np.power(np.clip(linear, 0.0, 1.0), 1 / 2.2)


class Shader:
    """Linear radiance of ray hits: albedo (textures, paint, materials) times the light map."""

    def __init__(self, garage: Garage, boxes: BoxSet, materials: list[str],
                 colors: np.ndarray, seed: int) -> None:
        rng = np.random.default_rng(seed + 7)
        self.g, self.boxes = garage, boxes
        self.material = np.array([_MATERIALS.index(m) for m in materials], np.int32)
        self.colors = colors.astype(np.float32)
        self.noise = _tileable_noise(rng, _NOISE_SIZE, 2.6)[..., None]
        self.grain = _tileable_noise(rng, _NOISE_SIZE, 0.3)[..., None]
        self.paint = self._paint_maps()
        self.floor = self._floor_map(rng)
        self.light = self._light_map()

    # --- textures built once per scene -----------------------------------------------------
    def _floor_grid(self, res: float) -> tuple[int, int]:
        return int(math.ceil(self.g.length / res)) + 1, int(math.ceil((self.g.y_max - self.g.y_min) / res)) + 1

    def _to_texel(self, x: np.ndarray, y: np.ndarray, res: float) -> tuple[np.ndarray, np.ndarray]:
        """World floor (x, y) -> texel coordinates of a floor map with ``res`` m per texel."""
        return (x / res - 0.5).astype(np.float32), ((y - self.g.y_min) / res - 0.5).astype(np.float32)

    def _paint_maps(self) -> np.ndarray:
        """Coverage [H, W, 2] (white, yellow) of all paint polygons, anti-aliased at 1/16 texel."""
        w, h = self._floor_grid(_PAINT_RES)
        layers = {"white": np.zeros((h, w), np.uint8), "yellow": np.zeros((h, w), np.uint8)}
        shift = 4
        for p in self.g.paint:
            pts = np.array(p.polygon)
            px = np.stack([pts[:, 0] / _PAINT_RES - 0.5, (pts[:, 1] - self.g.y_min) / _PAINT_RES - 0.5], 1)
            cv2.fillPoly(layers[p.color], [np.round(px * (1 << shift)).astype(np.int32)], 255,
                         lineType=cv2.LINE_AA, shift=shift)
        maps = np.stack([layers["white"], layers["yellow"]], -1)
        # Worn paint: scale coverage by a slow concrete-like variation, only where there is paint.
        r, c = np.nonzero(maps.max(-1))
        wear = np.clip(0.93 + 0.6 * (self.concrete(c * _PAINT_RES * 0.7 + 3.1, r * _PAINT_RES * 0.7) - 1.0), 0.7, 1.0)
        maps[r, c] = np.rint(maps[r, c] * wear[:, None]).astype(np.uint8)
        return maps

    def _floor_map(self, rng: np.random.Generator) -> np.ndarray:
        """Floor grey at 5 cm: large-scale concrete blotches, oil stains in the slots, tyre wear in the aisles."""
        res = 0.05
        w, h = self._floor_grid(res)
        stain = np.ones((h, w), np.float32)
        for s in self.g.slots:
            a, b = self.g.marks[s.p1], self.g.marks[s.p2]
            mid = np.array([(a.x + b.x) / 2, (a.y + b.y) / 2]) + s.depth * 0.45 * np.array(
                [math.cos(a.direction), math.sin(a.direction)])
            c = (int(mid[0] / res), int((mid[1] - self.g.y_min) / res))
            r = int(rng.uniform(0.3, 0.8) / res)
            cv2.circle(stain, c, r, float(rng.uniform(0.7, 0.9)), -1)
        for lane in self.g.lanes:
            for off in (-0.8, 0.8):
                y = int((lane + off - self.g.y_min) / res)
                cv2.line(stain, (0, y), (w - 1, y), 0.9, int(0.35 / res))
        stain = cv2.GaussianBlur(stain, (0, 0), 0.25 / res).astype(np.float32, copy=False)
        yy, xx = np.mgrid[0:h, 0:w].astype(np.float32) * res
        big = _bilinear(self.noise, (xx.ravel() / (4 * _NOISE_RES)), (yy.ravel() / (4 * _NOISE_RES)), True)
        return (0.42 * stain * (1.0 + 0.09 * big[:, 0].reshape(h, w)))[..., None]

    def _light_map(self) -> np.ndarray:
        """Floor irradiance at 10 cm: ambient plus a pool under each fixture, darkened under obstacles."""
        w, h = self._floor_grid(_LIGHT_RES)
        x = (np.arange(w) + 0.5) * _LIGHT_RES
        y = self.g.y_min + (np.arange(h) + 0.5) * _LIGHT_RES
        X, Y = np.meshgrid(x, y)
        height2 = self.g.height ** 2
        E = np.full((h, w), self.g.ambient, np.float32)
        for L in self.g.lights:
            if L.intensity > 0:
                r2 = (X - L.x) ** 2 + (Y - L.y) ** 2
                E += (L.intensity * (height2 / (r2 + height2)) ** 4).astype(np.float32)
        # Contact shadows: the floor under cars and pillars gets little light.
        mask = np.zeros((h, w), np.float32)
        for b, m in enumerate(self.material):
            if _MATERIALS[m] in ("car_body", "pillar"):
                corners = self._box_corners(b)
                px = np.stack([corners[:, 0] / _LIGHT_RES, (corners[:, 1] - self.g.y_min) / _LIGHT_RES], 1)
                cv2.fillPoly(mask, [np.round(px).astype(np.int32)], 1.0)
        mask = cv2.GaussianBlur(mask, (0, 0), 2.5).astype(np.float32, copy=False)
        return (E * (1 - 0.7 * np.clip(mask, 0, 1)))[..., None]

    def _box_corners(self, b: int) -> np.ndarray:
        c, s = self.boxes.yaw_cs[b]
        hl, hw = self.boxes.halves[b, :2]
        local = np.array([[hl, hw], [-hl, hw], [-hl, -hw], [hl, -hw]])
        return local @ np.array([[c, s], [-s, c]]) + self.boxes.centres[b, :2]

    # --- per-hit shading -------------------------------------------------------------------
    def irradiance(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Light map at floor positions ``x, y`` -> [N]."""
        fx, fy = self._to_texel(x, y, _LIGHT_RES)
        return _bilinear(self.light, fx, fy, False)[:, 0]

    def concrete(self, u: np.ndarray, v: np.ndarray) -> np.ndarray:
        """Tileable concrete variation (around 1) at surface coordinates (m) -> [N]."""
        fu, fv = (u / _NOISE_RES).astype(np.float32), (v / _NOISE_RES).astype(np.float32)
        big = _bilinear(self.noise, fu * 0.25, fv * 0.25, True)[:, 0]
        fine = _bilinear(self.grain, fu, fv, True)[:, 0]
        return 1.0 + 0.09 * big + 0.05 * fine

    def floor_albedo(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Concrete with dirt and worn paint at floor points -> [N, 3]."""
        fx, fy = self._to_texel(x, y, 0.05)
        grain = _bilinear(self.grain, (x / _NOISE_RES).astype(np.float32), (y / _NOISE_RES).astype(np.float32), True)
        grey = _bilinear(self.floor, fx, fy, False) * (1.0 + 0.05 * grain)
        px, py = self._to_texel(x, y, _PAINT_RES)
        cover = _bilinear(self.paint, px, py, False) * np.float32(1 / 255)
        white, yellow = (np.array(PAINT_RGB[k], np.float32) for k in ("white", "yellow"))
        bare = np.clip(1 - cover[:, :1] - cover[:, 1:], 0, 1)
        return grey * bare * np.array([1.0, 0.98, 0.94], np.float32) + cover[:, :1] * white + cover[:, 1:] * yellow

    def _box_albedo(self, boxes: BoxSet, idx: np.ndarray, points: np.ndarray,
                    face: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Albedo [N, 3] and emission [N] of box hits (walls, striped pillars, cars, fixtures)."""
        c, s = boxes.yaw_cs[idx, 0], boxes.yaw_cs[idx, 1]
        rel = points[:, :2] - boxes.centres[idx, :2]
        lx, ly = c * rel[:, 0] + s * rel[:, 1], -s * rel[:, 0] + c * rel[:, 1]
        z = points[:, 2]
        u = np.where(face < 2, ly, lx)  # along the face, horizontally
        mat = self.material[idx]
        conc = self.concrete(u + 0.37 * face, z)
        albedo = self.colors[idx] * conc[:, None]
        pick = lambda name: mat == _MATERIALS.index(name)  # noqa: E731
        # Pillars: yellow/black diagonal safety stripes up to 1.2 m, plain concrete above.
        stripes = (np.floor((u + z) / 0.22) % 2 == 0)
        low = pick("pillar") & (z < 1.2)
        albedo[low & stripes] = np.array([0.85, 0.66, 0.1], np.float32) * conc[low & stripes, None]
        albedo[low & ~stripes] = np.array([0.06, 0.06, 0.06], np.float32)
        # Walls: painted dado up to 1 m with a yellow band above it.
        wall = pick("wall")
        albedo[wall & (z < 1.0)] = np.array([0.18, 0.34, 0.3], np.float32) * conc[wall & (z < 1.0), None]
        albedo[wall & (z >= 1.0) & (z < 1.12)] = np.array([0.85, 0.68, 0.12], np.float32)
        emission = np.where(pick("fixture"), np.where(face == 5, 4.0, 1.5), 0.0).astype(np.float32)
        return albedo, emission

    def radiance(self, hits: Hits, boxes: BoxSet) -> np.ndarray:
        """Linear RGB [..., 3] of the hits against ``boxes`` (the scene's, same order as the
        materials, possibly with moved entries such as the ego car); 0 where nothing was hit."""
        shape = hits.prim.shape
        prim, face = hits.prim.reshape(-1), hits.face.reshape(-1)
        pts = hits.points.reshape(-1, 3)
        out = np.zeros((len(prim), 3), np.float32)
        light = self.irradiance(pts[:, 0], pts[:, 1])
        floor = prim == FLOOR
        out[floor] = self.floor_albedo(pts[floor, 0], pts[floor, 1]) * light[floor, None]
        ceil = prim == CEILING
        out[ceil] = (0.5 * self.concrete(pts[ceil, 0], pts[ceil, 1]) * (0.1 + 0.5 * light[ceil]))[:, None]
        box = prim > CEILING
        albedo, emission = self._box_albedo(boxes, prim[box] - 2, pts[box], face[box])
        # Facing light: tops get the full pool, sides a share growing with height, undersides little.
        zf = np.clip(pts[box, 2] / self.g.height, 0, 1)
        share = np.select([face[box] == 4, face[box] == 5], [1.0, 0.3], 0.5 + 0.3 * zf).astype(np.float32)
        out[box] = albedo * (light[box] * share)[:, None] + emission[:, None]
        return out.reshape(*shape, 3)


@dataclass(frozen=True)
class SensorOptions:
    """Which camera effects to apply (each can be switched off for clean ground truth)."""

    exposure: bool = True
    vignetting: bool = True
    noise: bool = True


class Sensor:
    """Per-camera exposure (fixed offset + slow auto-exposure drift), vignetting, gamma, noise."""

    def __init__(self, names: list[str], models: dict, options: SensorOptions, seed: int) -> None:
        rng = np.random.default_rng(seed + 11)
        self.options, self.seed = options, seed
        self.gain = {n: float(rng.uniform(0.82, 1.18)) for n in names}
        self.phase = {n: float(rng.uniform(0, 2 * math.pi)) for n in names}
        self.vignette = {n: self._vignette(models[n]) for n in names}

    @staticmethod
    def _vignette(model) -> np.ndarray:
        """Radial fall-off: 1 at the centre, ~0.6 at the lens' edge."""
        v, u = np.mgrid[0:model.height, 0:model.width].astype(np.float64)
        r = np.hypot((u - float(model.cx)) / float(model.fx), (v - float(model.cy)) / float(model.fy)) / model.rho_max
        return (1.0 - 0.4 * np.clip(r, 0, 1) ** 2.5).astype(np.float32)[..., None]

    def exposure(self, name: str, frame: int) -> float:
        """Exposure factor of a camera at a frame."""
        if not self.options.exposure:
            return 1.0
        return self.gain[name] * (1.0 + 0.04 * math.sin(0.07 * frame + self.phase[name]))

    def __call__(self, name: str, frame: int, radiance: np.ndarray, valid: np.ndarray,
                 exposure_frame: int | None = None) -> np.ndarray:
        """Linear radiance [H, W, 3] -> float32 display image in [0, 1], black outside the lens circle; ``frame``
        seeds the noise, ``exposure_frame`` (default ``frame``) sets the auto-exposure drift."""
        img = radiance * (1.25 * self.exposure(name, frame if exposure_frame is None else exposure_frame))
        if self.options.vignetting:
            img = img * self.vignette[name]
        img = to_srgb(img)
        if self.options.noise:
            rng = np.random.default_rng([self.seed, frame, sorted(self.gain).index(name)])
            sigma = 0.006 + 0.012 * np.sqrt(img)
            img = img + sigma * rng.standard_normal(img.shape, dtype=np.float32)
        return np.clip(img, 0.0, 1.0).astype(np.float32) * valid[..., None]
