"""The worn and busy presets' ingredients: varied cars, clutter and signs, worn paint, view-dependent wet and
glossy floor, camera knobs, motion blur; and their checks on bad input."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from parksim.cli import main
from parksim.synth import SceneRenderer, get_preset
from parksim.synth.cars import BODY_TYPES, car_boxes, random_shape
from parksim.synth.layout import Box, Decal, LayoutParams, build_garage
from parksim.synth.raycast import FLOOR, BoxSet, Hits
from parksim.synth.rig import ego_box
from parksim.synth.shading import SensorOptions, Shader
from parksim.synth.signage import DecalSet

TINY = get_preset("tiny")


def _dressed(**knobs: float | bool) -> LayoutParams:
    """The tiny garage with some of the real-garage knobs turned on."""
    return dataclasses.replace(TINY.layout, **knobs)


def _footprint_inside(inner: Box, outer: Box, tol: float) -> bool:
    """Whether all floor-plan corners of ``inner`` lie in ``outer`` grown by ``tol``."""
    c, s = math.cos(outer.yaw), math.sin(outer.yaw)
    rel = inner.corners_xy() - [outer.cx, outer.cy]
    local = rel @ np.array([[c, -s], [s, c]])
    return bool(np.all(np.abs(local) <= [outer.length / 2 + tol, outer.width / 2 + tol]))


@pytest.mark.parametrize("kind", list(BODY_TYPES))
def test_car_is_several_boxes_within_its_outline(kind):
    rng = np.random.default_rng(3)
    shape = random_shape(rng, kind)
    boxes = car_boxes(shape, 10.0, 4.0, 0.7, (0.5, 0.1, 0.1))
    outline = Box(10.0, 4.0, 0.0, shape.height, shape.length, shape.width, 0.7, "car")
    assert len(boxes) >= 13 and {b.material for b in boxes} >= {"car_body", "car_window", "wheel"}
    assert all(_footprint_inside(b, outline, 0.061) for b in boxes)  # bumpers stand 6 cm proud
    assert max(b.z1 for b in boxes) == pytest.approx(shape.height) and min(b.z0 for b in boxes) == 0.0
    lo, hi = zip(*BODY_TYPES[kind][:3])
    assert np.all(np.array(lo) <= [shape.length, shape.width, shape.height])
    assert np.all([shape.length, shape.width, shape.height] <= np.array(hi))


def test_varied_cars_clutter_and_signs_leave_the_classic_layout_alone():
    """Dressing adds boxes after the classic ones and never moves them; slots, marks and paint are the same."""
    plain = build_garage(TINY.layout)
    dressed = build_garage(_dressed(car_variety=1.0, clutter=1.0, signage=True))
    assert dressed.slots == plain.slots and dressed.marks == plain.marks and dressed.paint == plain.paint
    sizes = {(round(c.length, 2), round(c.width, 2)) for c in dressed.cars}
    assert len(sizes) >= min(3, len(dressed.cars)) and len(dressed.cars) == len(plain.cars)
    assert any(b.material == "clutter" for b in dressed.boxes) and any(b.material == "duct" for b in dressed.boxes)
    pillars = [i for i, b in enumerate(dressed.boxes) if b.material == "pillar"]
    assert {d.box for d in dressed.decals} & set(pillars)
    assert len(dressed.floor_text) == sum(s.kind != "parallel" for s in dressed.slots)
    walls = {i for i, b in enumerate(dressed.boxes) if b.material == "wall"}
    assert {d.box for d in dressed.decals} & walls


def test_decal_shows_only_inside_its_rectangle():
    decals = DecalSet([Decal(0, 2, 0.5, 1.5, 0.6, 0.4, "B7", (0.0, 0.0, 0.0), (1.0, 1.0, 1.0))], 1)
    u = np.array([0.5, 0.5, 0.9, 0.5])
    z = np.array([1.5, 1.36, 1.5, 1.5])
    face = np.array([2, 2, 2, 3])
    albedo = np.full((4, 3), 0.3, np.float32)
    decals.apply(np.zeros(4, np.int64), face, u, z, albedo, np.ones(4, np.float32))
    # centre: ink or panel (never the wall); near the panel's lower edge: the frame or panel; beside it and on
    # another face: the wall
    assert not np.allclose(albedo[0], 0.3) and not np.allclose(albedo[1], 0.3)
    assert np.allclose(albedo[2:], 0.3)


def _floor_hits(point: np.ndarray, dirs: np.ndarray) -> Hits:
    n = len(dirs)
    return Hits(np.ones(n), np.full(n, FLOOR, np.int32), np.full(n, 4, np.int8), np.repeat(point[None], n, 0),
                dirs)


def _directions() -> np.ndarray:
    """Unit rays hitting the floor steeply and at a grazing angle, from two sides."""
    d = np.array([[0.2, 0.0, -1.0], [4.0, 0.5, -1.0], [-4.0, 0.5, -1.0]])
    return d / np.linalg.norm(d, axis=1, keepdims=True)


def _shader(params: LayoutParams) -> tuple[Shader, BoxSet]:
    """The garage of ``params`` and its shader, with the ego parked at the origin."""
    garage = build_garage(params)
    boxes = BoxSet.from_boxes([*garage.boxes, ego_box(np.eye(4))])
    colors = np.array([b.color for b in garage.boxes] + [(0.1, 0.1, 0.1)])
    return Shader(garage, boxes, [b.material for b in garage.boxes] + ["ego"], colors, params.seed), boxes


def test_glossy_floor_is_view_dependent_and_plain_floor_is_not():
    """A glossy floor point's radiance changes with the viewing direction (Fresnel-weighted mirror image of the
    ceiling); a plain concrete floor (scene1-4) is Lambertian: the same from every direction."""
    point = np.array([17.0, 0.5, 0.0])  # mid-garage: both grazing reflections land on its ceiling
    looks = {}
    for gloss in (0.0, 1.0):
        shader, boxes = _shader(_dressed(floor_gloss=gloss))
        looks[gloss] = shader.radiance(_floor_hits(point, _directions()), boxes)
    assert np.ptp(looks[0.0], axis=0).max() == 0.0
    assert np.all(looks[1.0] >= looks[0.0])
    assert looks[1.0][1].mean() > looks[1.0][0].mean() + 0.003  # grazing reflects more than steep
    assert np.abs(looks[1.0][1] - looks[1.0][2]).max() > 1e-3  # and what it mirrors depends on the side


def test_worn_paint_fades_per_slot():
    """Paint coverage drops with paint_fade and scuff, by a different amount in different slots."""
    def coverage(params: LayoutParams) -> tuple[float, np.ndarray]:
        shader, _ = _shader(params)
        garage = shader.g
        per_slot = []
        for s in garage.slots:
            a = garage.marks[s.p1]
            x = np.array([a.x + 0.3 * math.cos(a.direction) * k for k in range(1, 12)])
            y = np.array([a.y + 0.3 * math.sin(a.direction) * k for k in range(1, 12)])
            px, py = shader._to_texel(x, y, 0.01)
            per_slot.append(shader.paint[np.rint(py).astype(int), np.rint(px).astype(int)].max(-1).mean())
        return float(shader.paint.astype(np.float64).sum()), np.array(per_slot)

    total_new, _ = coverage(TINY.layout)
    total_worn, slots_worn = coverage(_dressed(paint_fade=0.8, paint_scuff=0.3))
    assert total_worn < 0.8 * total_new
    assert np.ptp(slots_worn) > 20  # of 255


def test_motion_blur_moves_colour_only():
    """With a shutter time the colour image smears while depth (frame pose) stays exactly the same."""
    sharp = SceneRenderer(TINY)
    blurred = SceneRenderer(dataclasses.replace(TINY, sensor=SensorOptions(motion_blur=0.05)))
    pose = np.eye(4)
    pose[:2, 3] = [12.0, sharp.garage.lanes[0]]
    a, b = sharp.render(pose, 2, ["left"])["left"], blurred.render(pose, 2, ["left"])["left"]
    assert np.array_equal(a.depth, b.depth) and np.array_equal(a.prim, b.prim)
    assert 1e-3 < np.abs(a.image - b.image).mean() < 0.05


def test_per_camera_white_balance():
    renderer = SceneRenderer(dataclasses.replace(TINY, sensor=SensorOptions(white_balance=0.2)))
    gains = np.stack(list(renderer.sensor.balance.values()))
    assert np.all(gains[:, 1] == 1.0) and np.all(np.abs(gains - 1.0) <= 0.2)
    assert np.ptp(gains[:, 0]) > 0.01 and np.ptp(gains[:, 2]) > 0.01


@pytest.mark.parametrize("bad", [dict(car_variety=1.5), dict(stains=-1.0), dict(paint_fade=float("nan"))])
def test_layout_knobs_out_of_range(bad):
    with pytest.raises(ValueError, match="out of range"):
        dataclasses.replace(TINY.layout, **bad)


@pytest.mark.parametrize("bad", [dict(exposure_low=1.3), dict(white_balance=0.6), dict(motion_blur=0.5)])
def test_sensor_knobs_out_of_range(bad):
    with pytest.raises(ValueError, match="out of range"):
        SensorOptions(**bad)


def test_cli_offers_the_presets_and_checks_motion_blur(capsys):
    with pytest.raises(SystemExit) as e:
        main(["synth", "--help"])
    assert e.value.code == 0
    out = capsys.readouterr().out
    assert "worn" in out and "busy" in out and "--workers" in out and "--motion-blur" in out
    assert main(["synth", "tiny", "-o", "/nonexistent/x", "--motion-blur", "0.5"]) == 2
    assert "--motion-blur" in capsys.readouterr().err
