"""instant-ngp transforms.json: a synth dataset written in instant-ngp's layout imports back to the same cameras,
poses and images; the Blender-style variant (one camera_angle_x, extension-less paths) through the Python entry
point; bad input."""

from __future__ import annotations

import json
import math
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest

from parksim.cli import main
from parksim.data import DatasetReader
from parksim.importers import ImportSettings, import_recording
from parksim.importers.instant_ngp import InstantNgpOptions
from parksim.importers.recording import REPORT_FILE

TOL = 1e-9
"""float64 round trip: JSON keeps every bit; the 0.5 px shift and the rig fit's means over four cameras round at
~1e-14. A wrong pixel convention is 0.5 px, a wrong axis ~1."""
GL = np.diag([1.0, -1.0, -1.0, 1.0])
"""OpenCV camera axes (x right, y down, z forward) to OpenGL's (x right, y up, z back), and back."""
FPS = 10.0


@pytest.fixture(scope="module")
def tiny(tiny_data: Path) -> Path:
    """The session's ``parksim synth tiny`` (tests/conftest.py): read only."""
    return tiny_data


def _png(path: Path) -> np.ndarray:
    return cv2.imread(str(path), cv2.IMREAD_UNCHANGED)


def write_ngp(data: Path, out: Path) -> Path:
    """``data`` in instant-ngp's layout: images/<camera>/<frame>.png named without their extension, shared w, h,
    is_fisheye and the unit-cube keys at the top level, each camera's fl_x, fl_y, cx, cy, k1..k4 (instant-ngp's
    pixel centres at 0.5) and a sharpness per frame."""
    reader = DatasetReader(data)
    frames = []
    for f in reader.frames:
        for c in reader.rig.names:
            m = reader.rig.cameras[c].model
            rel = f"images/{c}/{f:06d}"
            (out / rel).parent.mkdir(parents=True, exist_ok=True)
            shutil.copyfile(reader.layout.image(c, f), out / f"{rel}.png")
            k = [float(v) for v in m.k]
            frames.append({"file_path": rel, "sharpness": 40.0 + f,
                           "transform_matrix": (reader.camera_pose(c, f).numpy() @ GL).tolist(),
                           "fl_x": float(m.fx), "fl_y": float(m.fy), "cx": float(m.cx) + 0.5,
                           "cy": float(m.cy) + 0.5, "k1": k[0], "k2": k[1], "k3": k[2], "k4": k[3]})
    meta = {"w": 160, "h": 120, "is_fisheye": True, "aabb_scale": 16, "scale": 0.33, "offset": [0.5, 0.5, 0.5],
            "frames": frames}
    (out / "transforms.json").write_text(json.dumps(meta, indent=1))
    return out


