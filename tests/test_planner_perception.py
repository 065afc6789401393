"""Perception planner: BEV training labels and detected-slot geometry agree with the map; the runner needs a BEV."""

from __future__ import annotations

import math

import numpy as np
import pytest

from parksim.bundle import load
from parksim.env import ParkingEnv
from parksim.planners.perception import PerceptionParker, detected_slots, run_perception_episode
from parksim.planners.slot_data import bev_labels, write_training_bevs
from parksim.recon.detectors import Detections, DMPRDetector, MarkingPoint, Slot
from parksim.recon.detectors.dataset import iter_items
from sim_fixtures import make_bundle


def _vehicle(pose: tuple[float, float, float], xy: np.ndarray) -> np.ndarray:
    x, y, yaw = pose
    c, s = math.cos(yaw), math.sin(yaw)
    d = np.asarray(xy, np.float64) - (x, y)
    return np.stack([c * d[..., 0] + s * d[..., 1], -s * d[..., 0] + c * d[..., 1]], -1)


@pytest.fixture(scope="module")
def bundle(tmp_path_factory):
    return make_bundle(tmp_path_factory.mktemp("perception") / "tiny")


def _slot_view(world_map: dict, slot: dict) -> tuple[float, float, float]:
    """A rear-axle pose 5.5 m before ``slot``'s entrance on its axis, facing in (the slot ahead in the BEV)."""
    c = np.asarray(slot["corners"], np.float64)
    entrance, axis = c[:2].mean(axis=0), c[2:].mean(axis=0) - c[:2].mean(axis=0)
    axis /= np.linalg.norm(axis)
    x, y = entrance - 5.5 * axis
    return float(x), float(y), math.atan2(axis[1], axis[0])


def test_labels_and_detected_slots_round_trip_the_map(bundle):
    """Map slots -> BEV labels -> Detections -> ``detected_slots`` gives back the map's corners in the ego frame."""
    b = load(bundle)
    spec, world_map = b.rig.bev, b.map
    slot = next(s for s in world_map["slots"] if s["type"] == "slanted")
    pose = _slot_view(world_map, slot)
    labels = bev_labels(world_map, pose, spec)
    points = [MarkingPoint(x - 1, y - 1, math.atan2(yd - y, xd - x), "L" if sh else "T", 1.0)
              for x, y, xd, yd, sh in labels["marks"]]
    slots = [Slot(p1 - 1, p2 - 1, 1.0, angle) for p1, p2, _, angle in labels["slots"]]
    found = detected_slots(Detections(points, slots), spec)
    assert found, labels
    expected = [_vehicle(pose, np.asarray(s["corners"])) for s in world_map["slots"]]
    for corners in found:
        best = min(expected, key=lambda e: float(np.abs(e[:2] - corners[:2]).max()))
        # float64 all the way (pixels, angles, depth by kind = the map's): rounding only, at ~20 m magnitudes
        assert np.abs(best - corners).max() <= 64 * np.spacing(20.0), (best, corners)


def test_training_bevs_are_labelled_ps2_pairs(bundle, tmp_path):
    items = list(iter_items(write_training_bevs(bundle, tmp_path / "bevs", 4, seed=1, scale=0.5)))
    assert len(items) == 4 and all(i.image.shape == (300, 300, 3) for i in items)
    assert sum(len(i.labels.slots) for i in items) > 0


def test_perception_episode_needs_the_bev(bundle):
    env = ParkingEnv(bundle=bundle, cameras=[])
    detector = DMPRDetector(width=0.125, input_size=64).eval()   # refused before it is used
    with pytest.raises(ValueError, match="bev=True"):
        run_perception_episode(env, 0, PerceptionParker(detector, env.sim.bundle.rig.bev))
