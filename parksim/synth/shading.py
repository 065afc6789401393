"""Surface appearance and lighting of the garage, and the camera's sensor effects.

Textures are built once per scene: a tileable concrete noise (1/f spectrum, FFT), floor paint
coverage (anti-aliased polygons at 1 cm), oil stains, and a floor light map (pools of light
under each fixture, contact shadows under cars and pillars). Where ``LayoutParams`` asks for them
(worn/busy), also worn paint, a dirt map (tyre tracks, stains), wet patches, sign decals, wall
grime, and a view-dependent floor reflection of the ceiling lights. ``Shader.radiance`` turns ray
hits into linear RGB; ``Sensor`` applies exposure, white balance, vignetting, gamma and noise per
camera.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np
from numba import njit

from .garage import Garage
from .raycast import CEILING, FLOOR, BoxSet, Hits
from .signage import DecalSet, draw_floor_text

__all__ = ["Shader", "Sensor", "SensorOptions", "PAINT_RGB", "to_srgb"]

PAINT_RGB = {"white": (0.86, 0.86, 0.84), "yellow": (0.88, 0.68, 0.12)}
"""Albedo of the marking paints."""
_PAINT_RES = 0.01      # m per texel of the paint coverage maps
_LIGHT_RES = 0.1       # m per texel of the floor light map
_NOISE_RES = 0.01      # m per texel of the concrete noise
_NOISE_SIZE = 512      # texels per side of the tileable concrete noise
_MATERIALS = ("wall", "pillar", "car_body", "car_window", "wheel", "fixture", "fixture_off", "ego", "clutter", "duct")
_DIRT_RES = 0.05       # m per texel of the floor dirt and wetness maps
_FIXTURE_EMISSION = 4.0  # radiance of a lit fixture's diffuser (its underside)


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
    """Linear radiance of ray hits: albedo (textures, paint, materials, decals) times the light map, plus the
    floor's specular reflection where it is wet or glossy."""

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
        # The real-garage dressing (off in scene1-4) draws from its own stream, after the classic textures.
        p, extra = garage.params, np.random.default_rng([seed, 7, 1])
        if p.paint_fade > 0 or p.paint_scuff > 0:
            self._wear_paint(extra)
        self.dirt = self._dirt_map(extra) if p.tyre_marks > 0 or p.stains > 0 else None
        self.wet = self._wet_map(extra) if p.wet_patches > 0 else None
        glossy = p.floor_gloss > 0 or self.wet is not None
        self.mirror = (self._mirror_map(0.06), self._mirror_map(0.35)) if glossy else None
        self.decals = DecalSet(garage.decals, len(garage.boxes))

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
        for t in self.g.floor_text:
            draw_floor_text(layers[t.color], t, _PAINT_RES, self.g.y_min)
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
                E += (L.intensity * (height2 / (r2 + height2)) ** self.g.params.light_falloff).astype(np.float32)
        # Contact shadows: the floor under cars and pillars gets little light.
        mask = np.zeros((h, w), np.float32)
        for b, m in enumerate(self.material):
            if _MATERIALS[m] in ("car_body", "pillar"):
                corners = self._box_corners(b)
                px = np.stack([corners[:, 0] / _LIGHT_RES, (corners[:, 1] - self.g.y_min) / _LIGHT_RES], 1)
                cv2.fillPoly(mask, [np.round(px).astype(np.int32)], 1.0)
        mask = cv2.GaussianBlur(mask, (0, 0), 2.5).astype(np.float32, copy=False)
        return (E * (1 - 0.7 * np.clip(mask, 0, 1)))[..., None]

    def _wear_paint(self, rng: np.random.Generator) -> None:
        """Worn markings: each slot's paint faded by its own amount (up to ``paint_fade``), and scuffed-off patches
        covering a ``paint_scuff`` share of the paint (thresholded concrete noise, soft-edged)."""
        p, maps = self.g.params, self.paint
        r, c = np.nonzero(maps.max(-1))
        x, y = (c + 0.5) * _PAINT_RES, self.g.y_min + (r + 0.5) * _PAINT_RES
        keep = np.ones(len(r), np.float32)
        if p.paint_fade > 0:
            w, h = self._floor_grid(_DIRT_RES)
            fade = np.full((h, w), 1.0 - 0.5 * p.paint_fade, np.float32)  # aisle arrows and lines: half the fade
            for s in self.g.slots:
                a, b = self.g.marks[s.p1], self.g.marks[s.p2]
                d = np.array([math.cos(a.direction), math.sin(a.direction)]) * s.depth
                quad = np.array([[a.x, a.y], [b.x, b.y], [b.x + d[0], b.y + d[1]], [a.x + d[0], a.y + d[1]]])
                px = np.stack([quad[:, 0] / _DIRT_RES, (quad[:, 1] - self.g.y_min) / _DIRT_RES], 1)
                cv2.fillPoly(fade, [np.round(px).astype(np.int32)], 1.0 - p.paint_fade * float(rng.uniform()) ** 0.7)
            fx, fy = self._to_texel(x, y, _DIRT_RES)
            keep *= _bilinear(fade[..., None], fx, fy, False)[:, 0]
        if p.paint_scuff > 0:
            n = self.concrete(x * 1.7 + 11.0, y * 1.7 - 5.0)
            thr = np.quantile(n, 1.0 - p.paint_scuff)
            keep *= 1.0 - 0.92 * np.clip((n - thr) / 0.04 + 0.5, 0.0, 1.0)
        maps[r, c] = np.rint(maps[r, c] * keep[:, None]).astype(np.uint8)

    def _dirt_map(self, rng: np.random.Generator) -> np.ndarray:
        """Floor darkening [H, W, 1] at 5 cm (1 = clean) over paint and concrete alike: tyre tracks into each slot
        (``tyre_marks``: share of slots and darkness), oil and water stains (``stains`` per slot and per 5 m of
        aisle), soft-edged."""
        p = self.g.params
        w, h = self._floor_grid(_DIRT_RES)
        dirt = np.ones((h, w), np.float32)
        to_px = lambda q: (int(q[0] / _DIRT_RES), int((q[1] - self.g.y_min) / _DIRT_RES))  # noqa: E731

        def stain(centre: np.ndarray) -> None:
            axes = (int(rng.uniform(0.12, 0.7) / _DIRT_RES), int(rng.uniform(0.1, 0.45) / _DIRT_RES))
            cv2.ellipse(dirt, to_px(centre), axes, float(rng.uniform(0, 180)), 0, 360,
                        float(1.0 - rng.uniform(0.15, 0.5)), -1)

        for s in self.g.slots:
            mid, into = self.g.slot_entrance(s)
            along = np.array([-into[1], into[0]])
            if rng.random() < p.tyre_marks:
                for track in (-0.78, 0.78):
                    lean = float(rng.normal(0, 0.12))
                    start = mid + along * track - into * rng.uniform(0.5, 2.0)
                    end = mid + along * (track + lean) + into * s.depth * rng.uniform(0.5, 0.9)
                    cv2.line(dirt, to_px(start), to_px(end), float(1.0 - p.tyre_marks * rng.uniform(0.2, 0.45)),
                             max(1, int(0.2 / _DIRT_RES)))
            for _ in range(int(rng.poisson(p.stains))):
                stain(mid + into * s.depth * rng.uniform(0.2, 0.8) + along * rng.normal(0, 0.5))
        for lane in self.g.lanes:
            for _ in range(int(rng.poisson(p.stains * self.g.length / 5.0))):
                stain(np.array([rng.uniform(1.0, self.g.length - 1.0), lane + rng.normal(0, 1.5)]))
        return cv2.GaussianBlur(dirt, (0, 0), 1.2).astype(np.float32, copy=False)[..., None]

    def _wet_map(self, rng: np.random.Generator) -> np.ndarray:
        """Wetness [H, W, 1] in [0, 1] at 5 cm: ``wet_patches`` puddles per 10 m of aisle, in the aisles and at the
        slot entrances, with ragged edges (concrete noise) as water lies in the floor's hollows."""
        p = self.g.params
        w, h = self._floor_grid(_DIRT_RES)
        wet = np.zeros((h, w), np.float32)
        for lane in self.g.lanes:
            for _ in range(int(rng.poisson(p.wet_patches * self.g.length / 10.0))):
                c = (rng.uniform(1.0, self.g.length - 1.0), lane + float(np.clip(rng.normal(0, 2.2), -4.5, 4.5)))
                axes = (int(rng.uniform(0.4, 1.8) / _DIRT_RES), int(rng.uniform(0.3, 1.0) / _DIRT_RES))
                cv2.ellipse(wet, (int(c[0] / _DIRT_RES), int((c[1] - self.g.y_min) / _DIRT_RES)), axes,
                            float(rng.uniform(0, 180)), 0, 360, 1.0, -1)
        wet = cv2.GaussianBlur(wet, (0, 0), 4.0).astype(np.float32, copy=False)
        yy, xx = np.mgrid[0:h, 0:w].astype(np.float32) * _DIRT_RES
        n = self.concrete(xx.ravel() * 0.8, yy.ravel() * 0.8).reshape(h, w)
        return np.clip((wet - 0.35 + 2.5 * (n - 1.0)) * 3.0, 0.0, 1.0).astype(np.float32)[..., None]

    def _mirror_map(self, blur: float) -> np.ndarray:
        """Radiance [H, W, 1] of the ceiling plane at 5 cm as a floor reflects it: the lit fixtures' diffusers,
        blurred by ``blur`` (m) for the floor's roughness."""
        w, h = self._floor_grid(_DIRT_RES)
        img = np.zeros((h, w), np.float32)
        for L in self.g.lights:
            if L.intensity > 0:
                x0, x1 = (L.x - 0.625) / _DIRT_RES, (L.x + 0.625) / _DIRT_RES
                y0, y1 = (L.y - 0.08 - self.g.y_min) / _DIRT_RES, (L.y + 0.08 - self.g.y_min) / _DIRT_RES
                cv2.rectangle(img, (int(x0), int(y0)), (int(x1), int(y1)), _FIXTURE_EMISSION, -1)
        return cv2.GaussianBlur(img, (0, 0), blur / _DIRT_RES).astype(np.float32, copy=False)[..., None]

    def _specular(self, pts: np.ndarray, dirs: np.ndarray) -> np.ndarray:
        """View-dependent floor reflection [N] of floor hits ``pts`` seen along unit ``dirs``: the ceiling and its
        fixtures mirrored about the floor (sharp in wet patches, blurred on a glossy floor), weighted by Schlick's
        Fresnel term, so it grows towards grazing views and moves with the camera."""
        p = self.g.params
        spec = np.zeros(len(pts), np.float32)
        down = dirs[:, 2] < -1e-3  # rays from a camera; the point cloud's direction-less samples get none
        if self.mirror is None or not down.any():
            return spec
        d, x, y = dirs[down], pts[down, 0], pts[down, 1]
        reach = self.g.height / -d[:, 2]
        qx, qy = x + d[:, 0] * reach, y + d[:, 1] * reach
        inside = (qx >= 0) & (qx <= self.g.length) & (qy >= self.g.y_min) & (qy <= self.g.y_max)
        fresnel = 0.02 + 0.98 * (1.0 + d[:, 2]) ** 5
        fx, fy = self._to_texel(qx, qy, _DIRT_RES)
        ceiling = 0.5 * (0.1 + 0.5 * self.irradiance(qx, qy))
        sharp = _bilinear(self.mirror[0], fx, fy, False)[:, 0] + ceiling
        broad = _bilinear(self.mirror[1], fx, fy, False)[:, 0] + ceiling
        wet = np.zeros(len(x), np.float32)
        if self.wet is not None:
            wet = _bilinear(self.wet, *self._to_texel(x, y, _DIRT_RES), False)[:, 0]
        spec[down] = np.where(inside, fresnel * (wet * sharp + 0.4 * p.floor_gloss * (1.0 - wet) * broad), 0.0)
        return spec

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
        albedo = grey * bare * np.array([1.0, 0.98, 0.94], np.float32) + cover[:, :1] * white + cover[:, 1:] * yellow
        if self.dirt is not None or self.wet is not None:
            dx, dy = self._to_texel(x, y, _DIRT_RES)
            if self.dirt is not None:
                albedo *= _bilinear(self.dirt, dx, dy, False)
            if self.wet is not None:  # wet concrete and paint look darker
                albedo *= 1.0 - 0.4 * _bilinear(self.wet, dx, dy, False)
        return albedo

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
        if self.g.params.grime > 0:  # run-off streaks down walls and pillars, splash dirt near the floor
            dirty = wall | pick("pillar")
            streak = np.clip(self.concrete(u[dirty] * 6.0, z[dirty] * 0.25) - 0.95, 0.0, 0.3) / 0.3
            splash = np.exp(-z[dirty] / 0.3)
            albedo[dirty] *= (1.0 - self.g.params.grime * (0.45 * streak + 0.35 * splash))[:, None]
        u_right = np.select([face == 0, face == 1, face == 2], [ly, -ly, -lx], lx)
        self.decals.apply(idx, face, u_right, z, albedo, conc)
        emission = np.where(pick("fixture"), np.where(face == 5, _FIXTURE_EMISSION, 1.5), 0.0).astype(np.float32)
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
        if self.mirror is not None:
            out[floor] += self._specular(pts[floor], hits.dirs.reshape(-1, 3)[floor])[:, None]
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
    """Which camera effects to apply (each can be switched off for clean ground truth) and how strong they are;
    the defaults are scene1-4's. docs/synth.md gives each knob's range and what it imitates."""

    exposure: bool = True
    vignetting: bool = True
    noise: bool = True
    exposure_low: float = 0.82
    exposure_high: float = 1.18
    drift: float = 0.04
    white_balance: float = 0.0
    vignette_strength: float = 0.4
    noise_scale: float = 1.0
    motion_blur: float = 0.0

    def __post_init__(self) -> None:
        checks = {"exposure_low": 0 < self.exposure_low <= self.exposure_high,
                  "exposure_high": self.exposure_high <= 4.0, "drift": 0 <= self.drift < 1,
                  "white_balance": 0 <= self.white_balance < 0.5, "vignette_strength": 0 <= self.vignette_strength <= 1,
                  "noise_scale": 0 <= self.noise_scale <= 10, "motion_blur": 0 <= self.motion_blur <= 0.1}
        bad = [f"{k} {getattr(self, k):g}" for k, ok in checks.items() if not ok]
        if bad:
            raise ValueError(f"sensor options out of range: {', '.join(bad)} (0 < exposure_low <= exposure_high <= 4, "
                             "drift in [0, 1), white_balance in [0, 0.5), vignette_strength in [0, 1], noise_scale "
                             "in [0, 10], motion_blur (s) in [0, 0.1])")


