"""Guards against mutations the rest of the suite let through (issue 18): the env's progress reward's sign, 'parked'
needing the ego stopped, roll and pitch kept apart in a 6-value pose through GET /render, the importers refusing a
reflection as a rotation, and the compositing constants pinned to the values docs/api.md states. Each expected value
is derived here by hand, not by calling the code under test."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
from fastapi.testclient import TestClient

from parksim.env import ParkingEnv
from parksim.frames import decode_npz
from parksim.geometry import pose_from_xyz_rpy
from parksim.imageio import to_uint8
from parksim.importers.recording import RecordingError, check_pose
from parksim.render import render
from parksim.server import create_app
from parksim.sim import LocalSim
from sim_fixtures import make_bundle


@pytest.fixture(scope="module")
def bundle_dir(tmp_path_factory):
    return make_bundle(tmp_path_factory.mktemp("guards") / "tiny", n=1500, bev_px=64)


def _hand_cost(env: ParkingEnv) -> float:
    """docs/env.md's progress cost d + 0.5 e by hand: d from the body centre (half-way along the footprint's x extent
    ahead of the rear axle) to the slot centre (the mean of its corners), e the heading error to the slot's longer
    side, either way, in [0, pi/2]."""
    s, p = env.state, env.vehicle
    ahead = (p.extent[0] + p.extent[1]) / 2
    body = np.array([s.x + ahead * math.cos(s.yaw), s.y + ahead * math.sin(s.yaw)])
    corners = np.asarray(env.slot["corners"], np.float64)
    sides = [corners[1] - corners[0], corners[2] - corners[1]]
    axis = max(sides, key=lambda v: float(np.hypot(*v)))
    diff = (s.yaw - math.atan2(axis[1], axis[0])) % math.pi
    return float(np.linalg.norm(body - corners.mean(axis=0))) + 0.5 * min(diff, math.pi - diff)


def test_progress_reward_is_the_decrease_of_the_cost_minus_the_step_cost(bundle_dir):
    """Driving straight at the slot's axis for one 0.1 s step at 2 m/s: the reward is the hand-computed decrease
    of d + 0.5 e minus 0.01, and it is positive (a flipped sign makes it negative)."""
    env = ParkingEnv(bundle=bundle_dir, cameras=[])
    _, info = env.reset(seed=0)
    x, y, yaw = env.target_pose()
    back = 3.0
    env.reset(options={"start": (x - back * math.cos(yaw), y - back * math.sin(yaw), yaw), "slot": info["slot"]})
    env.state = dataclasses.replace(env.state, v=2.0)
    before = _hand_cost(env)
    assert before == pytest.approx(back, abs=1e-9), "3 m straight behind the parked pose, heading already aligned"
    _, reward, terminated, _, info = env.step(np.array([0.0, 0.0], np.float32))
    after = _hand_cost(env)
    assert not terminated and not info["collision"]
    assert before - after == pytest.approx(2.0 * 0.1, abs=1e-9), "moved 0.2 m straight towards the slot centre"
    assert reward == pytest.approx((before - after) - 0.01, abs=1e-9)
    assert reward == pytest.approx(0.19, abs=1e-9) and reward > 0


@pytest.mark.parametrize("speed, parked", [(0.5, False), (0.09, True), (0.0, True)])
def test_parked_needs_the_ego_stopped(bundle_dir, speed, parked):
    """From the slot pose exactly, heading aligned, one step at constant speed (it moves speed * 0.1 s, well inside
    pos_tol = 0.35 m): parked (terminated, success) only below 0.1 m/s."""
    env = ParkingEnv(bundle=bundle_dir, cameras=[])
    _, info = env.reset(seed=0)
    x, y, yaw = env.target_pose()
    env.reset(options={"start": (x, y, yaw), "slot": info["slot"]})
    env.state = dataclasses.replace(env.state, v=speed)
    _, _, terminated, _, info = env.step(np.array([0.0, 0.0], np.float32))
    assert info["speed"] == speed and info["distance"] <= speed * 0.1 + 1e-9 < 0.35 and info["heading_error"] == 0.0
    assert not info["collision"]
    assert (terminated, info["is_success"]) == (parked, parked), info


def _hand_rotation(roll: float, pitch: float, yaw: float) -> np.ndarray:
    """docs/frames.md: R = Rz(yaw) @ Ry(pitch) @ Rx(roll), each an elementary right-handed rotation."""
    cr, sr, cp, sp, cy, sy = (math.cos(roll), math.sin(roll), math.cos(pitch), math.sin(pitch),
                              math.cos(yaw), math.sin(yaw))
    Rx = np.array([[1, 0, 0], [0, cr, -sr], [0, sr, cr]])
    Ry = np.array([[cp, 0, sp], [0, 1, 0], [-sp, 0, cp]])
    Rz = np.array([[cy, -sy, 0], [sy, cy, 0], [0, 0, 1]])
    return Rz @ Ry @ Rx


def test_pose_from_xyz_rpy_is_rz_ry_rx():
    T = pose_from_xyz_rpy(1.0, -2.0, 0.3, 0.2, -0.4, 1.1).numpy()
    np.testing.assert_allclose(T[:3, :3], _hand_rotation(0.2, -0.4, 1.1), rtol=0, atol=1e-15)
    np.testing.assert_array_equal(T[:3, 3], [1.0, -2.0, 0.3])
    np.testing.assert_array_equal(T[3], [0.0, 0.0, 0.0, 1.0])
    swapped = pose_from_xyz_rpy(1.0, -2.0, 0.3, -0.4, 0.2, 1.1).numpy()
    assert np.abs(swapped[:3, :3] - T[:3, :3]).max() > 0.1, "roll and pitch act differently"


def test_tilted_pose_through_get_render_matches_the_hand_built_matrix(bundle_dir):
    """A 6-value pose with roll != pitch through the real app renders the images of ``render`` at the 4x4
    ``pose_from_xyz_rpy`` gives (checked against Rz Ry Rx above), and not those with roll and pitch swapped."""
    pose = (12.0, 0.3, 0.2, 0.12, -0.06, 0.3)
    swapped = (12.0, 0.3, 0.2, -0.06, 0.12, 0.3)
    cameras, scale = ["front", "left"], 0.25
    sim = LocalSim(bundle_dir, "tiny")

    def by_matrix(p: tuple[float, ...]) -> dict[str, np.ndarray]:
        x, y, z, roll, pitch, yaw = p
        T = pose_from_xyz_rpy(x, y, z, roll, pitch, yaw)
        np.testing.assert_allclose(T[:3, :3].numpy(), _hand_rotation(roll, pitch, yaw), rtol=0, atol=1e-15)
        res = render(sim.bundle.scene, sim.bundle.rig, T, cameras=cameras, scale=scale,
                     method=sim.bundle.projection)
        return {n: to_uint8(res.images[n]) for n in cameras}

    expected, other = by_matrix(pose), by_matrix(swapped)
    with TestClient(create_app({"tiny": bundle_dir})) as c:
        r = c.get("/render", params={"pose": ",".join(map(str, pose)), "cameras": ",".join(cameras),
                                     "scale": scale})
    assert r.status_code == 200, r.text
    (frame,), _ = decode_npz(r.content)
    local = sim.render(pose, cameras=cameras, scale=scale)
    for n in cameras:
        np.testing.assert_array_equal(frame.images[n], expected[n], err_msg=f"{n}: server vs hand-built matrix")
        np.testing.assert_array_equal(local.images[n], expected[n], err_msg=f"{n}: LocalSim vs hand-built matrix")
        diff = np.abs(expected[n].astype(np.int16) - other[n].astype(np.int16))
        assert (diff > 8).mean() > 0.01, f"{n}: swapping roll and pitch must change the image"


def test_importers_refuse_a_reflection():
    """diag(1, 1, -1) is orthonormal (R^T R = I) but det = -1: a mirror, not a rotation; |det R - 1| = 2."""
    T = np.diag([1.0, 1.0, -1.0, 1.0])
    with pytest.raises(RecordingError, match=r"^ego pose of frame 0: not a proper rotation \(.* = 2 > 0.001\)$"):
        check_pose(T, "ego pose of frame 0")
    check_pose(pose_from_xyz_rpy(1.0, 2.0, 3.0, 0.1, 0.2, 0.3).numpy(), "a proper rotation passes")


def test_compositing_constants_are_the_documented_3dgs_values():
    """docs/api.md: ``ALPHA_MIN = 1/255`` skipped, ``ALPHA_MAX = 0.99``, stop below ``T_MIN = 1e-4``, 16-pixel tiles."""
    from parksim.render.rasterize import ALPHA_MAX, ALPHA_MIN, T_MIN, TILE

    assert (ALPHA_MAX, ALPHA_MIN, T_MIN, TILE) == (0.99, 1.0 / 255.0, 1e-4, 16)
