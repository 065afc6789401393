"""Scenario pictures: the garage mosaic is the scene seen from above (parked cars where the map has them), a
thumbnail shows a parked car on the side it stands, an episode plot is a 600 x 500 PNG whose title tells success
from a collision, and bad input is a one-line ValueError.

The scene is scene1's garage as a 300-Gaussian bundle with a 64 px BEV."""

from __future__ import annotations

import dataclasses
import math

import cv2
import numpy as np
import pytest
import torch

from parksim.bundle import Bundle, load
from parksim.gaussians import SH_C0, GaussianScene
from parksim.scenarios import ActorSpec, Scenario
from parksim.scenarios.episode import Episode
from parksim.scenarios.pictures import EGO_RGB, SLOT_RGB, BevMap, bev_mosaic, plot_episode, summary, thumbnail
from parksim.scenarios.spec import EgoStart, PedestrianSpec
from parksim.scenarios.task import slot_pose
from parksim.sim import LocalSim
from parksim.vehicle import Obstacles, VehicleParams
from sim_fixtures import make_bundle

MARKERS = {0: (20.0, 2.0), 2: (30.0, -1.5)}
"""Paint spots added to the aisle floor, pure red (channel 0) and blue (2), channel -> world xy (m): off the
aisle's centre line, so a view flipped or turned in the mosaic puts them elsewhere."""


def _with_markers(bundle: Bundle) -> Bundle:
    """``bundle`` with an opaque flat disc (sigma 0.3 m) of each ``MARKERS`` colour lying on the floor."""
    scene, n = bundle.scene, len(MARKERS)
    xy = torch.tensor(list(MARKERS.values()), dtype=scene.means.dtype)
    rgb = torch.eye(3, dtype=scene.means.dtype)[list(MARKERS)]
    spots = GaussianScene(torch.cat([xy, torch.full((n, 1), 0.02)], 1), torch.tensor([[1.0, 0, 0, 0]] * n),
                          torch.tensor([[math.log(0.3), math.log(0.3), math.log(0.005)]] * n),
                          torch.full((n,), 6.0), ((rgb - 0.5) / SH_C0)[:, None], 0)
    merged = GaussianScene(**{k: torch.cat([getattr(scene, k), getattr(spots, k).to(scene.means)]) for k in
                              ("means", "quats", "log_scales", "opacity_logits", "sh")}, sh_degree=0)
    return dataclasses.replace(bundle, scene=merged)


@pytest.fixture(scope="module")
def sim(tmp_path_factory):
    folder = make_bundle(tmp_path_factory.mktemp("pictures") / "scene1", preset="scene1", n=300, bev_px=64)
    return LocalSim(_with_markers(load(folder)))


@pytest.fixture(scope="module")
def world_map(sim):
    return sim.bundle.map


@pytest.fixture(scope="module")
def mosaic(sim, world_map):
    return bev_mosaic(sim, world_map)


def _one_line(error: pytest.ExceptionInfo) -> str:
    message = str(error.value)
    assert message and "\n" not in message, message
    return message


def _mean_in(bev: BevMap, corners: np.ndarray) -> float:
    """Mean pixel value of the map inside a world polygon."""
    x0, _, _, y1 = bev.extent
    px = np.round(np.stack([(corners[:, 0] - x0) / bev.m_per_px, (y1 - corners[:, 1]) / bev.m_per_px], -1))
    inside = np.zeros(bev.seen.shape, np.uint8)
    cv2.fillPoly(inside, [px.astype(np.int32)], 1)
    return float(bev.image[inside.astype(bool)].mean())