@pytest.fixture(scope="module")
def imported(tiny: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The instant-ngp copy of tiny imported through the CLI, with tiny's rig as the known rig."""
    work = tmp_path_factory.mktemp("ngp")
    src = write_ngp(tiny, work / "ngp")
    assert main(["import", "instant-ngp", str(src), "-o", str(work / "ds"), "--rig", str(tiny), "--quiet"]) == 0
    return work / "ds"


def test_round_trip_keeps_intrinsics_poses_and_images(tiny: Path, imported: Path) -> None:
    a, b = DatasetReader(tiny), DatasetReader(imported)
    assert b.rig.names == a.rig.names and b.frames == a.frames
    assert b.timestamps == pytest.approx([f / FPS for f in a.frames], abs=1e-12)   # instant-ngp has no times
    for c in a.rig.names:
        ma, mb = a.rig.cameras[c].model.to_dict(), b.rig.cameras[c].model.to_dict()
        assert ma.keys() == mb.keys() and ma["model"] == mb["model"] == "opencv_fisheye"
        assert all(np.abs(np.subtract(ma[k], mb[k])).max() <= TOL for k in ma if k != "model"), (ma, mb)
        assert (b.rig.cameras[c].T_vehicle_camera - a.rig.cameras[c].T_vehicle_camera).abs().max() < TOL
        for f in a.frames:
            assert (b.camera_pose(c, f) - a.camera_pose(c, f)).abs().max() < TOL
            assert np.array_equal(_png(b.layout.image(c, f)), _png(a.layout.image(c, f)))
    assert (b.poses - a.poses).abs().max() < TOL
    report = json.loads((imported / REPORT_FILE).read_text())
    assert report["importer"] == "instant-ngp" and report["rig_consistent"] is True
    assert report["camera_model"] == "OpenCV fisheye (is_fisheye)" and report["cameras_by"] == "parent folder"
    assert report["unit_cube"] == {"scale": 0.33, "offset": [0.5, 0.5, 0.5], "aabb_scale": 16}
    assert report["ignored"] == ["sharpness"] and report["focal_length_from"] == ["fl_x, fl_y"]


def _blender(tiny: Path, out: Path, angle: float, distortion: dict[str, float]) -> tuple[Path, list[int]]:
    """tiny's front camera as a Blender-style instant-ngp file: ./train/r_<frame> without extension, one top-level
    camera_angle_x and no w, h, cx, cy (both from the image), optional OpenCV distortion."""
    reader = DatasetReader(tiny)
    (out / "train").mkdir(parents=True)
    frames, ids = [], reader.frames[::3]
    for f in ids:
        shutil.copyfile(reader.layout.image("front", f), out / "train" / f"r_{f}.png")
        frames.append({"file_path": f"./train/r_{f}", "rotation": 0.0,
                       "transform_matrix": (reader.camera_pose("front", f).numpy() @ GL).tolist()})
    (out / "transforms.json").write_text(json.dumps({"camera_angle_x": angle, **distortion, "frames": frames}))
    return out, ids


@pytest.mark.parametrize("distortion", [{}, {"k1": -0.2, "k2": 0.03, "p1": 0.002, "p2": -0.001}])
def test_blender_style_file_through_the_python_entry_point(tiny: Path, tmp_path: Path,
                                                           distortion: dict[str, float]) -> None:
    """A pinhole with fx = fy = (w / 2) / tan(camera_angle_x / 2) centred on the image; OpenCV k1, k2, p1, p2
    undistorted as cv2's own undistortion maps do it."""
    angle = 1.2
    src, ids = _blender(tiny, tmp_path / "blender", angle, distortion)
    report = import_recording("instant-ngp", InstantNgpOptions(src, fps=5.0),
                              ImportSettings(tmp_path / "ds", test_every=0, quiet=True))
    assert report["frames"] == len(ids) and report["focal_length_from"] == ["camera_angle_x"]
    a, b = DatasetReader(tiny), DatasetReader(tmp_path / "ds")
    focal = 80.0 / math.tan(angle / 2)
    assert b.rig.names == ["cam0"] and b.frames == ids and b.timestamps == pytest.approx([f / 5 for f in ids])
    model = b.rig.cameras["cam0"].model.to_dict()
    assert model.pop("model") == "pinhole" and model.pop("max_fov_deg") == 170.0
    assert np.abs(np.subtract(list(model.values()), [160, 120, focal, focal, 79.5, 59.5])).max() < TOL, model
    for f in ids:
        assert (b.camera_pose("cam0", f) - a.camera_pose("front", f)).abs().max() < TOL
    K = np.array([[focal, 0, 79.5], [0, focal, 59.5], [0, 0, 1]])
    D = np.array([distortion.get(k, 0.0) for k in ("k1", "k2", "p1", "p2")] + [0.0])
    mx, my = cv2.initUndistortRectifyMap(K, D, None, K, (160, 120), cv2.CV_32FC1)
    for f in ids:
        source = cv2.cvtColor(_png(a.layout.image("front", f)), cv2.COLOR_BGR2RGB)
        expected = source if not distortion else cv2.remap(source, mx, my, cv2.INTER_LINEAR,
                                                           borderMode=cv2.BORDER_CONSTANT, borderValue=0)
        got = (b.image("cam0", f).numpy() * 255).round().astype(np.int16)
        assert np.abs(got - expected).max() <= (1 if distortion else 0)
    assert ("undistorted" in report) == bool(distortion)


def _ftheta(src: Path, meta: dict) -> None:
    meta["frames"][1]["ftheta_p0"] = 1.0


def _k3_perspective(src: Path, meta: dict) -> None:
    meta["k3"] = 0.01


def _no_focal(src: Path, meta: dict) -> None:
    del meta["camera_angle_x"]


@pytest.mark.parametrize("spoil, message", [
    (_ftheta, "frames[1] (./train/r_3.png): instant-ngp's FTheta lens is not supported"),
    (_k3_perspective, "k3, k4 belong to is_fisheye lenses"),
    (_no_focal, "frames[0] (./train/r_0.png): no focal length"),
])
def test_bad_input_is_one_line_exit_2_and_nothing_written(tiny: Path, tmp_path: Path, capsys, spoil,
                                                          message: str) -> None:
    src, _ = _blender(tiny, tmp_path / "src", 1.2, {})
    meta = json.loads((src / "transforms.json").read_text())
    spoil(src, meta)
    (src / "transforms.json").write_text(json.dumps(meta))
    capsys.readouterr()
    assert main(["import", "instant-ngp", str(src), "-o", str(tmp_path / "out"), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and message in err, err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["src"]
