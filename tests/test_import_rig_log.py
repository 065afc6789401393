"""rig-log import: a ``parksim synth tiny`` dataset written as a rig log (OpenCV YAML, WoodScape and OCamCalib
calibrations, CSV/JSON poses, image folders and mp4v videos) and imported back by the real CLI; unsynchronised
cameras against the synth trajectory; dropped frames; bad input.

The OpenCV-YAML, pose and image writers are the import benchmark suite's (``parksim.bench.rig_logs``); the
WoodScape and OCam writers are here.
"""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from parksim.bench.rig_logs import extrinsics_file, image_folders, poses_csv, stamp_name, videos, write_rig_log
from parksim.cli import main
from parksim.data import DatasetReader
from parksim.geometry import quaternion_from_rotation
from parksim.importers.recording import REPORT_FILE
from parksim.importers.rig_log import PoseLog

DECODED_FOURCC = "FMP4"
"""What cv2.VideoCapture reports (CAP_PROP_FOURCC) for an mp4v stream: FFmpeg's tag for MPEG-4 Part 2."""
VIDEO_PSNR_DB = 30.0
"""Least mean PSNR of the decoded mp4v frames against the dataset's PNGs (measured 34.8 dB on tiny's front camera)."""
TOL = 1e-9
"""Poses and intrinsics written with repr / 17 significant digits read back to the bit; 1e-9 leaves room for the
quaternion -> matrix round trip (~1e-16) and nothing for a convention error."""
OCAM_FIT_PX = 1e-3
"""Largest pixel distance between the synth OpenCVFisheye and its OCamCalib fit (ss of degree 8 in rho, least
squares over the lens' 95 deg) over a 6 px grid: measured 9.1e-5 px."""
OCAM_JSON_PX = 1e-6
"""The same for the OCam JSON form, whose invpol is the synth lens' own polynomial (exact up to rounding)."""
WOODSCAPE_FIT_PX = 0.02
"""The same for WoodScape's radial_poly (degree 4 in theta) least-squares fitted to the synth lens (theta up to
degree 9): measured 0.0073 px."""
UNSYNC_M, UNSYNC_RAD = 0.005, math.radians(0.1)
"""Interpolated camera poses against the synth trajectory (10 Hz log, 2 m/s): measured at most 1.8 mm and
0.05 deg (left camera, 25 ms past a logged pose). Not derived from a smoothness bound: the synth path's yaw is
a finite difference along a 5 cm polyline, so its second differences at 80 Hz (up to 15 m/s^2 at the front
camera) bound nothing useful."""
THETA_MAX = math.radians(95.0)


# --- writers: a dataset as a rig log ---------------------------------------------------------------------------------
def _quaternion(R: torch.Tensor) -> list[float]:
    return [float(v) for v in quaternion_from_rotation(R)]


def _kb_rho(model, theta: np.ndarray) -> np.ndarray:
    """Sensor radius (px, fx = fy) of the OpenCVFisheye at ``theta``."""
    k = model.k.numpy()
    t2 = theta * theta
    return float(model.fx) * theta * (1 + t2 * (k[0] + t2 * (k[1] + t2 * (k[2] + t2 * k[3]))))


def woodscape_json(name: str, cam, path: Path) -> None:
    """A WoodScape calibration: radial_poly k1..k4 least-squares fitted to the lens up to ``THETA_MAX``,
    the principal point as offsets from the image centre, extrinsics as quaternion (x, y, z, w) + translation."""
    m = cam.model
    theta = np.linspace(0.0, THETA_MAX, 400)
    k = np.linalg.lstsq(np.stack([theta ** i for i in range(1, 5)], 1), _kb_rho(m, theta), rcond=None)[0]
    qw, qx, qy, qz = _quaternion(cam.T_vehicle_camera[:3, :3])
    path.write_text(json.dumps({
        "name": name,
        "intrinsic": {"model": "radial_poly", "width": m.width, "height": m.height, "k1": k[0], "k2": k[1],
                      "k3": k[2], "k4": k[3], "cx_offset": float(m.cx) - (m.width / 2 - 0.5),
                      "cy_offset": float(m.cy) - (m.height / 2 - 0.5), "aspect_ratio": float(m.fy / m.fx)},
        "extrinsic": {"quaternion": [qx, qy, qz, qw], "translation": cam.T_vehicle_camera[:3, 3].tolist()}}))


