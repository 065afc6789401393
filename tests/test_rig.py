"""Rig files, the OpenCV-YAML and WoodScape importers, poses, and their errors."""

import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch
from kornia.geometry.conversions import quaternion_to_rotation_matrix

from parksim.assets import SAMPLE_DIR as SAMPLE
from parksim.camera import OpenCVFisheye, RadialPolyFisheye
from parksim.geometry import (
    as_pose,
    compose,
    invert_transform,
    pose_from_xy_yaw,
    quaternion_from_rotation,
    rotation_from_quaternion,
    transform_points,
    xy_yaw_from_pose,
)
from parksim.rig import BEVSpec, CalibrationError, Rig, RigCamera

# WoodScape's published front-camera calibration (scripts/calibration/front.json), written from the documented format.
WOODSCAPE_FV = {
    "extrinsic": {"quaternion": [0.5941767906169857, -0.5878843193897473, 0.3873184109007999, -0.3890121040340926],
                  "translation": [3.7484, 0.0, 0.6601699999999999]},
    "intrinsic": {"aspect_ratio": 1.0, "cx_offset": 3.942, "cy_offset": -3.093, "height": 966.0, "k1": 339.749,
                  "k2": -31.988, "k3": 48.275, "k4": -7.201, "model": "radial_poly", "poly_order": 4, "width": 1280.0},
    "name": "FV",
}


def test_pose_helpers_round_trip():
    T = pose_from_xy_yaw(3.0, -2.0, 2.5)
    x, y, yaw = xy_yaw_from_pose(T)
    assert (float(x), float(y), float(yaw)) == pytest.approx((3.0, -2.0, 2.5))
    assert torch.allclose(compose(T, invert_transform(T)), torch.eye(4, dtype=torch.float64), atol=1e-12)
    p = torch.tensor([[1.0, 0.0, 0.0]], dtype=torch.float64)
    assert torch.allclose(transform_points(T, p), torch.tensor([[3 + math.cos(2.5), -2 + math.sin(2.5), 0.0]],
                                                               dtype=torch.float64))
    assert torch.equal(as_pose((3.0, -2.0, 2.5)), T)
    assert torch.allclose(as_pose((3.0, -2.0, 0.0, 0.0, 0.0, 2.5)), T)
    with pytest.raises(ValueError, match="non-finite"):
        as_pose((float("nan"), 0.0, 0.0))
    with pytest.raises(ValueError, match="x, y, yaw"):
        as_pose((1.0, 2.0))


def test_quaternions_match_kornia_and_round_trip():
    q = torch.randn(200, 4, dtype=torch.float64)
    q = q / q.norm(dim=-1, keepdim=True)
    R = rotation_from_quaternion(q)
    assert torch.allclose(R, quaternion_to_rotation_matrix(q), atol=1e-12)  # kornia: (w, x, y, z)
    q2 = quaternion_from_rotation(R)
    assert torch.allclose(q2, q * torch.sign(q[:, :1]), atol=1e-12)
    assert torch.equal(rotation_from_quaternion(torch.zeros(4, dtype=torch.float64)), torch.eye(3, dtype=torch.float64))


def small_rig() -> Rig:
    cams = {}
    for i, name in enumerate(["front", "rear"]):
        model = OpenCVFisheye(64, 48, 20.0, 21.0, 31.5, 23.5, [0.01, -0.002, 0.0, 0.0])
        T = pose_from_xy_yaw(2.0 - 3 * i, 0.1, math.pi * i)
        cams[name] = RigCamera(name, model, T)
    cams["woodscape"] = RigCamera("woodscape", RadialPolyFisheye(80, 60, [30.0, -1.0, 2.0, -0.3], 0.5, -0.2, 1.01),
                                  torch.eye(4, dtype=torch.float64))
    return Rig(cams, BEVSpec(300, 200, 0.05, 1.2, 0.0, (-1.0, 3.0, -0.9, 0.9)))


@pytest.mark.parametrize("suffix", [".json", ".yaml"])
def test_rig_save_load_round_trip(tmp_path, suffix):
    rig = small_rig()
    rig.save(tmp_path / f"rig{suffix}")
    again = Rig.load(tmp_path / f"rig{suffix}")
    assert again.to_dict() == rig.to_dict()
    assert again.names == ["front", "rear", "woodscape"]


def test_bev_spec_pixel_mapping_matches_K_ipm():
    spec = BEVSpec(300, 200, 0.05, 1.2, -0.4)
    xy = torch.tensor([[1.2, -0.4], [3.0, 1.0], [-2.0, 0.5]], dtype=torch.float64)
    uv = spec.ground_to_pixel(xy)
    assert torch.allclose(uv[0], torch.tensor([149.5, 99.5], dtype=torch.float64))
    assert uv[1, 1] < uv[0, 1] and uv[1, 0] < uv[0, 0]  # forward is up, left is left
    hom = torch.cat([xy, torch.ones(3, 1, dtype=torch.float64)], -1) @ spec.K_ipm.T
    assert torch.allclose(hom[:, :2], uv)
    assert torch.allclose(spec.pixel_to_ground(uv), xy)