class Sensor:
    """Per-camera exposure (fixed offset + slow auto-exposure drift), white balance, vignetting, gamma, noise."""

    def __init__(self, names: list[str], models: dict, options: SensorOptions, seed: int) -> None:
        rng = np.random.default_rng(seed + 11)
        self.options, self.seed = options, seed
        self.gain = {n: float(rng.uniform(options.exposure_low, options.exposure_high)) for n in names}
        self.phase = {n: float(rng.uniform(0, 2 * math.pi)) for n in names}
        self.vignette = {n: self._vignette(models[n], options.vignette_strength) for n in names}
        # white balance: per-camera channel gains (green fixed), from their own stream so scene1-4 keep theirs
        wb = np.random.default_rng([seed, 11, 1])
        self.balance = {n: np.array([1.0 + options.white_balance * wb.uniform(-1, 1), 1.0,
                                     1.0 + options.white_balance * wb.uniform(-1, 1)], np.float32) for n in names}

    @staticmethod
    def _vignette(model, strength: float) -> np.ndarray:
        """Radial fall-off: 1 at the centre, ``1 - strength`` at the lens' edge."""
        v, u = np.mgrid[0:model.height, 0:model.width].astype(np.float64)
        r = np.hypot((u - float(model.cx)) / float(model.fx), (v - float(model.cy)) / float(model.fy)) / model.rho_max
        return (1.0 - strength * np.clip(r, 0, 1) ** 2.5).astype(np.float32)[..., None]

    def exposure(self, name: str, frame: int) -> float:
        """Exposure factor of a camera at a frame."""
        if not self.options.exposure:
            return 1.0
        return self.gain[name] * (1.0 + self.options.drift * math.sin(0.07 * frame + self.phase[name]))

    def __call__(self, name: str, frame: int, radiance: np.ndarray, valid: np.ndarray,
                 exposure_frame: int | None = None) -> np.ndarray:
        """Linear radiance [H, W, 3] -> float32 display image in [0, 1], black outside the lens circle; ``frame``
        seeds the noise, ``exposure_frame`` (default ``frame``) sets the auto-exposure drift."""
        img = radiance * (1.25 * self.exposure(name, frame if exposure_frame is None else exposure_frame))
        if self.options.exposure and self.options.white_balance > 0:
            img = img * self.balance[name]
        if self.options.vignetting:
            img = img * self.vignette[name]
        img = to_srgb(img)
        if self.options.noise:
            rng = np.random.default_rng([self.seed, frame, sorted(self.gain).index(name)])
            sigma = 0.006 + 0.012 * np.sqrt(img)
            if self.options.noise_scale != 1.0:
                sigma = sigma * np.float32(self.options.noise_scale)
            img = img + sigma * rng.standard_normal(img.shape, dtype=np.float32)
        return np.clip(img, 0.0, 1.0).astype(np.float32) * valid[..., None]
