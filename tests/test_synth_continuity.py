"""Continuity: the benchmark presets render as they did before the `worn`/`busy` presets were added.

The reference (tests/data/synth_continuity.npz) was computed once from the code before those presets existed
(commit bd297c8). It holds the layout's boxes and marking points and, per camera at two poses, 8x8-pixel block
means of the image and depth (stored as float32): any change to geometry, paint, lighting, exposure or noise
seeding moves some block mean by far more than float rounding (~1e-6) does, while the comparison stays immune to
last-bit differences between CPUs.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest

from parksim.synth import SceneRenderer, get_preset
from parksim.synth.trajectory import drive

REFERENCE = Path(__file__).with_name("data") / "synth_continuity.npz"
CASES = {"tiny": (0, 7), "scene1": (3, 40)}
"""Preset -> the two frames of its trajectory that are rendered (scene1 at tiny size: 160x120)."""
_BLOCK = 8


def _blocks(a: np.ndarray) -> np.ndarray:
    """Means over 8x8 pixel blocks of ``a[H, W, ...]`` (H, W multiples of 8)."""
    h, w = a.shape[:2]
    return a.reshape(h // _BLOCK, _BLOCK, w // _BLOCK, _BLOCK, *a.shape[2:]).mean((1, 3))


def fingerprint(name: str) -> dict[str, np.ndarray]:
    """Layout arrays and per-camera block means of the preset's renders at ``CASES[name]``, float64."""
    preset = dataclasses.replace(get_preset(name), width=160, height=120, bev_px=300)
    renderer = SceneRenderer(preset)
    g = renderer.garage
    out = {f"{name}/boxes": np.array([[b.cx, b.cy, b.z0, b.z1, b.length, b.width, b.yaw] for b in g.boxes]),
           f"{name}/marks": np.array([[m.x, m.y, m.direction] for m in g.marks])}
    poses, _ = drive(g, preset.trajectory, max(CASES[name]) + 1)
    for f in CASES[name]:
        for cam, view in renderer.render(poses[f], f).items():
            out[f"{name}/{f}/{cam}/image"] = _blocks(view.image.astype(np.float64))
            out[f"{name}/{f}/{cam}/depth"] = _blocks(view.depth.astype(np.float64))
    return out


@pytest.mark.parametrize("name", list(CASES))
def test_preset_renders_as_before(name):
    ref = np.load(REFERENCE)
    now = fingerprint(name)
    assert sorted(now) == sorted(k for k in ref.files if k.startswith(f"{name}/"))
    for key, value in now.items():
        # layout: float64 geometry; images in [0, 1] and depth (m, < 60) as means of 64 float32 pixels
        tol = 1e-9 if key.count("/") == 1 else 2e-5
        assert value.shape == ref[key].shape, key
        assert np.abs(value - ref[key]).max() <= tol, (key, np.abs(value - ref[key]).max())