def test_the_mosaic_is_the_garage_seen_from_above(mosaic, world_map):
    g = world_map["garage"]
    x0, x1, y0, y1 = mosaic.extent
    h, w, _ = mosaic.image.shape
    assert mosaic.image.dtype == np.uint8 and mosaic.seen.shape == (h, w)
    assert (x0, y0) == (g["x"][0], g["y"][0]) and math.isclose(mosaic.m_per_px, 10.0 / 64)
    assert 0 <= x1 - g["x"][1] < mosaic.m_per_px and 0 <= y1 - g["y"][1] < mosaic.m_per_px
    assert mosaic.seen.all(), "every pixel of the garage is covered, under the ego boxes too"
    assert mosaic.image.std() > 10, "not uniform"
    obstacles = Obstacles(world_map["obstacles"])
    cars = [_mean_in(mosaic, c) for kind, c in zip(obstacles.kinds, obstacles.corners()) if kind == "car"]
    free = [_mean_in(mosaic, np.asarray(s["corners"])) for s in world_map["slots"] if not s["occupied"]]
    assert len(cars) >= 3 and np.mean(cars) < np.mean(free) - 15, "the parked cars are where the map has them"


def test_floor_marks_land_where_they_lie(mosaic):
    """Each marker's colour, found in the aisle away from the red parked car, is centred on the marker."""
    aisle = mosaic.crop(14.0, 36.0, -3.0, 3.0)
    x0, _, _, y1 = aisle.extent
    image = aisle.image.astype(int)
    for c, (x, y) in MARKERS.items():
        rows, cols = np.nonzero(image[..., c] - np.delete(image, c, -1).max(-1) > 60)
        assert len(rows) > 4, f"marker at ({x}, {y}) not found"
        found = (x0 + (cols.mean() + 0.5) * aisle.m_per_px, y1 - (rows.mean() + 0.5) * aisle.m_per_px)
        assert math.dist(found, (x, y)) < 0.3, (found, (x, y))


def test_mosaic_resolution_and_crop(sim, world_map, mosaic):
    coarse = bev_mosaic(sim, world_map, m_per_px=0.5)
    assert coarse.image.shape == (35, 96, 3) and coarse.seen.all()
    np.testing.assert_allclose(coarse.extent, (0.0, 48.0, -8.7, 8.8))
    assert abs(float(coarse.image.mean()) - float(mosaic.image.mean())) < 5
    part = coarse.crop(10.2, 12.0, -1.0, 0.9)
    assert part.image.shape == (5, 4, 3), "whole pixels: rows from y 1.3 down to -1.2, columns x 10 to 12"
    np.testing.assert_allclose(part.extent, (10.0, 12.0, -1.2, 1.3))
    np.testing.assert_array_equal(part.image, coarse.image[15:20, 20:24])
    assert "outside the BEV map" in _one_line(pytest.raises(ValueError, coarse.crop, 50, 60, 0, 1))


def test_mosaic_bad_input(sim, world_map):
    assert "garage" in _one_line(pytest.raises(ValueError, bev_mosaic, sim, {"slots": []}))
    flat = dict(world_map, garage={"x": [0.0, 0.0], "y": [-1.0, 1.0]})
    assert "empty" in _one_line(pytest.raises(ValueError, bev_mosaic, sim, flat))
    assert "m_per_px" in _one_line(pytest.raises(ValueError, bev_mosaic, sim, world_map, 0.0))


START = Scenario(name="start", scene="scene1", ego=EgoStart(pose=(9.0, -1.5, 0.0)), target=1)
"""The ego in the aisle beside slanted slots 0 and 1, to its right (-y); slot 1 is the target."""


def test_a_thumbnail_shows_a_parked_car_on_its_side(sim, world_map):
    empty = thumbnail(Episode(START, world_map, sim, cameras=[], bev=True))
    parked = thumbnail(Episode(START.model_copy(update={"occupy": (0,)}), world_map, sim, cameras=[], bev=True))
    assert empty.shape == parked.shape == (256, 256, 3) and empty.dtype == np.uint8
    green = np.abs(empty.astype(int) - SLOT_RGB).max(-1) < 40
    orange = np.abs(empty.astype(int) - EGO_RGB).max(-1) < 40
    assert green[:, 128:].sum() > 100 and not green[:, :96].any(), "the target slot is on the right"
    assert orange[:, 96:160].sum() > 300, "the ego's outline is in the middle"
    change = np.abs(empty.astype(int) - parked).max(-1)
    assert change[:, 128:].max() > 40 and not change[:, :128].any(), "the parked car (right, -y) and only it"
    small = thumbnail(Episode(START, world_map, sim, cameras=[], bev=True), size=64)
    assert small.shape == (64, 64, 3)


