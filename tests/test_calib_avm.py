"""SensorsCalibration surround-view (AVM) calibration: the synth rig written in the format, read back into our vehicle
frame, and a BEV stitched through it whose sampling agrees with the format's own projection formula.

The format's formula (``manual_calib/src/run_avm.cpp``: ``project_on_ground``, ``world2cam``) is written out here
in NumPy from the files alone, independently of ``parksim.calib.avm`` and ``OCamFisheye``: BEV pixel (j, i) ->
``P_G = h K_G^-1 (j, i, 1)`` -> ``P_C = T_CG P_G`` -> ``(X, Y) = P_C[:2] / z`` -> ``world2cam(X, Y, -1)``.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch

from parksim.calib.avm import read_avm
from parksim.camera import OCamFisheye
from parksim.importers.recording import CALIBRATION_ROTATIONS, Corrections
from parksim.importers.rig_log_calib import load_calibration
from parksim.ipm import IPM
from parksim.rig import BEVSpec, CalibrationError, Rig
from parksim.synth.rig import avm_rig

BEV_PX = 160
M_PER_PX = 0.0625                                   # 10 m across
DEPTHS = {"front": 6.07826, "left": 6.25217, "rear": 6.31014, "right": 6.28116}   # unequal, as the tool's sample
AFFINE = {"front": (0.999838, 4.9e-4, 2.4e-4), "left": (1.0, 0.0, 0.0), "rear": (1.0002, -3e-4, 1e-4),
          "right": (0.9997, 2e-4, -2e-4)}        # cam_K's c', d', e'
AXIS_RESIDUAL = np.array([0.003] + [0.0] * 9)    # a fitted invpol's residual on the axis (px), as real files have
BEV_SPEC = BEVSpec(BEV_PX, BEV_PX, M_PER_PX, 1.4, 0.0, (-1.05, 3.85, -1.0, 1.0))
R_VG = np.array([[0.0, -1.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])   # BEV camera axes in our vehicle frame


def _invpol(model) -> np.ndarray:
    """The world2cam polynomial of a Kannala-Brandt lens (a polynomial in theta), in ``theta - pi/2``: exact."""
    k = model.k.numpy()
    kb = np.polynomial.Polynomial([0, 1, 0, k[0], 0, k[1], 0, k[2], 0, k[3]]) * float(model.fx)
    return kb(np.polynomial.Polynomial([math.pi / 2, 1])).coef


def write_avm(rig: Rig, folder: Path, decimals: int | None = None) -> None:
    """``rig`` (Kannala-Brandt lenses) as a SensorsCalibration folder: OCam intrinsics, ``T_CG`` extrinsics at the
    ground depths ``DEPTHS`` (each camera's translation scaled to its own depth), ``avm.json`` for ``BEV_SPEC``;
    the matrices printed with ``decimals`` as the tool does, or in full."""
    for sub in ("intrinsic", "extrinsic"):
        (folder / sub).mkdir(parents=True)
    H = sum(DEPTHS.values()) / len(DEPTHS)
    s = BEV_SPEC
    x0 = s.center_x + ((s.height - 1) / 2 - s.height // 2) * s.m_per_px    # ground point under the BEV camera
    y0 = s.center_y + ((s.width - 1) / 2 - s.width // 2) * s.m_per_px
    T_VG = np.eye(4)
    T_VG[:3, :3], T_VG[:3, 3] = R_VG, (x0, y0, H)
    for name, cam in rig.cameras.items():
        m = cam.model
        cp, dp, ep = AFFINE[name]
        K = [[cp, dp, float(m.cx)], [ep, 1.0, float(m.cy)], [0.0, 0.0, 1.0]]
        param = {"img_dist_w": m.width, "img_dist_h": m.height, "cam_K": {"rows": 3, "cols": 3, "data": K},
                 "cam_dist": {"rows": 1, "cols": 10, "data": [(_invpol(m) / cp + AXIS_RESIDUAL).tolist()]}}
        (folder / "intrinsic" / f"{name}.json").write_text(json.dumps({f"{name}_camera-intrinsic": {"param": param}}))
        T_CG = np.linalg.inv(cam.T_vehicle_camera.numpy()) @ T_VG
        T_CG[:3, 3] *= DEPTHS[name] / H
        if decimals is not None:
            T_CG = np.round(T_CG, decimals)
        doc = {f"bev-to-{name}_camera-extrinsic": {"sensor_name": "camera", "param": {"time_lag": 0, "sensor_calib": {
            "rows": 4, "cols": 4, "type": 6, "continuous": True, "data": T_CG.tolist()}}}}
        (folder / "extrinsic" / f"{name}.json").write_text(json.dumps(doc))
    (folder / "avm.json").write_text(json.dumps({
        "bev_camera": {"width": s.width, "height": s.height, "dX": s.m_per_px / H, "dY": s.m_per_px / H},
        "ground_depth": DEPTHS, "bev_center": [x0, y0], "ego_box": list(s.ego_box)}))


def format_projection(folder: Path, name: str) -> tuple[np.ndarray, np.ndarray]:
    """The tool's own BEV -> image map of camera ``name``, from the files: ``(uv [H, W, 2], z_C > 0 [H, W])``."""
    spec = json.loads((folder / "avm.json").read_text())
    bev, h = spec["bev_camera"], spec["ground_depth"][name]
    rows, cols = bev["height"], bev["width"]
    K_G = np.array([[1 / bev["dX"], 0, cols // 2], [0, 1 / bev["dY"], rows // 2], [0, 0, 1.0]])
    T_CG = np.array(next(iter(json.loads((folder / "extrinsic" / f"{name}.json").read_text()).values()))
                    ["param"]["sensor_calib"]["data"])
    param = next(iter(json.loads((folder / "intrinsic" / f"{name}.json").read_text()).values()))["param"]
    K, D = np.array(param["cam_K"]["data"]), np.array(param["cam_dist"]["data"]).ravel()
    i, j = np.mgrid[0:rows, 0:cols].astype(np.float64)
    P_G = h * np.einsum("ab,bhw->ahw", np.linalg.inv(K_G), np.stack([j, i, np.ones_like(i)]))
    P_C = np.einsum("ab,bhw->ahw", T_CG[:3, :3], P_G) + T_CG[:3, 3, None, None]
    X, Y = P_C[0] / P_C[2], P_C[1] / P_C[2]
    norm = np.hypot(X, Y)
    theta = np.arctan(-1.0 / norm)
    rho = sum(c * theta ** n for n, c in enumerate(D))
    x, y = X / norm * rho, Y / norm * rho
    u = x * K[0, 0] + y * K[0, 1] + K[0, 2]
    v = x * K[1, 0] + y + K[1, 2]
    return np.stack([u, v], -1), P_C[2] > 0


def _bilinear(image: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """``image [h, w, C]`` at ``uv [N, 2]`` (column, row, centres at integers), inside the image."""
    u0 = np.clip(np.floor(uv[:, 0]).astype(int), 0, image.shape[1] - 2)
    v0 = np.clip(np.floor(uv[:, 1]).astype(int), 0, image.shape[0] - 2)
    a, b = (uv[:, 0] - u0)[:, None], (uv[:, 1] - v0)[:, None]
    return ((1 - a) * (1 - b) * image[v0, u0] + a * (1 - b) * image[v0, u0 + 1]
            + (1 - a) * b * image[v0 + 1, u0] + a * b * image[v0 + 1, u0 + 1])


@pytest.fixture(scope="module")
def ours() -> Rig:
    """The synth rig at 320x240 with ``BEV_SPEC``, its lenses as the OCam models the written files hold."""
    rig = avm_rig(320, 240)
    return Rig(dict(rig.cameras), BEV_SPEC)


@pytest.fixture(scope="module", params=[None, 6], ids=["full", "6-decimals"])
def written(ours: Rig, tmp_path_factory: pytest.TempPathFactory, request: pytest.FixtureRequest
            ) -> tuple[Path, int | None]:
    folder = tmp_path_factory.mktemp("avm") / "calib"
    write_avm(ours, folder, request.param)
    return folder, request.param


def test_read_back_is_our_rig(ours: Rig, written: tuple[Path, int | None]) -> None:
    folder, decimals = written
    rig = read_avm(folder)
    assert rig.names == list(DEPTHS)
    tol = 1e-12 if decimals is None else 2e-5
    for name, cam in ours.cameras.items():
        got = rig.cameras[name]
        expected = OCamFisheye.from_json(folder / "intrinsic" / f"{name}.json")
        assert isinstance(got.model, OCamFisheye)
        assert torch.equal(got.model.k, expected.k) and float(got.model.cx) == float(expected.cx)
        assert float(got.model.cy) == float(expected.cy) and float(got.model.fy) == float(expected.fy)
        assert torch.allclose(got.T_vehicle_camera, cam.T_vehicle_camera, atol=tol, rtol=0)
        assert (got.rotation_correction == 0.0) == (decimals is None) and got.rotation_correction < 1e-5
    b = rig.bev
    assert (b.width, b.height, b.ego_box) == (BEV_PX, BEV_PX, BEV_SPEC.ego_box)
    assert b.m_per_px == pytest.approx(M_PER_PX, rel=1e-12)
    assert (b.center_x, b.center_y) == pytest.approx((BEV_SPEC.center_x, BEV_SPEC.center_y), abs=1e-12)


def test_stitched_bev_samples_where_the_format_projects(written: tuple[Path, int | None]) -> None:
    """For every ground pixel a camera contributes to, our IPM samples the pixel the format's formula gives
    (< 0.05 px), and the stitched BEV is the weighted blend of the images there."""
    folder, _ = written
    rig = read_avm(folder)
    ipm = IPM(rig, dtype=torch.float64)
    images, formula = {}, {}
    for name, cam in rig.cameras.items():
        v, u = np.mgrid[0:cam.model.height, 0:cam.model.width]
        images[name] = np.stack([np.sin(u / 13.0 + v / 29.0), np.cos(v / 17.0), np.sin((u - v) / 23.0)], -1)
        uv, ahead = format_projection(folder, name)
        seen = ipm.weights[name].numpy() > 0
        assert seen.sum() > 1000 and (ahead[seen]).mean() > 0.75   # the format maps only ground ahead (z_C > 0)
        check = seen & ahead
        err = np.abs(ipm.pixel_coords[name].numpy()[check] - uv[check]).max()
        assert err < 0.05, f"{name}: IPM samples {err:.3g} px from the format's projection"
        formula[name] = (uv, ahead)
    bev = ipm({n: torch.from_numpy(im) for n, im in images.items()}).numpy()
    expected = np.zeros_like(bev)
    usable = ipm.mask.numpy().copy()
    for name, (uv, ahead) in formula.items():
        w = ipm.weights[name].numpy()
        h, wd = images[name].shape[:2]
        inside = ahead & (uv[..., 0] >= 0) & (uv[..., 0] <= wd - 1) & (uv[..., 1] >= 0) & (uv[..., 1] <= h - 1)
        usable &= (w == 0) | inside
        expected += w[..., None] * _bilinear(images[name], np.nan_to_num(uv).reshape(-1, 2)).reshape(bev.shape)
    assert usable.sum() > 0.5 * ipm.mask.sum()
    assert np.abs(bev[usable] - expected[usable]).max() < 0.01    # 0.05 px x the images' gradient (< 0.11 / px)


def test_rig_log_calibration_reads_the_folder(written: tuple[Path, int | None]) -> None:
    folder, decimals = written
    corrected = Corrections()
    rig, notes = load_calibration(folder, corrected=corrected)
    assert notes["calibration_format"] == "avm" and rig.names == list(DEPTHS)
    entry = corrected.kinds.get(CALIBRATION_ROTATIONS)
    if decimals is None:
        assert entry is None
    else:
        assert entry["count"] == 4 and 0 < entry["largest"] < 1e-5 and ": T_CG" in entry["where"]


def _edit(folder: Path, rel: str, change) -> None:
    path = folder / rel
    path.write_text(json.dumps(change(json.loads(path.read_text()))))


def _scale_rotation(doc: dict) -> dict:
    data = next(iter(doc.values()))["param"]["sensor_calib"]["data"]
    for row in data[:3]:
        row[:3] = [1.01 * v for v in row[:3]]
    return doc


def _set(key: str, value):
    def change(doc: dict) -> dict:
        doc[key] = value
        return doc
    return change


MALFORMED = {
    "no avm.json": (lambda f: (f / "avm.json").unlink(), "avm.json"),
    "non-square BEV": (lambda f: _edit(f, "avm.json", lambda d: {**d, "bev_camera": {**d["bev_camera"], "dY": 0.02}}),
                       "square pixels"),
    "depth missing a camera": (lambda f: _edit(f, "avm.json", _set("ground_depth", {"front": 6.0})), "ground_depth"),
    "negative depth": (lambda f: _edit(f, "avm.json", _set("ground_depth", -1.0)), "positive"),
    "unknown key": (lambda f: _edit(f, "avm.json", _set("K_G", 1)), "unknown keys"),
    "3x3 extrinsic": (lambda f: _edit(f, "extrinsic/left.json", lambda d: {"x": {"param": {"sensor_calib": {
        "data": [[1, 0, 0], [0, 1, 0], [0, 0, 1]]}}}}), "left.json"),
    "scaled rotation": (lambda f: _edit(f, "extrinsic/rear.json", _scale_rotation), "rotation"),
    "not JSON": (lambda f: (f / "extrinsic" / "right.json").write_text("R: [1, 0]"), "right.json"),
    "no intrinsics": (lambda f: (f / "intrinsic" / "front.json").unlink(), "has no"),
    "bad intrinsics": (lambda f: (f / "intrinsic" / "front.json").write_text('{"a": {"param": {}}}'), "front.json"),
}


@pytest.mark.parametrize("case", list(MALFORMED))
def test_malformed_files_are_one_line_errors(ours: Rig, tmp_path: Path, case: str) -> None:
    folder = tmp_path / "calib"
    write_avm(ours, folder)
    spoil, says = MALFORMED[case]
    spoil(folder)
    with pytest.raises(CalibrationError) as e:
        read_avm(folder)
    message = str(e.value)
    assert "\n" not in message and says in message and str(folder) in message


def test_conversion_puts_a_camera_where_the_format_says(tmp_path: Path) -> None:
    """One hand-made camera: T_CG = identity at ground depth 2 is a camera 2 m up, looking straight down, image
    top towards the vehicle's front and image right towards its right, over the BEV's centre pixel."""
    model = avm_rig(320, 240).cameras["front"].model
    folder = tmp_path / "one"
    for sub in ("intrinsic", "extrinsic"):
        (folder / sub).mkdir(parents=True)
    param = {"img_dist_w": 320, "img_dist_h": 240, "cam_K": {"data": [[1, 0, 160], [0, 1, 120], [0, 0, 1]]},
             "cam_dist": {"data": _invpol(model).tolist()}}
    (folder / "intrinsic" / "down.json").write_text(json.dumps({"down": {"param": param}}))
    (folder / "extrinsic" / "down.json").write_text(json.dumps(
        {"bev-to-down-extrinsic": {"param": {"sensor_calib": {"data": np.eye(4).tolist()}}}}))
    (folder / "avm.json").write_text(json.dumps({"bev_camera": {"width": 101, "height": 101, "dX": 0.01, "dY": 0.01},
                                                 "ground_depth": 2.0, "bev_center": [1.5, 0.0]}))
    got = read_avm(folder)
    T = got.cameras["down"].T_vehicle_camera
    assert torch.allclose(T[:3, 3], torch.tensor([1.5, 0.0, 2.0], dtype=torch.float64))
    # camera x (image right) -> vehicle -y, camera y (image down) -> vehicle -x, optical axis -> vehicle -z
    assert torch.equal(T[:3, :3], torch.tensor(R_VG))
    assert got.bev.m_per_px == pytest.approx(0.02) and (got.bev.center_x, got.bev.center_y) == (1.5, 0.0)