def _invpol(model) -> np.ndarray:
    """OCamCalib's world2cam polynomial for the lens: its own polynomial in theta, moved to ``theta - pi/2``
    (exact: Kannala-Brandt is a polynomial in theta)."""
    k = model.k.numpy()
    kb = np.polynomial.Polynomial([0, 1, 0, k[0], 0, k[1], 0, k[2], 0, k[3]]) * float(model.fx)
    return kb(np.polynomial.Polynomial([math.pi / 2, 1])).coef


def ocam_json(name: str, model, path: Path) -> None:
    """The surround-view OCam JSON for the lens: cam_K = [[1, 0, cx], [0, 1, cy], [0, 0, 1]], cam_dist = invpol."""
    K = [[1.0, 0.0, float(model.cx)], [0.0, 1.0, float(model.cy)], [0.0, 0.0, 1.0]]
    param = {"img_dist_w": model.width, "img_dist_h": model.height, "cam_K": {"data": K},
             "cam_dist": {"data": _invpol(model).tolist()}}
    path.write_text(json.dumps({name: {"param": param}}))


def ocam_txt(model, path: Path) -> None:
    """OCamCalib's calib_results.txt for the lens: ss (cam2world, degree 8 in rho) least-squares fitted to
    ``-rho / tan(theta)``, and ``_invpol``."""
    theta = np.linspace(1e-4, THETA_MAX, 600)
    rho = _kb_rho(model, theta)
    scale = rho.max()
    ss = np.polynomial.polynomial.polyfit(rho / scale, -rho / np.tan(theta), 8) / scale ** np.arange(9)
    invpol = _invpol(model)
    fmt = lambda c: " ".join(repr(float(v)) for v in c)  # noqa: E731
    path.write_text(
        "#polynomial coefficients for the DIRECT mapping function (ocam_model.ss in MATLAB)\n\n"
        f"{len(ss)} {fmt(ss)}\n\n#polynomial coefficients for the inverse mapping function (ocam_model.invpol)\n\n"
        f"{len(invpol)} {fmt(invpol)}\n\n#center: \"row\" and \"column\", starting from 0 (C convention)\n\n"
        f"{float(model.cy)!r} {float(model.cx)!r}\n\n#affine parameters \"c\", \"d\", \"e\"\n\n"
        f"{float(model.fy / model.fx)!r} 0 0\n\n#image size: \"height\" and \"width\"\n\n"
        f"{model.height} {model.width}\n")


# --- fixtures --------------------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def tiny(tiny_data: Path) -> Path:
    """The session's ``parksim synth tiny`` (tests/conftest.py): read only."""
    return tiny_data


