"""Synthetic garage: labels sit on paint in the GT BEV, geometry matches the camera model and depth."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest
import torch

from parksim.data import DatasetReader
from parksim.synth import SceneRenderer, generate, get_preset
from parksim.synth.labels import _seen
from parksim.synth.layout import Box
from parksim.synth.raycast import FLOOR, BoxSet, box_id, trace_world
from parksim.synth.shading import SensorOptions

TINY = get_preset("tiny")


@pytest.fixture(scope="module")
def scene(tmp_path_factory) -> Path:
    """The tiny preset, generated once for the module."""
    return generate(TINY, tmp_path_factory.mktemp("synth") / "tiny")


@pytest.fixture(scope="module")
def renderer() -> SceneRenderer:
    return SceneRenderer(TINY)


def test_layout_is_complete(scene):
    r = DatasetReader(scene)
    r.validate(deep=True)
    assert r.frames == list(range(TINY.frames))
    assert r.split["test"] == [0, 10] and len(r.split["train"]) == TINY.frames - 2
    assert r.meta["preset"] == "tiny" and r.meta["width"] == 160
    assert len(r.points[0]) == TINY.points
    kinds = {o["kind"] for o in r.map["obstacles"]}
    assert {"pillar", "car", "wall"} <= kinds
    assert not list(scene.parent.glob(".tiny.tmp-*"))
    n_marks = [len(r.labels(f)["marks"]) for f in r.frames]
    assert min(n_marks) >= 2, n_marks


def test_marks_lie_on_painted_lines(scene):
    """Each labelled marking point is brighter than the concrete around it in the GT IPM image."""
    r = DatasetReader(scene)
    checked = 0
    for f in r.frames:
        bev = r.ipm(f).numpy().max(-1)  # paint is bright in some channel (white or yellow)
        for m in r.labels(f)["marks"]:
            u, v = int(round(m["x"])), int(round(m["y"]))
            patch = bev[max(v - 1, 0):v + 2, max(u - 1, 0):u + 2]
            around = bev[max(v - 15, 0):v + 16, max(u - 15, 0):u + 16]
            assert patch.mean() > np.median(around) + 0.04, (f, m, patch.mean(), np.median(around))
            checked += 1
    assert checked >= 20


def test_shapes_and_directions(renderer):
    """T where the entrance line continues both ways, L at row ends; directions point into the slot; the slot
    angle is the one from the entrance p1 -> p2 to the separators (120 deg for a 60 deg slant on the +y side)."""
    g = renderer.garage
    for s in g.slots:
        a, b = g.marks[s.p1], g.marks[s.p2]
        entrance = np.array([b.x - a.x, b.y - a.y])
        into = np.array([np.cos(a.direction), np.sin(a.direction)])
        # slot on the right of p1 -> p2: cross(entrance, into) < 0 in the world (z up)
        assert entrance[0] * into[1] - entrance[1] * into[0] < 0
        cos = entrance @ into / np.linalg.norm(entrance)
        assert s.angle_deg == pytest.approx(np.degrees(np.arccos(cos)), abs=1e-6)
    assert {s.angle_deg for s in g.slots if s.kind == "slanted"} == {60.0, 120.0}
    shapes = [m.shape for m in g.marks]
    assert "T" in shapes and "L" in shapes


def test_point_seen_by_a_third_of_the_blend_is_labelled():
    """The BEV blends cameras by weight: paint seen clearly by cameras with 35 % of the weight still shows there
    (beside the ego, the front or rear camera sees its own body), so the point is labelled; at 25 % it is not."""
    wall = BoxSet.from_boxes([Box(1.0, 0.0, 0.0, 3.0, 0.2, 4.0, 0.0, "pillar")])  # hides the point from "a" only
    point = np.array([2.0, 0.0, 0.0])
    origins = {"a": np.array([0.0, 0.0, 1.0]), "b": np.array([2.0, 3.0, 1.0])}
    assert _seen(point, origins, {"a": 0.65, "b": 0.35}, wall, 3.0)
    assert not _seen(point, origins, {"a": 0.75, "b": 0.25}, wall, 3.0)


def _visible(origin: np.ndarray, point: np.ndarray, boxes: BoxSet, height: float) -> bool:
    ray = point - origin
    dist = np.linalg.norm(ray)
    return trace_world(origin, (ray / dist)[None], boxes, height).t[0] >= dist - 0.02


def test_pillar_corner_projects_where_drawn():
    """A pillar's floor corner, projected by the camera model, lands on the pillar/floor boundary
    the ray caster drew, in every camera that sees it (at 320x240 so pillars span pixels)."""
    renderer = SceneRenderer(dataclasses.replace(TINY, width=320, height=240))
    g = renderer.garage
    checked = 0
    for i, b in enumerate(g.boxes):
        if b.material != "pillar":
            continue
        for dx in (-3.0, 0.0, 3.0):  # drive past the pillar in the aisle
            pose = np.eye(4)
            pose[:2, 3] = [b.cx + dx, g.lanes[0]]
            views = renderer.render(pose, 0)
            boxes = renderer.boxes_at(pose)
            for corner in b.corners_xy():
                p = np.array([corner[0], corner[1], 0.0])
                for name, cam in renderer.rig.cameras.items():
                    T = renderer.camera_pose(pose, name)
                    if not _visible(T[:3, 3], p, boxes, g.height):
                        continue
                    p_cam = (p - T[:3, 3]) @ T[:3, :3]
                    uv, valid = cam.model.project(torch.from_numpy(p_cam))
                    u, v = (int(round(float(c))) for c in uv)
                    # away from the lens rim, where a pillar is squeezed below a pixel
                    if not valid or float(cam.model.theta_of(torch.from_numpy(p_cam))) > np.radians(80):
                        continue
                    ids = views[name].prim[v - 2:v + 3, u - 2:u + 3]
                    assert box_id(i) in ids and FLOOR in ids, (name, dx, uv, ids)
                    checked += 1
    assert checked >= 2


def _box_sdf(points: np.ndarray, boxes: BoxSet) -> np.ndarray:
    """Unsigned distance of points [N, 3] to the nearest box surface."""
    rel = points[:, None, :] - boxes.centres[None]
    c, s = boxes.yaw_cs[None, :, 0], boxes.yaw_cs[None, :, 1]
    local = np.stack([c * rel[..., 0] + s * rel[..., 1], -s * rel[..., 0] + c * rel[..., 1], rel[..., 2]], -1)
    q = np.abs(local) - boxes.halves[None]
    outside = np.linalg.norm(np.maximum(q, 0), axis=-1)
    inside = np.minimum(q.max(-1), 0)
    return np.abs(outside + inside).min(1)


def test_depth_agrees_with_geometry(scene, renderer):
    """Every depth pixel, unprojected with the camera model, lies on the floor, ceiling or a box face."""
    r = DatasetReader(scene)
    f = 5
    pose = r.pose(f).numpy()
    boxes = renderer.boxes_at(pose)
    for name, cam in r.rig.cameras.items():
        depth = r.depth(name, f).numpy().astype(np.float64)
        v, u = np.nonzero(depth > 0)
        assert len(v) > 0.5 * depth.size
        rays = cam.model.unproject(torch.from_numpy(np.stack([u, v], -1).astype(np.float64))).numpy()
        T = pose @ cam.T_vehicle_camera.numpy()
        pts = (rays * depth[v, u, None]) @ T[:3, :3].T + T[:3, 3]
        dist = np.minimum(np.minimum(np.abs(pts[:, 2]), np.abs(pts[:, 2] - renderer.garage.height)),
                          _box_sdf(pts, boxes))
        assert np.quantile(dist, 0.999) < 0.004 and dist.max() < 0.05, (name, dist.max())


def test_seeded_and_switchable(renderer):
    pose = np.eye(4)
    pose[:2, 3] = [12.0, renderer.garage.lanes[0]]
    a = renderer.render(pose, 3, ["front"])["front"].image
    b = renderer.render(pose, 3, ["front"])["front"].image
    assert np.array_equal(a, b)
    clean = SceneRenderer(dataclasses.replace(TINY, sensor=SensorOptions(False, False, False)))
    c = clean.render(pose, 3, ["front"])["front"].image
    assert 0.005 < np.abs(a - c).mean() < 0.2


def test_labels_json_is_dmpr_like(scene):
    data = json.loads((scene / "labels" / "000006.json").read_text())
    assert set(data) == {"frame", "bev", "marks", "slots"}
    for m in data["marks"]:
        assert set(m) >= {"x", "y", "direction", "shape"} and m["shape"] in ("T", "L")
    for s in data["slots"]:
        assert s["type"] in ("perpendicular", "parallel", "slanted") and 0 < s["angle"] < 180