def test_from_woodscape_matches_documented_projection(tmp_path):
    path = tmp_path / "FV.json"
    path.write_text(json.dumps(WOODSCAPE_FV))
    rig = Rig.from_woodscape([path])
    cam = rig.cameras["FV"]
    # WoodScape: (quaternion (x, y, z, w), translation) maps camera -> vehicle (ISO 8855, rear axle).
    qx, qy, qz, qw = WOODSCAPE_FV["extrinsic"]["quaternion"]
    R = quaternion_to_rotation_matrix(torch.tensor([qw, qx, qy, qz], dtype=torch.float64))
    t = torch.tensor(WOODSCAPE_FV["extrinsic"]["translation"], dtype=torch.float64)
    pts_vehicle = torch.tensor([[8.0, 1.0, 0.0], [5.0, -3.0, 0.5], [4.0, 0.0, 0.0]], dtype=torch.float64)
    p_cam = (pts_vehicle - t) @ R  # R^T (p - t)
    x, y, z = p_cam.numpy().T
    chi = np.hypot(x, y)
    theta = np.pi / 2 - np.arctan2(z, chi)
    k = [339.749, -31.988, 48.275, -7.201]
    rho = sum(c * theta ** (i + 1) for i, c in enumerate(k))
    expected = np.stack([rho * x / chi + 3.942 + 640 - 0.5, rho * y / chi - 3.093 + 483 - 0.5], -1)
    uv, valid = cam.model.project(transform_points(invert_transform(cam.T_vehicle_camera), pts_vehicle))
    assert np.abs(uv.numpy() - expected).max() < 1e-9
    assert valid.all()
    # The front camera looks forward: its optical axis has a positive vehicle-x component.
    assert cam.T_vehicle_camera[0, 2] > 0.5


def test_from_opencv_yaml_reads_the_sample():
    paths = {name: SAMPLE / "yaml" / f"{stem}.yaml" for name, stem in
             [("front", "front"), ("rear", "back"), ("left", "left"), ("right", "right")]}
    rig = Rig.from_opencv_yaml(paths, {n: torch.eye(4, dtype=torch.float64) for n in paths})
    m = rig.cameras["front"].model
    assert (m.width, m.height) == (960, 640)
    assert float(m.fx) == pytest.approx(302.45305983229298)
    assert float(m.k[3]) == pytest.approx(8.4123126605702321e-03)


def test_bad_calibration_files_give_clear_errors(tmp_path):
    garbage = tmp_path / "garbage.yaml"
    garbage.write_text("%YAML:1.0\n---\ncamera_matrix: [1, 2\n")
    with pytest.raises(CalibrationError, match="garbage.yaml"):
        Rig.from_opencv_yaml({"front": garbage}, {"front": torch.eye(4, dtype=torch.float64)})
    missing_d = tmp_path / "nodist.yaml"
    missing_d.write_text("%YAML:1.0\n---\ncamera_matrix: !!opencv-matrix\n   rows: 3\n   cols: 3\n   dt: d\n"
                         "   data: [300., 0., 480., 0., 300., 320., 0., 0., 1.]\nresolution: !!opencv-matrix\n"
                         "   rows: 2\n   cols: 1\n   dt: i\n   data: [960, 640]\n")
    with pytest.raises(CalibrationError, match="missing 'dist_coeffs'"):
        Rig.from_opencv_yaml({"front": missing_d}, {"front": torch.eye(4, dtype=torch.float64)})
    with pytest.raises(CalibrationError, match="not found"):
        Rig.from_opencv_yaml({"front": tmp_path / "nope.yaml"}, {"front": torch.eye(4, dtype=torch.float64)})

    def woodscape(mutate) -> Path:
        d = json.loads(json.dumps(WOODSCAPE_FV))
        mutate(d)
        p = tmp_path / "ws.json"
        p.write_text(json.dumps(d))
        return p

    with pytest.raises(CalibrationError, match="unknown camera model 'mei'"):
        Rig.from_woodscape([woodscape(lambda d: d["intrinsic"].update(model="mei"))])
    with pytest.raises(CalibrationError, match="missing key 'k3'"):
        Rig.from_woodscape([woodscape(lambda d: d["intrinsic"].pop("k3"))])
    with pytest.raises(CalibrationError, match="quaternion"):
        Rig.from_woodscape([woodscape(lambda d: d["extrinsic"].update(quaternion=[0, 0, 0, 0]))])
    bad_json = tmp_path / "bad.json"
    bad_json.write_text("{not json")
    with pytest.raises(CalibrationError, match="not valid JSON"):
        Rig.from_woodscape([bad_json])

    rig_file = tmp_path / "rig.json"
    d = small_rig().to_dict()
    d["cameras"]["front"]["intrinsics"]["model"] = "fisheye624"
    rig_file.write_text(json.dumps(d))
    with pytest.raises(CalibrationError, match="camera 'front': unknown camera model 'fisheye624'"):
        Rig.load(rig_file)
    d = small_rig().to_dict()
    d["cameras"]["rear"]["T_vehicle_camera"][0][0] = 2.0
    rig_file.write_text(json.dumps(d))
    with pytest.raises(CalibrationError, match="not a proper rotation"):
        Rig.load(rig_file)
    rig_file.write_text("cameras: [")
    with pytest.raises(CalibrationError, match="cannot parse"):
        Rig.load(rig_file.rename(tmp_path / "rig.yaml"))
