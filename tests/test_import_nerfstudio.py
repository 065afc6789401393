"""nerfstudio transforms.json: export a dataset, import it back, against nerfstudio's own ray generation; bad input."""

from __future__ import annotations

import json
import math
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from parksim.cli import main
from parksim.data import DatasetReader
from parksim.importers.images import undistortion_maps
from parksim.importers.nerfstudio import Lens
from parksim.importers.recording import REPORT_FILE

TOL = 1e-9
"""float64 round trip of poses and intrinsics: JSON keeps every bit, so only the 0.5 px shift (one rounding,
~1e-14 px) and the rig fit's means over four cameras (~1e-14 m at 35 m) differ; 1e-9 leaves room for neither to
hide a convention error (a wrong pixel offset is 0.5 px, a wrong axis ~1)."""


@pytest.fixture(scope="module")
def tiny(tiny_data: Path) -> Path:
    """The session's ``parksim synth tiny`` (tests/conftest.py): read only."""
    return tiny_data


@pytest.fixture(scope="module")
def work(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """This module's folder for what it writes."""
    return tmp_path_factory.mktemp("ns")


@pytest.fixture(scope="module")
def exported(tiny: Path, work: Path) -> Path:
    out = work / "exported"
    assert main(["export", "nerfstudio", str(tiny), "-o", str(out)]) == 0
    return out


@pytest.fixture(scope="module")
def imported(tiny: Path, exported: Path, work: Path) -> Path:
    """The export imported back with the original rig as the known rig (its vehicle frame and scale)."""
    out = work / "imported"
    assert main(["import", "nerfstudio", str(exported), "-o", str(out), "--rig", str(tiny), "--quiet"]) == 0
    return out


def _meta(folder: Path) -> dict:
    return json.loads((folder / "transforms.json").read_text())


def _write_meta(folder: Path, meta: dict) -> None:
    (folder / "transforms.json").write_text(json.dumps(meta))


def _kb_theta(rho: np.ndarray, k: list[float]) -> np.ndarray:
    """Solve Kannala-Brandt ``theta (1 + k1 t^2 + k2 t^4 + k3 t^6 + k4 t^8) = rho`` by bisection."""
    lo, hi = np.zeros_like(rho), np.full_like(rho, 1.7)
    for _ in range(200):
        mid = (lo + hi) / 2
        t2 = mid * mid
        too_far = mid * (1 + t2 * (k[0] + t2 * (k[1] + t2 * (k[2] + t2 * k[3])))) > rho
        hi, lo = np.where(too_far, mid, hi), np.where(too_far, lo, mid)
    return (lo + hi) / 2


def _nerfstudio_rays(frame: dict, uv: np.ndarray) -> np.ndarray:
    """World ray directions of ParkSim pixels ``uv`` as nerfstudio's Cameras make them for OPENCV_FISHEYE:
    pixel centre at index + 0.5, ``((x - cx) / fx, (y - cy) / fy)``, Kannala-Brandt undistortion to theta, y
    flipped to OpenGL, direction ``(sin theta * x / r, sin theta * y / r, -cos theta)``, rotated by the c2w."""
    x = (uv[:, 0] + 0.5 - frame["cx"]) / frame["fl_x"]
    y = (uv[:, 1] + 0.5 - frame["cy"]) / frame["fl_y"]
    rho = np.hypot(x, y)
    theta = _kb_theta(rho, [frame[k] for k in ("k1", "k2", "k3", "k4")])
    d = np.stack([np.sin(theta) * x / rho, -np.sin(theta) * y / rho, -np.cos(theta)], 1)
    return d @ np.asarray(frame["transform_matrix"])[:3, :3].T


def test_export_gives_nerfstudio_the_same_rays_and_the_same_files(tiny: Path, exported: Path) -> None:
    reader, meta = DatasetReader(tiny), _meta(exported)
    assert meta["camera_model"] == "OPENCV_FISHEYE" and "fl_x" not in meta   # the synth cameras' centres differ
    assert len(meta["frames"]) == len(reader.frames) * len(reader.rig.names)
    for frame in meta["frames"]:
        camera, stem = Path(frame["file_path"]).parts[-2:]
        f = int(Path(stem).stem)
        model = reader.rig.cameras[camera].model
        uv = torch.stack(torch.meshgrid(torch.arange(0, 160, 7.0, dtype=torch.float64),
                                        torch.arange(0, 120, 7.0, dtype=torch.float64), indexing="xy"), -1)
        uv = uv.reshape(-1, 2)[model.pixel_valid(uv.reshape(-1, 2))]
        T = reader.camera_pose(camera, f)
        ours = (model.unproject(uv) @ T[:3, :3].T).numpy()
        assert np.abs(_nerfstudio_rays(frame, uv.numpy()) - ours).max() < TOL
        assert np.abs(np.asarray(frame["transform_matrix"])[:3, 3] - T[:3, 3].numpy()).max() == 0
        assert frame["time"] == reader.timestamps[reader.frames.index(f)]
        assert (exported / frame["file_path"]).read_bytes() == reader.layout.image(camera, f).read_bytes()
    test = {f"images/{c}/{f:06d}.png" for f in reader.split["test"] for c in reader.rig.names}
    assert set(meta["test_filenames"]) == set(meta["val_filenames"]) == test
    assert len(meta["train_filenames"]) == len(reader.split["train"]) * 4
    assert (exported / meta["ply_file_path"]).read_bytes() == reader.layout.points.read_bytes()


def test_round_trip_keeps_intrinsics_poses_pixels_and_the_rig(tiny: Path, imported: Path) -> None:
    a, b = DatasetReader(tiny), DatasetReader(imported)
    assert b.rig.names == a.rig.names and b.frames == a.frames and b.timestamps == a.timestamps
    assert b.split == a.split and b.has_camera_poses
    for c in a.rig.names:
        ma, mb = a.rig.cameras[c].model.to_dict(), b.rig.cameras[c].model.to_dict()
        assert ma.keys() == mb.keys() and ma["model"] == mb["model"] == "opencv_fisheye"
        assert all(abs(np.subtract(ma[k], mb[k])).max() <= TOL for k in ma if k != "model")
        assert (b.rig.cameras[c].T_vehicle_camera - a.rig.cameras[c].T_vehicle_camera).abs().max() < TOL
        for f in a.frames:
            assert (b.camera_pose(c, f) - a.camera_pose(c, f)).abs().max() < TOL
            assert np.array_equal(cv2.imread(str(b.layout.image(c, f)), cv2.IMREAD_UNCHANGED),
                                  cv2.imread(str(a.layout.image(c, f)), cv2.IMREAD_UNCHANGED))
    assert (b.poses - a.poses).abs().max() < TOL
    assert all(np.array_equal(p, q) for p, q in zip(a.points, b.points))
    report = json.loads((imported / REPORT_FILE).read_text())
    assert report["rig_consistent"] is True and report["poses"] == "ego and per-image"
    assert report["cameras_by"] == "parent folder" and report["dropped"] == 0


def test_without_a_known_rig_the_fit_recovers_the_rig_up_to_the_vehicle_frame(tiny: Path, exported: Path,
                                                                              work: Path) -> None:
    out = work / "free"
    assert main(["import", "nerfstudio", str(exported), "-o", str(out), "--quiet"]) == 0
    a, b = DatasetReader(tiny), DatasetReader(out)
    X = torch.linalg.inv(a.poses[0]) @ b.poses[0]           # the fit's vehicle frame in the original's
    assert (a.poses @ X - b.poses).abs().max() < TOL
    for c in a.rig.names:
        assert (torch.linalg.inv(X) @ a.rig.cameras[c].T_vehicle_camera - b.rig.cameras[c].T_vehicle_camera
                ).abs().max() < TOL
    assert json.loads((out / REPORT_FILE).read_text())["rig_consistent"] is True


def test_poses_that_no_rig_explains_import_per_image_and_train(tiny: Path, exported: Path, tmp_path: Path) -> None:
    src = tmp_path / "moved"
    shutil.copytree(exported, src)
    meta = _meta(src)
    for frame in meta["frames"]:
        if frame["file_path"].startswith("images/left/") and int(Path(frame["file_path"]).stem) >= 6:
            frame["transform_matrix"][0][3] += 0.3                # the left camera slips 30 cm half-way
    _write_meta(src, meta)
    out = tmp_path / "ds"
    assert main(["import", "nerfstudio", str(src), "-o", str(out), "--quiet"]) == 0
    report = json.loads((out / REPORT_FILE).read_text())
    assert report["rig_consistent"] is False and report["poses"] == "per-image only"
    assert "not consistent with a fixed rig" in report["rig_fit"]
    reader = DatasetReader(out)
    assert not reader.has_vehicle_poses
    moved = reader.camera_pose("left", 8) - DatasetReader(tiny).camera_pose("left", 8)
    assert abs(float(moved[0, 3]) - 0.3) < TOL and float(moved.abs().sum()) - 0.3 < TOL
    run = tmp_path / "run"
    assert main(["reconstruct", str(out), "-o", str(run), "--config", "tiny"]) == 0
    assert (run / "gaussians.ply").is_file()


def test_a_frame_missing_a_camera_is_dropped_and_counted(exported: Path, tmp_path: Path) -> None:
    src = tmp_path / "gap"
    shutil.copytree(exported, src)
    meta = _meta(src)
    meta["frames"] = [fr for fr in meta["frames"] if fr["file_path"] != "images/rear/000005.png"]
    _write_meta(src, meta)
    assert main(["import", "nerfstudio", str(src), "-o", str(tmp_path / "ds"), "--quiet"]) == 0
    report = json.loads((tmp_path / "ds" / REPORT_FILE).read_text())
    assert report["frames"] == 11 and report["dropped"] == 1
    assert report["dropped_by_reason"] == {"no image from camera(s) rear": 1}
    assert 5 not in DatasetReader(tmp_path / "ds").frames


def _no_file_path(src: Path, meta: dict) -> None:
    del meta["frames"][3]["file_path"]


def _nan_matrix(src: Path, meta: dict) -> None:
    meta["frames"][5]["transform_matrix"][1][3] = math.nan   # json.dumps writes NaN, which json.loads reads back


def _unknown_model(src: Path, meta: dict) -> None:
    meta["camera_model"] = "EQUIRECTANGULAR"


@pytest.mark.parametrize("spoil, message", [
    (_no_file_path, "frames[3]: no 'file_path'"),
    (_nan_matrix, "frames[5] (images/rear/000001.png): transform_matrix has non-finite values"),
    (_unknown_model, "camera_model 'EQUIRECTANGULAR' is not supported"),
])
def test_bad_input_is_one_line_exit_2_and_nothing_written(exported: Path, tmp_path: Path, capsys, spoil,
                                                          message: str) -> None:
    src = tmp_path / "src"
    shutil.copytree(exported, src)
    meta = _meta(src)
    spoil(src, meta)
    _write_meta(src, meta)
    capsys.readouterr()
    assert main(["import", "nerfstudio", str(src), "-o", str(tmp_path / "out"), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and message in err, err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["src"]


def test_export_refuses_a_lens_nerfstudio_lacks(tiny: Path, tmp_path: Path, capsys) -> None:
    data = tmp_path / "data"
    shutil.copytree(tiny, data)
    rig = json.loads((data / "rig.json").read_text())
    rig["cameras"]["rear"]["intrinsics"] = {"model": "radial_poly", "width": 160, "height": 120,
                                            "k": [45.0, 0.0, 0.0, 0.0], "cx_offset": 0.0, "cy_offset": 0.0,
                                            "aspect_ratio": 1.0, "max_fov_deg": 190.0}
    (data / "rig.json").write_text(json.dumps(rig))
    capsys.readouterr()
    assert main(["export", "nerfstudio", str(data), "-o", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "camera 'rear' is radial_poly" in err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["data"]


def _pattern(w: int, h: int, phase: float) -> np.ndarray:
    """A smooth colour pattern (bilinear resampling of it differs from cv2's only by rounding)."""
    v, u = np.mgrid[0:h, 0:w].astype(np.float64)
    rgb = [127 + 120 * np.sin(u / 9 + phase), 127 + 120 * np.cos(v / 7 - phase), 127 + 120 * np.sin((u + v) / 13)]
    return np.stack(rgb, -1).round().astype(np.uint8)


def test_distorted_perspective_cameras_are_undistorted_to_pinholes(tmp_path: Path) -> None:
    """Two OPENCV cameras in one folder (grouped by intrinsics), no time (frame / fps): pinhole cameras with the
    same focal length and centre, images resampled as cv2's own undistortion maps do it."""
    src = tmp_path / "ns"
    (src / "images").mkdir(parents=True)
    lenses = [{"fl_x": 50.0, "fl_y": 51.0, "cx": 40.5, "cy": 30.0, "k1": -0.2, "k2": 0.03, "p1": 0.002,
               "p2": -0.001},
              {"fl_x": 48.0, "fl_y": 48.0, "cx": 39.0, "cy": 31.5, "k1": -0.1, "k2": 0.0, "p1": 0.0, "p2": 0.0}]
    frames = []
    for f in (2, 4, 6):
        for i, lens in enumerate(lenses):
            name = f"images/cam{'ab'[i]}_{f:04d}.png"
            cv2.imwrite(str(src / name), cv2.cvtColor(_pattern(80, 60, f + i), cv2.COLOR_RGB2BGR))
            T = np.eye(4)
            T[:3, 3] = [0.5 * f, 0.2 * i, 1.0]
            frames.append({"file_path": name, "transform_matrix": T.tolist(), **lens})
    applied = [[0.0, 1.0, 0.0, 0.0], [1.0, 0.0, 0.0, 0.0], [0.0, 0.0, -1.0, 0.0]]   # as ns-process-data writes
    _write_meta(src, {"camera_model": "OPENCV", "w": 80, "h": 60, "applied_transform": applied, "frames": frames})
    out = tmp_path / "ds"
    assert main(["import", "nerfstudio", str(src / "transforms.json"), "-o", str(out), "--fps", "4",
                 "--quiet"]) == 0
    reader = DatasetReader(out)
    assert reader.rig.names == ["cam0", "cam1"] and reader.frames == [2, 4, 6]
    assert reader.timestamps == [0.5, 1.0, 1.5]
    report = json.loads((out / REPORT_FILE).read_text())
    assert report["cameras_by"] == "distinct intrinsics" and sorted(report["undistorted"]) == ["cam0", "cam1"]
    assert report["applied_transform"] == applied      # reported; the poses are already in the file's world
    assert torch.equal(reader.camera_pose("cam1", 4), torch.tensor(
        [[1.0, 0, 0, 2.0], [0, -1.0, 0, 0.2], [0, 0, -1.0, 1.0], [0, 0, 0, 1.0]], dtype=torch.float64))
    for c, lens in zip(reader.rig.names, lenses):
        model = reader.rig.cameras[c].model
        assert model.to_dict() == {"model": "pinhole", "width": 80, "height": 60, "fx": lens["fl_x"],
                                   "fy": lens["fl_y"], "cx": lens["cx"] - 0.5, "cy": lens["cy"] - 0.5,
                                   "max_fov_deg": 170.0}
        K = np.array([[lens["fl_x"], 0, lens["cx"] - 0.5], [0, lens["fl_y"], lens["cy"] - 0.5], [0, 0, 1]])
        D = np.array([lens["k1"], lens["k2"], lens["p1"], lens["p2"], 0.0])
        mx, my = cv2.initUndistortRectifyMap(K, D, None, K, (80, 60), cv2.CV_32FC1)
        distortion = Lens("OPENCV", 80, 60, lens["fl_x"], lens["fl_y"], lens["cx"], lens["cy"],
                          (lens["k1"], lens["k2"], 0.0, 0.0, lens["p1"], lens["p2"]), None).distortion_to_remove
        assert distortion is not None
        ours = undistortion_maps(distortion)
        assert max(np.abs(ours[0] - mx).max(), np.abs(ours[1] - my).max()) < 1e-3
        for f in reader.frames:
            source = _pattern(80, 60, f + reader.rig.names.index(c))
            expected = cv2.remap(source, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
            got = (reader.image(c, f).numpy() * 255).round().astype(np.int16)
            assert np.abs(got - expected).max() <= 1