def test_thumbnail_bad_input(sim, world_map):
    assert "renderer" in _one_line(pytest.raises(ValueError, thumbnail, Episode(START, world_map)))
    no_bev = Episode(START, world_map, sim, cameras=["front"])
    assert "bev=True" in _one_line(pytest.raises(ValueError, thumbnail, no_bev))
    moved = Episode(START, world_map, sim, cameras=[], bev=True)
    moved.advance([0.0, 0.0])
    assert "begin()" in _one_line(pytest.raises(ValueError, thumbnail, moved))
    assert "8 px" in _one_line(pytest.raises(ValueError, thumbnail, Episode(START, world_map, sim, bev=True), 4))


@pytest.fixture(scope="module")
def episodes(world_map):
    """Two state-only episodes run to their end: the ego standing parked in slot 8 (a success), and the ego
    driving off while a pedestrian crosses in front of it (an actor collision)."""
    vehicle = VehicleParams()
    centre, yaw = slot_pose(world_map["slots"][8])
    d = (vehicle.extent[0] + vehicle.extent[1]) / 2
    pose = (float(centre[0] - d * math.cos(yaw)), float(centre[1] - d * math.sin(yaw)), yaw)
    walker = ActorSpec(name="walker", asset="pedestrian", pose=(13.0, -2.5, math.pi / 2),
                       behaviour=PedestrianSpec(type="pedestrian", to=(13.0, 2.5), speed=1.4))
    runs = {"parked": (Scenario(name="parked", scene="scene1", ego=EgoStart(pose=pose), target=8), [0.0, 0.0]),
            "walker": (Scenario(name="walker", scene="scene1", ego=EgoStart(pose=(10.0, 0.0, 0.0)), target=8,
                                actors=(walker,)), [0.5, 0.3])}
    out = {}
    for name, (scenario, action) in runs.items():
        episode = Episode(scenario, world_map)
        while not episode.done:
            episode.advance(action)
        out[name] = episode
    return out


def test_episode_plots(episodes, mosaic, tmp_path):
    ok, hit = episodes["parked"].result(), episodes["walker"].result()
    assert ok.success and hit.actor_collisions == 1
    assert summary(ok).startswith("success |") and "no collision" in summary(ok)
    assert summary(hit).startswith("failure |") and "1 actor collision from" in summary(hit)
    images = []
    for name, card in (("parked", ok), ("walker", hit)):
        path = plot_episode(episodes[name].log, card, mosaic, tmp_path / "plots" / f"{name}.png", name)
        assert path == tmp_path / "plots" / f"{name}.png" and path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
        images.append(cv2.imread(str(path), cv2.IMREAD_COLOR))
        assert images[-1].shape == (500, 600, 3)
    assert sorted(p.name for p in (tmp_path / "plots").iterdir()) == ["parked.png", "walker.png"], "no temp left"
    assert (images[0][:40] != images[1][:40]).any(), "the titles differ"
    red = [int((np.abs(image.astype(int) - (0, 0, 255)).max(-1) < 60).sum()) for image in images]   # BGR
    assert red[1] > red[0] + 50, "the walker's track and footprint (red) are drawn"
    assert np.mean(images[0][60:440, 100:400]) < 200, "the plot area shows the mosaic, not a white page"


def test_plot_bad_input(episodes, mosaic, tmp_path):
    log, card = episodes["parked"].log, episodes["parked"].result()
    assert ".png" in _one_line(pytest.raises(ValueError, plot_episode, log, card, mosaic, tmp_path / "a.jpg", "a"))
    away = BevMap(mosaic.image, (100.0, 148.125, 100.0, 117.5), mosaic.seen)
    assert "outside" in _one_line(pytest.raises(ValueError, plot_episode, log, card, away, tmp_path / "a.png", "a"))
    assert not list(tmp_path.iterdir())