@pytest.fixture(scope="module")
def log(tiny: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """tiny as a rig log: OpenCV YAML, WoodScape and OCam calibrations, poses.csv, PNG folders and mp4v videos."""
    root = tmp_path_factory.mktemp("riglog") / "log"
    write_rig_log(tiny, root, video=False)
    videos(tiny, root / "video", 10.0)
    rig = DatasetReader(tiny).rig
    for kind in ("woodscape", "ocam", "ocam_json"):
        (root / kind).mkdir()
    for c, cam in rig.cameras.items():
        woodscape_json(c, cam, root / "woodscape" / f"{c}.json")
        ocam_txt(cam.model, root / "ocam" / f"{c}.txt")
        ocam_json(c, cam.model, root / "ocam_json" / f"{c}.json")
    extrinsics_file(rig, root / "ocam" / "extrinsics.json")
    extrinsics_file(rig, root / "ocam_json" / "extrinsics.yaml")
    return root


def run(args: list[str], out: Path) -> dict:
    assert main([*args, "-o", str(out), "--quiet"]) == 0
    return json.loads((out / REPORT_FILE).read_text())


def base(log: Path, calib: str = "calib") -> list[str]:
    return ["import", "rig-log", "--calib", str(log / calib), "--poses", str(log / "poses.csv")]


def _png(path: Path) -> np.ndarray:
    return cv2.imread(str(path), cv2.IMREAD_UNCHANGED)


def _rays(model, step: float = 6.0) -> torch.Tensor:
    """Unit rays of a pixel grid of ``model`` (float64), those it calls valid."""
    uv = torch.stack(torch.meshgrid(torch.arange(0, model.width, step, dtype=torch.float64),
                                    torch.arange(0, model.height, step, dtype=torch.float64), indexing="xy"), -1)
    uv = uv.reshape(-1, 2)
    return model.unproject(uv[model.pixel_valid(uv)])


def _pixel_error(a, b) -> float:
    """Largest distance (px) between where models ``a`` and ``b`` put ``a``'s pixel-grid rays both see."""
    rays = _rays(a)
    ua, va = a.project(rays)
    ub, vb = b.project(rays)
    both = va & vb
    assert both.float().mean() > 0.9
    return float((ua - ub)[both].norm(dim=-1).max())


# --- tests -----------------------------------------------------------------------------------------------------------
def test_opencv_yaml_and_image_folders_import_to_the_same_dataset(tiny: Path, log: Path) -> None:
    report = run([*base(log), "--images", str(log / "images")], log.parent / "from_images")
    a, b = DatasetReader(tiny), DatasetReader(log.parent / "from_images")
    assert b.rig.names == a.rig.names and b.frames == a.frames and b.split == a.split
    assert np.abs(np.subtract(b.timestamps, a.timestamps)).max() < TOL
    assert b.has_vehicle_poses and not b.has_camera_poses and (b.poses - a.poses).abs().max() < TOL
    assert b.rig.bev == a.rig.bev
    for c in a.rig.names:
        assert b.rig.cameras[c].model.to_dict() == a.rig.cameras[c].model.to_dict()
        assert (b.rig.cameras[c].T_vehicle_camera - a.rig.cameras[c].T_vehicle_camera).abs().max() < TOL
        for f in a.frames:
            assert np.array_equal(_png(b.layout.image(c, f)), _png(a.layout.image(c, f)))
    assert report["dropped"] == 0 and report["synchronised"] is True and report["poses"] == "ego"
    assert report["calibration_format"] == "opencv-yaml" and report["time_unit"] == "ns"
    assert report["pose_log"].startswith("6-DoF")


def test_mp4_videos_import_with_their_frame_times_and_sample_at_fps(tiny: Path, log: Path) -> None:
    cams = DatasetReader(tiny).rig.names
    video_args = ["--video", *(f"{c}={log / 'video' / c}.mp4" for c in cams)]
    report = run([*base(log), *video_args], log.parent / "from_video")
    a, b = DatasetReader(tiny), DatasetReader(log.parent / "from_video")
    assert b.frames == a.frames and (b.poses - a.poses).abs().max() < TOL
    assert np.abs(np.subtract(b.timestamps, a.timestamps)).max() < TOL   # frame i at i / 10 fps
    assert report["sources"]["front"]["fourcc"] == DECODED_FOURCC and report["sources"]["front"]["frame_rate"] == 10.0
    for c in cams:
        mse = [np.mean((_png(b.layout.image(c, f)).astype(float) - _png(a.layout.image(c, f))) ** 2) for f in a.frames]
        assert np.mean([10 * math.log10(255 ** 2 / e) for e in mse]) > VIDEO_PSNR_DB
    half = run([*base(log), *video_args, "--fps", "5", "--video-start", "front=0", "rear=0"],
               log.parent / "from_video_5hz")
    assert DatasetReader(log.parent / "from_video_5hz").frames == [0, 1, 2, 3, 4, 5]
    assert DatasetReader(log.parent / "from_video_5hz").timestamps == pytest.approx([0.0, 0.2, 0.4, 0.6, 0.8, 1.0],
                                                                                 abs=TOL)
    assert half["sources"]["rear"]["sampled"] == 6 and half["sources"]["rear"]["frames"] == 12


@pytest.mark.parametrize("calib, fmt, bound", [("woodscape", "woodscape", WOODSCAPE_FIT_PX),
                                               ("ocam", "ocam-txt", OCAM_FIT_PX),
                                               ("ocam_json", "ocam-json", OCAM_JSON_PX)])
def test_woodscape_and_ocam_calibrations_reproduce_the_lens(tiny: Path, log: Path, calib: str, fmt: str,
                                                            bound: float) -> None:
    out = log.parent / f"from_{calib}"
    report = run([*base(log, calib), "--images", str(log / "images")], out)
    a, b = DatasetReader(tiny), DatasetReader(out)
    assert report["calibration_format"] == fmt
    assert sorted(b.rig.names) == sorted(a.rig.names) and (b.poses - a.poses).abs().max() < TOL
    for c in a.rig.names:
        assert b.rig.cameras[c].model.model == ("radial_poly" if calib == "woodscape" else "ocam")
        assert _pixel_error(a.rig.cameras[c].model, b.rig.cameras[c].model) < bound
        assert (b.rig.cameras[c].T_vehicle_camera - a.rig.cameras[c].T_vehicle_camera).abs().max() < TOL


def test_2d_odometry_in_json_gives_the_planar_poses(tiny: Path, log: Path, tmp_path: Path) -> None:
    a = DatasetReader(tiny)
    P = a.poses.numpy()
    rows = [{"t": t, "x": T[0, 3], "y": T[1, 3], "yaw_deg": math.degrees(math.atan2(T[1, 0], T[0, 0]))}
            for t, T in zip(a.timestamps, P)]
    (tmp_path / "odometry.json").write_text(json.dumps({"poses": rows}))
    args = ["import", "rig-log", "--calib", str(log / "calib"), "--poses", str(tmp_path / "odometry.json"),
            "--images", str(log / "images")]
    report = run(args, tmp_path / "ds")
    assert report["pose_log"] == "2D odometry (x, y, yaw_deg; z = 0)"
    assert (DatasetReader(tmp_path / "ds").poses - a.poses).abs().max() < TOL


def test_frames_outside_the_log_in_a_gap_or_missing_a_camera_are_dropped_and_counted(tiny: Path, log: Path,
                                                                                   tmp_path: Path) -> None:
    a = DatasetReader(tiny)
    keep = [i for i in range(12) if i >= 2 and i not in (6, 7, 8)]   # log starts at 0.2 s, 0.5 -> 0.9 s gap
    poses_csv(tmp_path / "poses.csv", np.array(a.timestamps)[keep], a.poses.numpy()[keep])
    images = tmp_path / "images"
    image_folders(tiny, images)
    (images / "rear" / stamp_name(a.timestamps[3])).unlink()
    args = ["import", "rig-log", "--calib", str(log / "calib"), "--poses", str(tmp_path / "poses.csv"),
            "--images", str(images), "--max-gap", "0.25"]
    report = run(args, tmp_path / "ds")
    assert report["dropped_by_reason"] == {
        "no image from camera(s) rear within --sync-tolerance": 1,
        "frame time outside the pose log": 2,
        "frame time in a pose-log gap longer than --max-gap 0.25 s": 3}   # 0.6, 0.7, 0.8 s
    b = DatasetReader(tmp_path / "ds")
    assert b.frames == [2, 4, 5, 9, 10, 11] and report["frames"] == 6
    assert (b.poses - a.poses[b.frames]).abs().max() < TOL


def test_unsynchronised_cameras_get_per_image_poses_at_their_own_times(tiny: Path, log: Path, tmp_path: Path) -> None:
    """left 25 ms and rear 12.5 ms late: each image's pose is interpolated between the 10 Hz log's poses (linear,
    slerp) and compared with the synth trajectory at that time (an 80 Hz drive along the same path), within
    ``UNSYNC_M`` and ``UNSYNC_RAD``; the nearest logged pose would be off by v * 25 ms = 5 cm."""
    from parksim.synth.layout import build_garage
    from parksim.synth.presets import get_preset
    from parksim.synth.trajectory import drive

    preset = get_preset("tiny")
    h = 1 / 80
    truth, _ = drive(build_garage(preset.layout), dataclasses.replace(preset.trajectory, rate=80.0), 89)
    a = DatasetReader(tiny)
    assert np.abs(truth[::8] - a.poses.numpy()).max() == 0          # the same path at 8x the rate
    offsets = {"left": 0.025, "rear": 0.0125}
    image_folders(tiny, tmp_path / "images", offsets)
    report = run(["import", "rig-log", "--calib", str(log / "calib"), "--poses", str(log / "poses.csv"),
                  "--images", str(tmp_path / "images"), "--sync-tolerance", "0.03"], tmp_path / "ds")
    b = DatasetReader(tmp_path / "ds")
    assert report["synchronised"] is False and report["poses"] == "ego and per-image"
    assert b.frames == list(range(11))      # frame 11 (mean time 1.109 s) is past the log
    assert report["dropped_by_reason"] == {"frame time outside the pose log": 1}
    assert b.timestamps == pytest.approx([a.timestamps[f] + 0.0375 / 4 for f in b.frames], abs=TOL)  # the mean
    for c in a.rig.names:
        T_vc = a.rig.cameras[c].T_vehicle_camera.numpy()
        for f in b.frames:
            i = round((a.timestamps[f] + offsets.get(c, 0.0)) / h)
            true, nearest = truth[i] @ T_vc, truth[8 * f] @ T_vc
            got = b.camera_pose(c, f).numpy()
            assert np.abs(got[:3, 3] - true[:3, 3]).max() < UNSYNC_M
            assert _angle(got, true) < UNSYNC_RAD
            if c in offsets:    # the tolerance tells interpolation from taking the logged pose at the frame
                assert np.abs(nearest[:3, 3] - true[:3, 3]).max() > 4 * UNSYNC_M


def _angle(A: np.ndarray, B: np.ndarray) -> float:
    """Rotation angle (rad) between the rotations of two poses."""
    return math.acos(min(1.0, (np.trace(A[:3, :3].T @ B[:3, :3]) - 1) / 2))


def test_pose_log_slerps_yaw_on_the_short_arc_and_flips_no_sign(tmp_path: Path) -> None:
    """Yaw 0 -> 170 deg -> -170 deg (20 deg across +-180) with the quaternion's sign flipped on the last row:
    slerp at weight w turns by w times the step, the short way."""
    from parksim.importers.rig_log import read_poses

    half = np.radians([0.0, 170.0, 190.0]) / 2
    q = np.stack([np.cos(half), 0 * half, 0 * half, np.sin(half)], 1) * [[1], [1], [-1]]
    rows = [f"{t},{t},0,0,{','.join(map(repr, r))}" for t, r in zip([0.0, 1.0, 2.0], q.tolist())]
    (tmp_path / "p.csv").write_text("t,x,y,z,qw,qx,qy,qz\n" + "\n".join(rows) + "\n")
    log: PoseLog = read_poses(tmp_path / "p.csv")
    t = np.array([0.25, 0.5, 1.25, 1.75])
    T, why = log.at(t, max_gap=1.0)
    assert why == [None] * 4
    yaw = np.degrees(np.arctan2(T[:, 1, 0], T[:, 0, 0]))
    assert np.abs(yaw - [42.5, 85.0, 175.0, -175.0]).max() < 1e-9
    assert np.abs(T[:, 0, 3] - t).max() < 1e-12
    assert log.at(np.array([2.5, -0.1]), 1.0)[1] == ["outside the pose log"] * 2
    assert log.at(np.array([0.5]), 0.9)[1] == ["in a pose-log gap longer than --max-gap 0.9 s"]


def _spoilt_poses(tiny: Path, tmp: Path, spoil: dict[int, dict[str, float]]) -> Path:
    a = DatasetReader(tiny)
    poses_csv(tmp / "poses.csv", np.array(a.timestamps), a.poses.numpy(), spoil)
    return tmp / "poses.csv"


def _non_unit_quaternion(tiny: Path, log: Path, tmp: Path) -> list[str]:
    return ["--calib", str(log / "calib"), "--poses", str(_spoilt_poses(tiny, tmp, {4: {"qw": 1.2}})),
            "--images", str(log / "images")]


def _decreasing_time(tiny: Path, log: Path, tmp: Path) -> list[str]:
    return ["--calib", str(log / "calib"), "--poses", str(_spoilt_poses(tiny, tmp, {5: {"timestamp": 0.35}})),
            "--images", str(log / "images")]


def _unreadable_video(tiny: Path, log: Path, tmp: Path) -> list[str]:
    (tmp / "rear.mp4").write_bytes(np.random.default_rng(0).integers(0, 256, 4096, dtype=np.uint8).tobytes())
    video = {c: log / "video" / f"{c}.mp4" for c in ("front", "left", "right")} | {"rear": tmp / "rear.mp4"}
    return ["--calib", str(log / "calib"), "--poses", str(log / "poses.csv"),
            "--video", *(f"{c}={p}" for c, p in video.items())]


def _no_extrinsics(tiny: Path, log: Path, tmp: Path) -> list[str]:
    (tmp / "calib").mkdir()
    for c in ("front", "rear", "left", "right"):
        (tmp / "calib" / f"{c}.yaml").write_bytes((log / "calib" / f"{c}.yaml").read_bytes())
    return ["--calib", str(tmp / "calib"), "--poses", str(log / "poses.csv"), "--images", str(log / "images")]


def _sfm_flags(tiny: Path, log: Path, tmp: Path) -> list[str]:
    return ["--calib", str(log / "calib"), "--poses", str(log / "poses.csv"), "--images", str(log / "images"),
            "--scale", "2", "--camera-height", "1.2"]


@pytest.mark.parametrize("spoil, message", [
    (_sfm_flags, "--scale, --camera-height apply to per-image (SfM) poses fitted to a rig; this recording has ego"),
    (_non_unit_quaternion, "poses.csv line 6: quaternion (qw, qx, qy, qz) = [1.2, "),
    (_decreasing_time, "poses.csv line 7: timestamp 0.35 does not follow 0.4; timestamps must increase strictly"),
    (_unreadable_video, "rear.mp4: cannot open the video (missing, unreadable or unsupported)"),
    (_no_extrinsics, "front.yaml: OpenCV fisheye YAML (camera_matrix, dist_coeffs, resolution) has no extrinsics"),
])
def test_bad_input_is_one_line_exit_2_and_nothing_written(tiny: Path, log: Path, tmp_path: Path, capsys, spoil,
                                                          message: str) -> None:
    args = spoil(tiny, log, tmp_path)
    capsys.readouterr()
    assert main(["import", "rig-log", *args, "-o", str(tmp_path / "out"), "--quiet"]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and message in err, err
    assert not (tmp_path / "out").exists() and not list(tmp_path.glob(".out*"))


def test_a_parksim_rig_file_is_a_whole_calibration(tiny: Path, log: Path) -> None:
    report = run(["import", "rig-log", "--calib", str(tiny / "rig.json"), "--poses", str(log / "poses.csv"),
                  "--images", str(log / "images")], log.parent / "from_rig")
    assert report["calibration_format"] == "parksim"
    assert DatasetReader(log.parent / "from_rig").rig.to_dict() == DatasetReader(tiny).rig.to_dict()
